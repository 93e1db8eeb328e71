"""``graphsfm reconstruct``: every stage in order (paper Figure 1).

Extract and match run when an image folder is given; a workspace whose database came from
``synth`` or from COLMAP starts at ``cluster``.  With one cluster (all images fit) the map
stage's models are the final ones and nothing is merged.  :func:`reconstruct` is the whole run
as the command line and :func:`sfm.reconstruct` start it: the executor and the recording
opened, every stage run, both closed.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from sfm.clustering.options import ClusterOptions
from sfm.core.options import OptionError, options_from, unknown_names
from sfm.execution.options import ExecutionOptions, make_executor
from sfm.execution.local import LocalExecutor
from sfm.execution.process_pool import start_pool_server
from sfm.execution.spare_cores import spare_cores
from sfm.features.options import ExtractOptions
from sfm.errors import InputError
from sfm.io.report import finish_run, read_report, start_run, update_report
from sfm.io.workspace import RECORDING, WorkspaceLock
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
    """Every stage in order on ``executor`` (default: local processes), the pipeline of the
    paper's Figure 1; returns the report."""
    workspace = Path(workspace)
    recorder = recorder or Recorder.disabled()
    if images is not None:
        run_extract(Path(images), workspace, options.extract, executor, recorder)
        run_match(workspace, options.match, executor, recorder)
    run_cluster(workspace, options.cluster, recorder)
    map_result = run_map(workspace, options.mapper, recorder, executor)
    if map_result.direct:  # one cluster: its models are the final ones, nothing to merge
        update_report(workspace, {}, {"merge": 0.0, "final_ba": 0.0})
    else:
        # the merge runs in this process while the local workers idle: its final BA's
        # split-sample test may use their cores (sfm.execution.spare_cores)
        local = executor is None or not executor.remote
        with spare_cores((executor or LocalExecutor()).workers - 1 if local else 0):
            run_merge(workspace, options.mapper, options.merge, recorder)
    return read_report(workspace)


def reconstruct(images: Path | None, workspace: Path, options: ReconstructOptions, command: str | None = None) -> dict:
    """The whole run: takes the workspace (``WORK/run.lock``), opens the executor and the
    recording (``WORK/recording.rrd``) that ``options`` ask for, runs every stage, closes both;
    returns the report (``command``: the command line it records)."""
    workspace = Path(workspace)
    if workspace.exists() and not workspace.is_dir():
        raise InputError(f"--workspace: {workspace} is a file, not a folder")
    workspace.mkdir(parents=True, exist_ok=True)
    with WorkspaceLock(workspace, command or "sfm.reconstruct"):
        if options.execution.executor == "local":
            start_pool_server()  # the worker processes' imports overlap the Rerun SDK's
        start_run(workspace, command, fresh=True, image_dir=str(Path(images).resolve()) if images else None)
        rec = options.recording
        recorder = Recorder(workspace / RECORDING, workspace, rec.spawn, rec) if rec.recording else Recorder.disabled()
        try:
            with recorder, make_executor(options.execution) as executor:
                run_reconstruct(workspace, images, options, executor, recorder)
        except BaseException:
            with contextlib.suppress(Exception):  # the error that stopped the run is the one to report
                finish_run(workspace, "failed")
            raise
        return finish_run(workspace, "finished")
