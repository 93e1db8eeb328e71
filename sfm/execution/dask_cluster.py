"""Running a stage's tasks on a Dask distributed cluster (the ``dist`` extra): other machines.

The same ``map`` as :class:`sfm.execution.local.LocalExecutor` (see there).  Only data travels:
tasks carry image bytes, feature arrays and cluster payloads, never paths (``remote = True``
tells the stages so), and the results come back to the client, which alone writes the
workspace, so no shared filesystem is needed.  ``scheduler=None`` starts a ``LocalCluster`` of
``workers`` single-threaded processes on this machine, kept for the whole run (extract, match
and map share it) and closed by :meth:`DaskExecutor.close`.

Failures are Dask's business, not a loop of ours: a task whose worker dies is rescheduled on
another worker by the scheduler; a task that raises is retried once (``retries=1``) and then
either stops the map or is reported in its :class:`~sfm.execution.local.TaskResult`, as the
caller asked.
"""

from __future__ import annotations

import logging
import uuid
import warnings
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from sfm.errors import InputError
from sfm.execution.local import TaskResult, run_task
from sfm.execution.process_pool import single_threaded, unguarded_call_site, usable_cores
from sfm.execution.logs import collect_records, replay

log = logging.getLogger(__name__)


def _remote_task(func: Callable[[Any], Any], item: Any, catch: bool, level: int) -> tuple[Any, str | None, str, list]:
    """Worker side: one task, single-threaded, tagged with the Dask worker's address, with the
    log records it made at ``level`` and above (``sfm.execution.logs``)."""
    from distributed import get_worker

    single_threaded()
    with collect_records(level) as records:
        value, error, _ = run_task(func, item, catch)
    return value, error, get_worker().address, records


class DaskExecutor:
    """Runs tasks on ``scheduler`` (``tcp://host:port``) or on a LocalCluster of ``workers``."""

    name = "dask"
    remote = True

    def __init__(self, scheduler: str | None = None, workers: int = 0) -> None:
        try:
            import distributed  # noqa: F401
        except ImportError as exc:
            raise InputError("--executor dask needs the dist extra: pip install 'graphsfm[dist]'") from exc
        if workers < 0:
            raise ValueError(f"workers must be >= 0 (0: one per core), got {workers}")
        site = unguarded_call_site() if scheduler is None else None
        if site is not None:
            raise InputError(f"{site} calls graphsfm outside `if __name__ == \"__main__\":`, which each worker of "
                             "a Dask LocalCluster would run again: put the call under that guard")
        self.scheduler = scheduler
        self.workers = workers or usable_cores()
        self.address: str | None = scheduler
        self._client = None
        self._cluster = None

    def client(self):
        """The Dask client, connecting (or starting the LocalCluster) on first use."""
        if self._client is None:
            from distributed import Client, LocalCluster

            if self.scheduler is None:
                self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
            try:
                self._client = Client(self.scheduler or self._cluster, timeout="30s")
            except OSError as exc:
                self.close()
                raise InputError(f"cannot reach the Dask scheduler at {self.scheduler}: {exc}") from exc
            self.address = self._client.scheduler.address
            log.info("dask: scheduler %s, %d workers", self.address, self.num_workers())
        return self._client

    def num_workers(self) -> int:
        return max(1, len(self.client().scheduler_info()["workers"]))

    def runs_in_process(self, num_items: int, max_workers: int = 0) -> bool:
        return False

    def map(self, func: Callable[[Any], Any], items: Iterable[Any], *, num_items: int | None = None,
            ordered: bool = True, errors: str = "raise", max_workers: int = 0) -> Iterator[TaskResult]:
        """``func`` over ``items`` on the cluster, at most two tasks per worker in flight (so
        large items are not all sent at once); ``max_workers`` is left to the cluster's size."""
        from distributed import as_completed

        if errors not in ("raise", "return"):
            raise ValueError(f"errors must be 'raise' or 'return', got {errors!r}")
        client = self.client()
        catch = errors == "return"
        level = logging.getLogger().getEffectiveLevel()
        window = 2 * self.num_workers()
        run_id = uuid.uuid4().hex[:8]  # task keys "sfm-<task>-<index>-<run>": readable on the dashboard
        source = enumerate(items)
        in_flight: dict = {}
        order: deque = deque()
        finished = as_completed()

        def submit_next() -> None:
            nxt = next(source, None)
            if nxt is None:
                return
            with warnings.catch_warnings():  # a payload is its task's data: it travels with the task
                warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
                key = f"sfm-{getattr(func, '__name__', 'task')}-{nxt[0]}-{run_id}"
                future = client.submit(_remote_task, func, nxt[1], catch, level, key=key, pure=False, retries=1)
            in_flight[future] = nxt[0]
            order.append(future)
            finished.add(future)

        for _ in range(window):
            submit_next()
        try:
            while in_flight:
                future = order.popleft() if ordered else next(finished)
                if not ordered:
                    order.remove(future)
                index = in_flight.pop(future)
                try:
                    value, error, worker, records = future.result()
                except Exception as exc:  # noqa: BLE001 - failed twice (retries=1)
                    if not catch:
                        raise
                    value, error, worker, records = None, f"{type(exc).__name__}: {exc}", "", []
                replay(records)
                submit_next()
                yield TaskResult(index, value, error, worker)
        finally:
            for future in in_flight:
                future.release()

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
