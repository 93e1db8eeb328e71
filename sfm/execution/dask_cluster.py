"""Work on a Dask distributed cluster (the ``dist`` extra): local SfM, feature extraction, matching.

Only data travels: local-SfM payloads (arrays, no paths) and local models; image *bytes* read by
the client for extraction, keypoints and descriptors for matching, and the arrays that come back.
The database stays on the client, which alone writes it, so no shared filesystem is needed.
``scheduler=None`` starts a ``LocalCluster`` of ``workers`` single-threaded processes, kept for the
whole run (extract, match and map share it) and closed by :meth:`DaskExecutor.close`.

Failures are Dask's business, not a loop of ours: a task whose worker dies is rescheduled on
another worker by the scheduler; a task that raises is retried once (``retries=1``) and then
reported as a failed cluster, and the run goes on without it.
"""

from __future__ import annotations

import logging
import os
import uuid
import warnings
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

from tqdm import tqdm

from sfm.execution.local import ClusterResult, map_cluster, payload_labels, payload_sizes
from sfm.mapper.payload import MapperInput, MapperOptions
from sfm.viz.recorder import Recorder

log = logging.getLogger(__name__)


def _single_threaded() -> None:
    """Each Dask worker runs one task at a time: OpenCV's and BLAS's own threads would fight."""
    import cv2

    cv2.setNumThreads(1)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - scikit-learn brings threadpoolctl
        pass


def _task(payload: MapperInput, options: MapperOptions):
    """Worker side: the pure local-SfM task, tagged with the Dask worker's address."""
    from distributed import get_worker

    models, _ = map_cluster(payload, options)
    return models, get_worker().address


def _call(func: Callable[[Any], Any], item: Any) -> Any:
    _single_threaded()
    return func(item)


class DaskExecutor:
    """Runs tasks on ``scheduler`` (``tcp://host:port``) or on a LocalCluster of ``workers``."""

    name = "dask"

    def __init__(self, scheduler: str | None = None, workers: int = 0) -> None:
        try:
            import distributed  # noqa: F401
        except ImportError as exc:
            from sfm.errors import InputError

            raise InputError("--executor dask needs the dist extra: pip install 'graphsfm[dist]'") from exc
        self.scheduler = scheduler
        self.workers = workers if workers > 0 else (os.cpu_count() or 1)
        self.address: str | None = scheduler
        self._client = None
        self._cluster = None

    # ------------------------------------------------------------------ connection
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
                from sfm.errors import InputError

                self.close()
                raise InputError(f"cannot reach the Dask scheduler at {self.scheduler}: {exc}") from exc
            self.address = self._client.scheduler.address
            log.info("dask: scheduler %s, %d workers", self.address, self.num_workers())
        return self._client

    def num_workers(self) -> int:
        return max(1, len(self.client().scheduler_info()["workers"]))

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

    # ------------------------------------------------------------------ work
    def imap(self, func: Callable[[Any], Any], items: Iterable[Any], window: int = 0) -> Iterator[Any]:
        """``map(func, items)`` on the cluster, results in order, at most ``window`` tasks in
        flight (default: two per worker), so large inputs (image bytes) are not all sent at once."""
        client = self.client()
        window = window or 2 * self.num_workers()
        pending: deque = deque()
        for item in items:
            pending.append(client.submit(_call, func, item, pure=False, retries=1))
            if len(pending) >= window:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()

    def run(self, payloads: Sequence[MapperInput], options: MapperOptions,
            recorder: Recorder | None = None) -> Iterator[ClusterResult]:
        """One :class:`ClusterResult` per payload as they finish; a failed task becomes an error."""
        from distributed import as_completed

        client = self.client()
        run_id = uuid.uuid4().hex[:8]
        sizes, labels = payload_sizes(payloads), payload_labels(payloads)
        pending = iter(sorted(range(len(payloads)), key=lambda k: -sizes[k]))  # largest first
        futures: dict = {}
        finished = as_completed()

        def submit_next() -> None:  # two payloads in flight per worker: each is read only then
            k = next(pending, None)
            if k is None:
                return
            with warnings.catch_warnings():  # a payload is its cluster's data: it travels with the task
                warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
                future = client.submit(_task, payloads[k], options, key=f"sfm-{labels[k]}-{run_id}", retries=1, pure=False)
            futures[future] = k
            finished.add(future)

        for _ in range(2 * self.num_workers()):
            submit_next()
        bar = tqdm(total=len(payloads), desc="local SfM (dask)", unit="cluster", disable=None)
        try:
            for future in finished:
                k = futures[future]
                submit_next()
                try:
                    models, worker = future.result()
                    yield ClusterResult(k, models, worker)
                except Exception as exc:  # noqa: BLE001 - a failed cluster is reported, not fatal
                    log.warning("cluster %s failed on dask: %s", labels[k], exc)
                    yield ClusterResult(k, [], "", f"{type(exc).__name__}: {exc}")
                bar.update()
        finally:
            bar.close()
            for future in futures:
                future.release()
