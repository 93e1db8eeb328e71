"""Local SfM of clusters on a Dask distributed cluster (the ``dist`` extra).

The same self-contained payloads as :class:`sfm.executors.LocalExecutor` travel to the workers
(pickled arrays, no paths), and the local models travel back; no shared filesystem is needed.
``scheduler=None`` starts a ``LocalCluster`` of ``workers`` single-threaded processes and closes
it afterwards.  Dask's own machinery handles a worker that dies (its tasks are rescheduled
elsewhere); a task that raises is retried once (``retries=1``) and then reported as a failed
cluster, and the run goes on without it.  We write no RPC, scheduler or retry loop of our own.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator, Sequence

from tqdm import tqdm

from sfm.executors import ClusterResult, map_cluster
from sfm.mapper_input import MapperInput, MapperOptions
from sfm.recording import Recorder

log = logging.getLogger(__name__)


def _task(payload: MapperInput, options: MapperOptions):
    """Worker side: the pure local-SfM task, tagged with the Dask worker's address."""
    from distributed import get_worker

    models, _ = map_cluster(payload, options)
    return models, get_worker().address


class DaskExecutor:
    """Runs payloads as Dask tasks on ``scheduler`` (``tcp://host:port``) or a LocalCluster."""

    name = "dask"

    def __init__(self, scheduler: str | None = None, workers: int = 0) -> None:
        try:
            import distributed  # noqa: F401
        except ImportError as exc:
            from sfm.errors import InputError

            raise InputError("--executor dask needs the dist extra: pip install 'graphsfm[dist]'") from exc
        import os

        self.scheduler = scheduler
        self.workers = workers if workers > 0 else (os.cpu_count() or 1)
        self.address: str | None = scheduler

    def run(self, payloads: Sequence[MapperInput], options: MapperOptions,
            recorder: Recorder | None = None) -> Iterator[ClusterResult]:
        from distributed import Client, LocalCluster, as_completed

        cluster = None
        if self.scheduler is None:
            cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        client = Client(self.scheduler or cluster)
        self.address = client.scheduler.address
        log.info("dask: scheduler %s, %d workers", self.address, len(client.scheduler_info()["workers"]))
        run_id = uuid.uuid4().hex[:8]
        try:
            order = sorted(range(len(payloads)), key=lambda k: -len(payloads[k].names))
            futures = {client.submit(_task, payloads[k], options, key=f"sfm-{payloads[k].label}-{run_id}",
                                     retries=1, pure=False): k for k in order}
            bar = tqdm(total=len(payloads), desc="local SfM (dask)", unit="cluster", disable=None)
            for future in as_completed(futures):
                k = futures[future]
                try:
                    models, worker = future.result()
                    yield ClusterResult(k, models, worker)
                except Exception as exc:  # noqa: BLE001 - a failed cluster is reported, not fatal
                    log.warning("cluster %s failed on dask: %s", payloads[k].label, exc)
                    yield ClusterResult(k, [], "", f"{type(exc).__name__}: {exc}")
                bar.update()
            bar.close()
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
