"""The program ``graphsfm`` (``sfm.__main__``): the supervised child starts the fork server of a
pooled command before it imports the command line, the raw command line says which commands
those are, the supervisor's stop line needs no valid arguments, and every process of a run
imports graphsfm's packages whatever the working directory holds."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import sfm

from sfm.__main__ import runs_local_pool
from sfm.cli import stopped
from sfm.core.progress import STATUS_FILE_ENV
from sfm.execution.process_pool import usable_cores


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["reconstruct", "--images", "photos", "--workspace", "w"], "cores"),
        (["-v", "map", "--workspace", "w"], "cores"),
        (["extract", "--workspace", "w", "--workers", "2"], "yes"),
        (["match", "--workspace", "w", "--workers=3", "--executor=local"], "yes"),
        (["map", "--workspace", "w", "--workers", "1"], "no"),
        (["map", "--workspace", "w", "--workers=1"], "no"),
        (["reconstruct", "--workspace", "w", "--executor", "dask"], "no"),
        (["reconstruct", "--workspace", "w", "--executor=dask", "--workers", "4"], "no"),
        (["cluster", "--workspace", "w"], "no"),
        (["export", "model", "out.ply"], "no"),
        (["reconstruct", "--help"], "no"),
        (["--version"], "no"),
        ([], "no"),
    ],
)
def test_which_command_lines_start_the_fork_server_early(argv, expected):
    """"cores": the default worker count, one per core: early on a machine of several."""
    assert runs_local_pool(argv) is {"yes": True, "no": False, "cores": usable_cores() > 1}[expected]


_ORDER = """
import sys
import sfm.execution.process_pool as process_pool
process_pool.start_pool_server = lambda: print("server started; command line imported:", "sfm.cli" in sys.modules)
from sfm.__main__ import main
sys.argv = ["graphsfm", *sys.argv[1:]]
code = main()
print("exit", code, "; command line imported:", "sfm.cli" in sys.modules)
"""


@pytest.mark.parametrize("workers, server", [("2", True), ("1", False)])
def test_the_child_starts_the_fork_server_before_importing_the_command_line(tmp_path, workers, server):
    env = dict(os.environ, **{STATUS_FILE_ENV: str(tmp_path / "status")})  # the supervised child's side
    done = subprocess.run([sys.executable, "-c", _ORDER, "map", "--workspace", str(tmp_path / "none"), "--workers",
                           workers], capture_output=True, text=True, env=env, timeout=120)
    lines = done.stdout.splitlines()
    assert lines[-1] == "exit 2 ; command line imported: True"  # no such workspace: a bad argument
    assert lines[:-1] == (["server started; command line imported: False"] if server else [])
    assert "no database at" in done.stderr


@pytest.mark.parametrize("module", ["sfm", "sfm.cli"])
def test_both_module_entries_run_the_program(module):
    done = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.startswith("graphsfm ")
    done = subprocess.run([sys.executable, "-m", module, "mapp"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "unknown command 'mapp'" in done.stderr and "did you mean" in done.stderr.lower()


def test_a_stop_before_the_arguments_were_refused_names_no_command(capsys):
    stopped(["mapp", "--workspace", "w"], signal.SIGINT, "start-up")
    assert capsys.readouterr().err == "graphsfm: stopped by Ctrl-C (SIGINT) during start-up\n"


def test_a_stop_names_the_command_and_says_a_rerun_resumes(tmp_path, capsys):
    stopped(["match", "--workspace", str(tmp_path / "not_made")], signal.SIGTERM, "match")
    assert capsys.readouterr().err == "graphsfm match: stopped by SIGTERM during match; rerun the same command to resume\n"


def test_the_child_freezes_the_heap_once_the_command_has_returned(tmp_path):
    """The shutdown's collections skip what is left of the command (``sfm.__main__``, 3.)."""
    code = ("import gc, sys; from sfm.__main__ import main; sys.argv = ['graphsfm', '--version']; "
            "print(gc.get_freeze_count() == 0); code = main(); print(code, gc.get_freeze_count() > 0)")
    env = dict(os.environ, **{STATUS_FILE_ENV: str(tmp_path / "status")})
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    before, version, after = done.stdout.splitlines()
    assert before == "True" and version.startswith("graphsfm ") and after == "0 True"


def test_a_users_own_sfm_and_backend_in_the_working_directory_are_not_imported(tmp_path):
    """graphsfm run where the user keeps an ``sfm`` or ``backend`` package of their own: the
    child, the fork server and the pool's workers all import graphsfm's."""
    import cv2
    import numpy as np

    for name in ("sfm", "backend"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise SystemExit('the working directory\\'s {name}')\n")
    images = tmp_path / "photos"
    images.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        cv2.imwrite(str(images / f"{i}.png"), cv2.GaussianBlur(rng.integers(0, 255, (240, 320), np.uint8), (5, 5), 0))
    root = str(Path(sfm.__file__).resolve().parents[1])
    program = f"import sys; sys.path.insert(0, {root!r}); from sfm.__main__ import main; sys.exit(main())"
    done = subprocess.run([sys.executable, "-c", program, "extract", "--images", "photos", "--workspace", "w",
                           "--workers", "2", "--no-recording"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "working directory" not in done.stderr + done.stdout
    assert "2 images extracted" in (tmp_path / "w" / "log.txt").read_text()
