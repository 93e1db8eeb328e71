"""Work a running task may hand to a core of this machine that no task uses.

When a stage runs its only task in this process (``map`` with one cluster: ``LocalExecutor``
with one item), the other workers' cores are idle.  :class:`LocalExecutor` says so while the
task runs (:func:`spare_cores`), and the task can start an independent piece of its work in a
process of its own (:func:`run_beside`) while it computes another piece itself: the principal
point's split-sample test has two bundle adjustments of half the images each
(``sfm.mapper.self_calibration``).  Anywhere else (a pool worker, a Dask worker, ``--workers 1``)
no core is spare and the piece runs in the caller, with the same result: the function is the
same and the side process forks from the pipeline's fork server (``sfm.execution.process_pool``)
with one thread, as pool workers do.  Should the side process fail, the caller computes the
piece itself.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from sfm.execution.process_pool import pool_context, single_threaded

log = logging.getLogger(__name__)

_SPARE = contextvars.ContextVar("spare_cores", default=0)


@contextlib.contextmanager
def spare_cores(count: int) -> Iterator[None]:
    """While the block runs, :func:`run_beside` may use ``count`` idle cores of this machine."""
    token = _SPARE.set(max(0, int(count)))
    try:
        yield
    finally:
        _SPARE.reset(token)


def run_beside(func: Callable[[Any], Any], item: Any, fits: bool = True) -> Callable[[], Any]:
    """Start ``func(item)`` in a process of its own when a core is spare (:func:`spare_cores`)
    and ``fits`` (the caller's word that memory holds this piece and its own at once); returns
    the function that gives its value, waiting for the process, or computing it here when no
    process ran it (no spare core, no room, or the process failed)."""
    if _SPARE.get() < 1 or not fits:
        return lambda: func(item)
    try:
        pool = ProcessPoolExecutor(1, mp_context=pool_context(), initializer=single_threaded)
        future = pool.submit(func, item)
    except Exception as exc:  # noqa: BLE001 - the caller computes it instead
        log.debug("no side process (%s): computed here", exc)
        return lambda: func(item)

    def result() -> Any:
        try:
            return future.result()
        except Exception as exc:  # noqa: BLE001 - a dead or failing side process: computed here
            log.debug("side process failed (%s: %s): computed here", type(exc).__name__, exc)
            return func(item)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    return result
