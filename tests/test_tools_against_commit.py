"""tools/bench_against_commit.py: the base side runs the code of the commit it names, not this
checkout's (the editable install and ``python -m``'s working directory must not win)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

pytestmark = pytest.mark.skipif(not (ROOT / ".git").exists(), reason="needs the git checkout")


def test_the_base_side_imports_the_exported_commit(tmp_path):
    from bench_against_commit import export_tree

    short = export_tree("HEAD", tmp_path / "base")
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=7", "HEAD"], capture_output=True, text=True)
    assert short == head.stdout.strip()
    committed = subprocess.run(["git", "-C", str(ROOT), "show", "HEAD:sfm/cli.py"], capture_output=True).stdout
    assert (tmp_path / "base" / "sfm" / "cli.py").read_bytes() == committed
    where = subprocess.run([sys.executable, "-c", "import sfm.cli, graph, backend; "
                            "print(sfm.cli.__file__, graph.__file__, backend.__file__)"],
                           env=dict(os.environ, PYTHONPATH=str(tmp_path / "base")), cwd=tmp_path,
                           capture_output=True, text=True, check=True).stdout.split()
    assert len(where) == 3 and all(Path(p).is_relative_to(tmp_path / "base") for p in where)


def test_each_side_runs_the_script_entry_point_its_own_pyproject_names(tmp_path):
    from bench_against_commit import export_tree, program

    export_tree("HEAD", tmp_path / "base")
    command = program("HEAD")
    assert command[:2] == [sys.executable, "-c"] and "sfm.__main__ import main" in command[2]
    done = subprocess.run([*command, "--version"], env=dict(os.environ, PYTHONPATH=str(tmp_path / "base")),
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.startswith("graphsfm ")
