"""The Python API: ``sfm.reconstruct(images, workspace, **options)`` and one function per stage.

Keyword options are the fields of the stages' option dataclasses (``ExtractOptions``,
``MatchOptions``, ``ClusterOptions``, ``MapperOptions``, ``MergeOptions``), the same names as the
command-line flags with underscores; a name no stage knows is an error, not a silent default.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from sfm.stages.cluster import ClusterOptions, run_cluster
from sfm.io.colmap_model import read_model
from sfm.stages.extract import ExtractOptions, run_extract
from sfm.mapper.payload import MapperOptions
from sfm.stages.map import run_map
from sfm.stages.match import MatchOptions, run_match
from sfm.merge.cluster_graph import MergeOptions
from sfm.core.model import Reconstruction
from sfm.stages.merge import ReconstructOptions, run_merge, run_reconstruct
from sfm.viz.recorder import Recorder

STAGE_OPTIONS = {"extract": ExtractOptions, "match": MatchOptions, "cluster": ClusterOptions,
                 "mapper": MapperOptions, "merge": MergeOptions}


def make_options(**options) -> ReconstructOptions:
    """Stage option dataclasses from keyword options (a field shared by several stages, such as
    ``seed``, goes to each of them)."""
    unknown = set(options)
    built = {}
    for stage, cls in STAGE_OPTIONS.items():
        names = {f.name for f in dataclasses.fields(cls)}
        built[stage] = cls(**{k: v for k, v in options.items() if k in names})
        unknown -= names
    if unknown:
        raise TypeError(f"unknown option(s): {', '.join(sorted(unknown))}")
    return ReconstructOptions(**built)


def reconstruct(images: str | Path | None, workspace: str | Path, workers: int = 0, recording: bool = True,
                executor: str = "local", scheduler: str | None = None,
                **options) -> tuple[list[Reconstruction], dict]:
    """Run every stage; return the final models (``WORK/sparse/N``, largest first) and the
    report.  ``images=None`` starts from an existing ``WORK/database.db``.  ``executor="dask"``
    runs extraction, matching and the clusters on Dask (``scheduler="tcp://host:port"``, or a
    LocalCluster of ``workers`` processes).

    >>> models, report = reconstruct("photos", "work", max_cluster_size=50, seed=0)  # doctest: +SKIP
    """
    from sfm.execution.local import LocalExecutor
    from sfm.execution.process_pool import start_pool_server

    if executor == "dask":
        from sfm.execution.dask_cluster import DaskExecutor

        runner = DaskExecutor(scheduler, workers)
    elif executor == "local" and scheduler is None:
        runner = LocalExecutor(workers)
    else:
        raise ValueError(f"executor must be 'local' or 'dask' (scheduler only with dask), got {executor!r}")
    workspace = Path(workspace)
    if executor == "local":
        start_pool_server()  # the worker processes' imports overlap the Rerun SDK's
    recorder = Recorder(workspace / "recording.rrd", workspace) if recording else Recorder.disabled()
    with recorder, runner:
        report = run_reconstruct(workspace, Path(images) if images is not None else None, make_options(**options),
                                 runner, recorder)
    sparse = workspace / "sparse"
    folders = sorted((d for d in sparse.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name))
    return [read_model(d) for d in folders], report


__all__ = ["reconstruct", "make_options", "run_extract", "run_match", "run_cluster", "run_map", "run_merge",
           "ExtractOptions", "MatchOptions", "ClusterOptions", "MapperOptions", "MergeOptions", "Reconstruction",
           "read_model"]
