"""The start method of this package's local process pools (extract, match, map), and the one
thread each of their workers runs (:func:`single_threaded`).

``forkserver`` where the platform has it: one server process imports the pipeline once
(``PRELOAD``), and every pool's workers are forked from it, so a pool starts with its imports
done instead of starting interpreters and importing OpenCV, NumPy and GTSAM in each worker, for
every stage, as a ``spawn`` pool does.  The server holds no threads of ours when it
forks (it is a fresh interpreter, not the caller), which is what makes forking safe with
OpenCV's and BLAS's thread pools.  ``spawn`` elsewhere (Windows).  Either way, scripts need the
``if __name__ == "__main__":`` guard.

Each worker also runs the caller's main module again (as ``__mp_main__``, so that functions
defined there unpickle).  The server's own ``"__main__"`` preload never happens on CPython
3.11 (``forkserver.ensure_running`` forwards a ``main_path`` key that
``spawn.get_preparation_data`` calls ``init_main_from_path``), so what that module imports
must already be in the server: ``PRELOAD`` holds ``sfm.api``, which imports every stage.  With
only the worker modules there, the workers of each pool of ``graphsfm reconstruct`` or of a
script importing ``sfm.api`` would import the rest again before their first task.
"""

from __future__ import annotations

import multiprocessing
import os
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
    goes on (e.g. importing the Rerun SDK), so the first pool forks from a ready server."""
    if pool_context().get_start_method() == "forkserver":
        from multiprocessing import forkserver

        forkserver.ensure_running()


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
