"""The local pools' fork server: workers find the pipeline imported when they re-run the
caller's main module (``sfm.execution.process_pool``)."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

MAIN = '''
import os, sys
if __name__ == "__mp_main__":  # a pool worker re-running this script
    with open(os.environ["OUT"], "a") as f:
        f.write(f"{os.getpid()} {'sfm.api' in sys.modules} {'gtsam' in sys.modules}\\n")
from concurrent.futures import ProcessPoolExecutor

def pid(_):
    return os.getpid()

if __name__ == "__main__":
    from sfm.execution.process_pool import pool_context
    for _ in range(2):  # two pools, as extract and match
        with ProcessPoolExecutor(2, mp_context=pool_context()) as pool:
            assert len(set(pool.map(pid, range(8)))) >= 1
'''


@pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(), reason="no forkserver here")
def test_pool_workers_start_with_the_pipeline_imported(tmp_path):
    """Each worker re-runs the main script; the modules a script or the CLI imports (``sfm.api``
    and through it GTSAM) are already there, preloaded by the server, so no pool waits for its
    workers to import them again."""
    script, out = tmp_path / "main_script.py", tmp_path / "workers.txt"
    script.write_text(MAIN)
    root = Path(__file__).resolve().parents[1]
    path = os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))
    env = dict(os.environ, OUT=str(out), PYTHONPATH=path)
    subprocess.run([sys.executable, str(script)], env=env, check=True, cwd=tmp_path, timeout=120)
    rows = [line.split() for line in out.read_text().splitlines()]
    assert len(rows) == 4  # two workers in each of two pools
    assert all(api == "True" and gtsam == "True" for _, api, gtsam in rows), rows
