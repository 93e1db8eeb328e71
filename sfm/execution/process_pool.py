"""The start method of this package's local process pools (extract, match, map), and the one
thread each of their workers runs (:func:`single_threaded`).

``forkserver`` where the platform has it: one server process imports the pipeline once
(``PRELOAD``), and every pool's workers are forked from it, so a pool starts with its imports
done instead of starting interpreters and importing OpenCV, NumPy and GTSAM in each worker, for
every stage, as a ``spawn`` pool does.  The server holds no threads of ours when it
forks (it is a fresh interpreter, not the caller), which is what makes forking safe with
OpenCV's and BLAS's thread pools.  ``spawn`` elsewhere (Windows).  Either way, scripts need the
``if __name__ == "__main__":`` guard: :func:`unguarded_call_site` finds a script that calls
graphsfm outside it; the local executor then runs its tasks in the script's own process, and a
Dask LocalCluster refuses to start.

Each worker also runs the caller's main module again (as ``__mp_main__``, so that functions
defined there unpickle).  The server's own ``"__main__"`` preload never happens on CPython
3.11 (``forkserver.ensure_running`` forwards a ``main_path`` key that
``spawn.get_preparation_data`` calls ``init_main_from_path``), so what that module imports
must already be in the server: ``PRELOAD`` holds ``sfm.api``, which imports every stage.  With
only the worker modules there, the workers of each pool of ``graphsfm reconstruct`` or of a
script importing ``sfm.api`` would import the rest again before their first task.
"""

from __future__ import annotations

import ast
import functools
import multiprocessing
import os
import sys
from multiprocessing.context import BaseContext

# "__main__" is multiprocessing's own default preload: the caller's functions can be pickled.
PRELOAD = ["__main__", "sfm.api"]


def pool_context() -> BaseContext:
    """The multiprocessing context every local pool of the pipeline uses (see module docstring)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


def start_pool_server() -> None:
    """Start the fork server now: it imports ``PRELOAD`` in its own process while the caller
    goes on (e.g. importing the Rerun SDK), so the first pool forks from a ready server.  Not
    for a script that no pool will serve (:func:`unguarded_call_site`)."""
    if pool_context().get_start_method() == "forkserver" and unguarded_call_site() is None:
        from multiprocessing import forkserver

        forkserver.ensure_running()


def unguarded_call_site() -> str | None:
    """Where the running script calls graphsfm from its top-level code outside an
    ``if __name__ == "__main__":`` block (``"run.py, line 3"``), or None.

    Each worker of a forkserver or spawn pool (and of a Dask LocalCluster) runs the caller's main
    module again before its first task; such a call would then run again inside every worker,
    which dies with it.  None when the main module is not a file (an interactive session, a
    notebook), is a package's ``__main__`` (which multiprocessing never runs again: ``python -m
    pytest``, graphsfm's own program), or the call does not come from its top-level code."""
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None)
    path = getattr(main, "__file__", None)
    if main is None or not path or (name is not None and (name == "__main__" or name.endswith(".__main__"))):
        return None
    frame = sys._getframe(1)
    while frame is not None and not (frame.f_globals is vars(main) and frame.f_code.co_name == "<module>"):
        frame = frame.f_back
    if frame is None:
        return None
    line = frame.f_lineno
    return None if _guarded(os.path.abspath(path), line) else f"{os.path.basename(path)}, line {line}"


@functools.lru_cache(maxsize=8)
def _guarded(path: str, line: int) -> bool:
    """Whether ``line`` of the script ``path`` is inside the body of a top-level ``if __name__
    == "__main__":`` (either order of the comparison); True when the source cannot be read."""
    try:
        with open(path, "rb") as f:
            tree = ast.parse(f.read())
    except (OSError, SyntaxError, ValueError):
        return True
    return is_guarded_line(tree, line)


def is_guarded_line(tree: ast.Module, line: int) -> bool:
    """Whether ``line`` lies in the body of a top-level ``if`` whose test compares ``__name__``
    with ``"__main__"`` (the code a worker process running the module again skips)."""
    for stmt in tree.body:
        if not isinstance(stmt, ast.If) or not stmt.body:
            continue
        if stmt.body[0].lineno <= line <= (stmt.body[-1].end_lineno or stmt.body[-1].lineno) and any(
                isinstance(node, ast.Compare) and _compares_name_with_main(node) for node in ast.walk(stmt.test)):
            return True
    return False


def _compares_name_with_main(node: ast.Compare) -> bool:
    sides = [node.left, *node.comparators]
    return (all(isinstance(op, ast.Eq) for op in node.ops)
            and any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides)
            and any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides))


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, which a container or ``taskset``
    makes fewer than the machine's): what ``--workers 0``, one worker per core, means."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def single_threaded() -> None:
    """Limit OpenCV's and BLAS's thread pools to one thread in this process: each worker runs
    one task, and several workers' thread pools would fight over the cores."""
    import cv2

    cv2.setNumThreads(1)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - scikit-learn brings threadpoolctl
        pass
