"""Running a stage's independent tasks on this machine, in a process pool.

Every parallel stage (extract: one task per image; match: one per batch of pairs; map: one per
cluster, the paper's "local SfM in parallel", section 3.2) hands its tasks to an executor's
:meth:`~LocalExecutor.map`.  Two executors implement it: :class:`LocalExecutor` (this machine)
and :class:`sfm.execution.dask_cluster.DaskExecutor` (a Dask cluster, other machines).  What a
stage needs to know of where its tasks run is one attribute, ``remote``: remote workers cannot
read this machine's files, so their tasks must carry their data (image bytes, feature arrays)
instead of paths.

``map(func, items, ordered=..., errors=..., max_workers=...)`` yields one :class:`TaskResult` per
item: in input order (``ordered=True``: extraction and matching write the database in a fixed
order, so any number of workers gives the same files) or as tasks finish.  At most two tasks
per worker are in flight, so lazily built items (image bytes, cluster payloads) are built only
when a worker is about to need them.  A map that runs its tasks in this process lends the other
workers' cores to them (``sfm.execution.spare_cores``).  A task that raises either stops the map
(``errors="raise"``) or becomes a :class:`TaskResult` with its ``error`` (``errors="return"``: a
failed cluster must not stop the others).  A worker process that dies (killed by the kernel for
memory, say) raises :class:`WorkerDied`.

Each worker process runs one task at a time with OpenCV's and BLAS's own threads limited to one
(``sfm.execution.process_pool.single_threaded``): the parallelism is across processes.  Its log messages and progress
events reach this process as they are made (``sfm.execution.logs``).  One worker runs the
tasks in this process, and so does a script that calls graphsfm outside ``if __name__ ==
"__main__":`` (``sfm.execution.process_pool.unguarded_call_site``), with a warning that says
where: every worker would run that call again.
"""

from __future__ import annotations

import logging
import os
import socket
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from sfm.execution.logs import DETAILS, forwarded_logs, init_worker
from sfm.execution.process_pool import pool_context, single_threaded, unguarded_call_site, usable_cores
from sfm.execution.spare_cores import spare_cores

log = logging.getLogger(__name__)
_WARNED: set[str] = set()  # the unguarded call sites already warned of


@dataclass
class TaskResult:
    """The outcome of one task: its position in the input, its value (None when it failed),
    the error that stopped it (``"ExceptionType: message"``, with ``errors="return"``) and the
    worker that ran it (``host:pid`` here, the worker's address on Dask)."""

    index: int
    value: Any = None
    error: str | None = None
    worker: str = ""


class WorkerDied(RuntimeError):
    """A worker process died while running tasks (killed by the kernel, say for memory)."""


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _init_pool_worker(queue, level: int) -> None:
    """A local pool worker: its logs go to the parent (``sfm.execution.logs``), one thread."""
    init_worker(queue, level)
    single_threaded()


def run_task(func: Callable[[Any], Any], item: Any, catch: bool) -> tuple[Any, str | None, str]:
    """``func(item)`` as ``(value, error, worker)``: with ``catch``, an exception becomes its
    one-line description (details in the log) instead of propagating."""
    if not catch:
        return func(item), None, worker_name()
    try:
        return func(item), None, worker_name()
    except Exception as exc:  # noqa: BLE001 - reported as this task's failure
        logging.getLogger(DETAILS).info("task failed\n%s", traceback.format_exc())
        return None, f"{type(exc).__name__}: {exc}", worker_name()


class LocalExecutor:
    """Runs tasks in a pool of ``workers`` processes on this machine (0: one per core), or in
    this process when one worker is enough."""

    name = "local"
    remote = False
    address = None

    def __init__(self, workers: int = 0) -> None:
        if workers < 0:
            raise ValueError(f"workers must be >= 0 (0: one per core), got {workers}")
        self.workers = workers or usable_cores()
        site = unguarded_call_site() if self.workers > 1 else None
        if site is not None:
            if site not in _WARNED:
                _WARNED.add(site)
                log.warning("%s calls graphsfm outside `if __name__ == \"__main__\":`, which every worker "
                            "process would run again: running in this process only; put the call under that "
                            "guard to use %d workers", site, self.workers)
            self.workers = 1

    def runs_in_process(self, num_items: int, max_workers: int = 0) -> bool:
        """Whether :meth:`map` of ``num_items`` items would run them in this process."""
        return self._pool_size(num_items, max_workers) <= 1

    def _pool_size(self, num_items: int, max_workers: int) -> int:
        return min(self.workers, max_workers or self.workers, max(num_items, 1))

    def map(self, func: Callable[[Any], Any], items: Iterable[Any], *, num_items: int | None = None,
            ordered: bool = True, errors: str = "raise", max_workers: int = 0) -> Iterator[TaskResult]:
        """``func`` over ``items`` (module docstring).  ``num_items``: how many items there are,
        when ``items`` has no ``len``."""
        if errors not in ("raise", "return"):
            raise ValueError(f"errors must be 'raise' or 'return', got {errors!r}")
        count = len(items) if num_items is None else num_items  # type: ignore[arg-type]
        catch = errors == "return"
        size = self._pool_size(count, max_workers)
        if size <= 1:
            for index, item in enumerate(items):
                with spare_cores(self.workers - 1):  # the other workers' cores idle meanwhile
                    value, error, worker = run_task(func, item, catch)
                yield TaskResult(index, value, error, worker)
            return
        context = pool_context()
        with forwarded_logs(context) as (queue, level):
            pool = ProcessPoolExecutor(size, mp_context=context, initializer=_init_pool_worker,
                                       initargs=(queue, level))
            finished = False
            try:
                yield from _pooled(pool, func, items, 2 * size, ordered, catch)
                finished = True
            except BrokenProcessPool as exc:
                raise WorkerDied("a worker process died (out of memory?)") from exc
            finally:
                pool.shutdown(wait=finished, cancel_futures=True)

    def close(self) -> None:
        """Nothing to close: each :meth:`map` opens and closes its own pool."""

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _pooled(pool: ProcessPoolExecutor, func, items: Iterable[Any], window: int, ordered: bool,
            catch: bool) -> Iterator[TaskResult]:
    """Submit ``items`` with at most ``window`` in flight; yield results in input order or as
    they finish."""
    source = enumerate(items)
    in_flight: dict = {}
    order: deque = deque()

    def submit_next() -> bool:
        nxt = next(source, None)
        if nxt is None:
            return False
        future = pool.submit(run_task, func, nxt[1], catch)
        in_flight[future] = nxt[0]
        order.append(future)
        return True

    while len(in_flight) < window and submit_next():
        pass
    while in_flight:
        if ordered:
            future = order.popleft()
            future.result()  # wait for the oldest
            done = [future]
        else:
            done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
        for future in done:
            index = in_flight.pop(future)
            if not ordered:
                order.remove(future)
            value, error, worker = future.result()
            submit_next()
            yield TaskResult(index, value, error, worker)
