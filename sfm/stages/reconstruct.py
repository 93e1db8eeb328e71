"""``graphsfm reconstruct``: every stage in order (paper Figure 1).

Extract and match run when an image folder is given; a workspace whose database came from
``synth`` or from COLMAP starts at ``cluster``.  With one cluster (all images fit) the map
stage's models are the final ones and nothing is merged.  :func:`reconstruct` is the whole run
as the command line and :func:`sfm.reconstruct` start it: the executor and the recording
opened, every stage run, both closed.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

from sfm.clustering.options import ClusterOptions
from sfm.core.options import OptionError, options_from, unknown_names
from sfm.execution.options import ExecutionOptions, make_executor
from sfm.execution.process_pool import start_pool_server
from sfm.features.options import ExtractOptions
from sfm.io.workspace import RECORDING, REPORT, read_json, update_report
from sfm.mapper.options import MapperOptions
from sfm.matching.options import MatchOptions
from sfm.merge.options import MergeOptions
from sfm.stages.cluster import run_cluster
from sfm.stages.extract import run_extract
from sfm.stages.map import run_map
from sfm.stages.match import run_match
from sfm.stages.merge import run_merge
from sfm.viz.options import RecordingOptions
from sfm.viz.recorder import Recorder


@dataclass(frozen=True)
class ReconstructOptions:
    """The options of every stage, and where and how the run goes."""

    extract: ExtractOptions = field(default_factory=ExtractOptions)
    match: MatchOptions = field(default_factory=MatchOptions)
    cluster: ClusterOptions = field(default_factory=ClusterOptions)
    mapper: MapperOptions = field(default_factory=MapperOptions)
    merge: MergeOptions = field(default_factory=MergeOptions)
    execution: ExecutionOptions = field(default_factory=ExecutionOptions)
    recording: RecordingOptions = field(default_factory=RecordingOptions)

    @classmethod
    def from_values(cls, values: dict) -> ReconstructOptions:
        """Every part built from the keyword values that are its fields (a name shared by several
        parts, such as ``seed``, goes to each); a name no part knows is an :class:`OptionError`."""
        parts = {f.name: f.default_factory for f in dataclasses.fields(cls)}  # type: ignore[misc]
        known = {n for make in parts.values() for n in (f.name for f in dataclasses.fields(make))}
        unknown = set(values) - known
        if unknown:
            raise OptionError(sorted(unknown)[0], f"unknown option {unknown_names(unknown, known)}")
        return cls(**{name: options_from(make, values) for name, make in parts.items()})


def run_reconstruct(workspace: Path, images: Path | None, options: ReconstructOptions,
                    executor=None, recorder: Recorder | None = None) -> dict:
    """Every stage in order on ``executor`` (default: local processes); returns the report."""
    workspace = Path(workspace)
    recorder = recorder or Recorder.disabled()
    if images is not None:
        t0 = time.perf_counter()
        run_extract(Path(images), workspace, options.extract, executor, recorder)
        t1 = time.perf_counter()
        run_match(workspace, options.match, executor, recorder)
        update_report(workspace, {"image_dir": str(images)}, {"T_feat": t1 - t0, "T_match": time.perf_counter() - t1})
    t0 = time.perf_counter()
    cluster_result = run_cluster(workspace, options.cluster, recorder)
    update_report(workspace, {"num_clusters": cluster_result.num_clusters}, {"T_GC": time.perf_counter() - t0})
    map_result = run_map(workspace, options.mapper, recorder, executor)
    if map_result.direct:  # one cluster: its models are the final ones, nothing to merge
        update_report(workspace, {}, {"T_merge": 0.0, "T_BA": 0.0})
    else:
        run_merge(workspace, options.mapper, options.merge, recorder)
    return read_json(workspace / REPORT)


def reconstruct(images: Path | None, workspace: Path, options: ReconstructOptions) -> dict:
    """The whole run: opens the executor and the recording (``WORK/recording.rrd``) that
    ``options`` ask for, runs every stage, closes both; returns the report."""
    workspace = Path(workspace)
    if options.execution.executor == "local":
        start_pool_server()  # the worker processes' imports overlap the Rerun SDK's
    rec = options.recording
    recorder = Recorder(workspace / RECORDING, workspace, rec.spawn, rec) if rec.recording else Recorder.disabled()
    with recorder, make_executor(options.execution) as executor:
        return run_reconstruct(workspace, images, options, executor, recorder)
