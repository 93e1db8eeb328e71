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


SCRIPT = '''
import os, sys
from pathlib import Path
with open(os.environ["OUT"], "a") as f:  # every process that runs this script's top level
    f.write(f"{__name__}\\n")
from sfm.execution.local import LocalExecutor
from sfm.stages.extract import run_extract
{call}
'''
CALL = 'run_extract(Path("photos"), Path("w"), executor=LocalExecutor(2))'


def _run_script(tmp_path: Path, body: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    import cv2
    import numpy as np

    images = tmp_path / "photos"
    images.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(2):
        cv2.imwrite(str(images / f"{i}.png"), cv2.GaussianBlur(rng.integers(0, 255, (240, 320), np.uint8), (5, 5), 0))
    script, out = tmp_path / "user_script.py", tmp_path / "runs.txt"
    script.write_text(SCRIPT.replace("{call}", body))
    root = Path(__file__).resolve().parents[1]
    path = os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))
    done = subprocess.run([sys.executable, str(script)], env=dict(os.environ, OUT=str(out), PYTHONPATH=path),
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    return done, out.read_text().split()


@pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(), reason="no forkserver here")
def test_a_script_calling_outside_the_main_guard_runs_in_its_own_process_and_says_where(tmp_path):
    """Without the guard every worker would run the script's call again and die with it (the
    run then failed with "a worker died"): the tasks run in the script's process, and one
    warning names the line."""
    done, runs = _run_script(tmp_path, CALL)
    assert done.returncode == 0, done.stderr[-2000:]
    assert runs == ["__main__"]  # no worker ran the script
    assert done.stderr.count("user_script.py, line 8 calls graphsfm outside") == 1, done.stderr
    assert len(list((tmp_path / "w").glob("database.db"))) == 1


@pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(), reason="no forkserver here")
def test_a_guarded_script_keeps_its_pool(tmp_path):
    done, runs = _run_script(tmp_path, f'if "__main__" == __name__:\n    {CALL}\n')
    assert done.returncode == 0, done.stderr[-2000:]
    assert runs.count("__main__") == 1 and runs.count("__mp_main__") >= 2  # the pool's workers ran its top level
    assert "outside" not in done.stderr


@pytest.mark.parametrize("source, line, guarded", [
    ('import sfm\nsfm.reconstruct("p", "w")\n', 2, False),
    ('import sfm\nif __name__ == "__main__":\n    sfm.reconstruct("p", "w")\n', 3, True),
    ("import sfm\nif '__main__' == __name__ and True:\n    x = 1\n    sfm.reconstruct(\n        'p', 'w')\n", 5, True),
    ('if __name__ == "__main__":\n    pass\nelse:\n    main()\n', 4, False),  # the else branch runs in workers
    ('if __name__ != "__main__":\n    main()\n', 2, False),
    ('def main():\n    pass\nif __name__ == "__main__":\n    main()\nmain()\n', 5, False),
])
def test_which_lines_the_main_guard_covers(source, line, guarded):
    import ast

    from sfm.execution.process_pool import is_guarded_line

    assert is_guarded_line(ast.parse(source), line) is guarded


def test_a_dask_local_cluster_refuses_an_unguarded_script(tmp_path):
    pytest.importorskip("distributed")
    done, runs = _run_script(tmp_path, "from sfm.execution.dask_cluster import DaskExecutor\nDaskExecutor(workers=2)")
    assert done.returncode == 1
    assert 'user_script.py, line 9 calls graphsfm outside `if __name__ == "__main__":`' in done.stderr
    assert runs == ["__main__"]
