"""Executors: where each cluster's local SfM runs (DESIGN.md, "Execution").

A cluster's local SfM is the pure function :func:`map_cluster`: a self-contained
:class:`~sfm.mapper.payload.MapperInput` payload (no paths into the caller's disk) in, local models
out.  :class:`LocalExecutor` runs payloads in a process pool (workers = cores by default) with a
progress bar; one worker runs in-process so the Rerun recording can show the model growing.  A
distributed executor (Dask) implements the same ``run`` interface.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass

from tqdm import tqdm

from sfm.mapper.incremental import reconstruct_incremental
from sfm.mapper.payload import MapperInput, MapperOptions
from sfm.core.model import Reconstruction
from sfm.execution.process_pool import pool_context
from sfm.viz.recorder import Recorder

log = logging.getLogger(__name__)


@dataclass
class ClusterResult:
    """Local models of one payload (largest first), where it ran, or the error that stopped it."""

    index: int
    models: list[Reconstruction]
    worker: str
    error: str | None = None


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def map_cluster(payload: MapperInput, options: MapperOptions) -> tuple[list[Reconstruction], str]:
    """The pure local-SfM task: payload -> (models, worker).  Safe in any worker process."""
    import cv2

    cv2.setNumThreads(1)
    return reconstruct_incremental(payload, options), worker_name()


class LocalExecutor:
    """Runs payloads on this machine: in-process for one worker, else a process pool."""

    name = "local"

    def __init__(self, workers: int = 0) -> None:
        self.workers = workers if workers > 0 else (os.cpu_count() or 1)

    def close(self) -> None:
        """Nothing to close: each ``run`` opens and closes its own pool."""

    def __enter__(self) -> LocalExecutor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run(self, payloads: Sequence[MapperInput], options: MapperOptions,
            recorder: Recorder | None = None) -> Iterator[ClusterResult]:
        """Yield one :class:`ClusterResult` per payload as they finish (any order)."""
        bar = tqdm(total=len(payloads), desc="local SfM", unit="cluster", disable=None)
        if self.workers == 1 or len(payloads) == 1:
            for k, payload in enumerate(payloads):
                try:
                    models = reconstruct_incremental(payload, options, recorder)
                    yield ClusterResult(k, models, worker_name())
                except Exception as exc:  # noqa: BLE001 - one failed cluster must not stop the run
                    log.warning("cluster %s failed: %s", payload.label, exc)
                    yield ClusterResult(k, [], worker_name(), f"{type(exc).__name__}: {exc}")
                bar.update()
            bar.close()
            return
        # Largest payloads first, so the pool is not left waiting on one big straggler; one
        # payload queued ahead per worker (each is read and pickled only then: memory).
        sizes, labels = payload_sizes(payloads), payload_labels(payloads)
        pending = iter(sorted(range(len(payloads)), key=lambda k: -sizes[k]))
        with ProcessPoolExecutor(max_workers=min(self.workers, len(payloads)), mp_context=pool_context()) as pool:
            futures: dict = {}

            def submit_next() -> None:
                k = next(pending, None)
                if k is not None:
                    futures[pool.submit(map_cluster, payloads[k], options)] = k

            for _ in range(2 * self.workers):
                submit_next()
            while futures:
                done, _ = wait(futures, return_when=FIRST_COMPLETED)
                for future in done:
                    k = futures.pop(future)
                    submit_next()
                    try:
                        models, worker = future.result()
                        yield ClusterResult(k, models, worker)
                    except Exception as exc:  # noqa: BLE001
                        log.warning("cluster %s failed: %s", labels[k], exc)
                        yield ClusterResult(k, [], "", f"{type(exc).__name__}: {exc}")
                    bar.update()
        bar.close()


def payload_sizes(payloads: Sequence[MapperInput]) -> list[int]:
    """Images per payload, without reading a lazy sequence (``sfm.stages.map.ClusterPayloads``)."""
    sizes = getattr(payloads, "sizes", None)
    return list(sizes) if sizes is not None else [len(p.names) for p in payloads]


def payload_labels(payloads: Sequence[MapperInput]) -> list[str]:
    labels = getattr(payloads, "labels", None)
    return list(labels) if labels is not None else [p.label for p in payloads]
