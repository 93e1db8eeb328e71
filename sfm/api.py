"""The Python API: ``sfm.reconstruct(images, workspace, **options)``, ``sfm.extend(workspace,
images, **options)`` (new photos added to a finished model), one function per stage, and
what to do with a model: ``sfm.export`` (COLMAP, PLY, undistorted images, nerfstudio),
``sfm.info`` (a summary) and ``sfm.align`` (onto GPS or reference positions).

Keyword options are the fields of the option dataclasses (``ExtractOptions``, ``MatchOptions``,
``ClusterOptions``, ``MapperOptions``, ``MergeOptions``, ``ExecutionOptions``,
``RecordingOptions``): the command-line flags with underscores for dashes.  A name no stage
knows, or a value an option does not allow, raises :class:`sfm.core.options.OptionError` (a
``ValueError``) before any work starts.
"""

from __future__ import annotations

from pathlib import Path

from sfm.clustering.options import ClusterOptions
from sfm.core.model import Reconstruction
from sfm.evaluation.options import AlignOptions
from sfm.io.colmap_model import read_model
from sfm.io.options import ExportOptions
from sfm.io.workspace import numbered_folders
from sfm.execution.options import ExecutionOptions
from sfm.features.options import ExtractOptions
from sfm.mapper.options import MapperOptions
from sfm.matching.options import MatchOptions
from sfm.merge.options import ExtendOptions, MergeOptions
from sfm.stages.cluster import run_cluster
from sfm.stages.extract import run_extract
from sfm.stages.map import run_map
from sfm.stages.match import run_match
from sfm.stages.merge import run_merge
from sfm.stages.extend import ExtendRunOptions
from sfm.stages.extend import extend as _extend
from sfm.stages.model_tools import align, export, info
from sfm.stages.reconstruct import ReconstructOptions
from sfm.stages.reconstruct import reconstruct as _run
from sfm.viz.options import RecordingOptions


def make_options(**options) -> ReconstructOptions:
    """Every stage's options from keyword options (a field shared by several stages, such as
    ``seed``, goes to each of them)."""
    return ReconstructOptions.from_values(options)


def reconstruct(images: str | Path | None, workspace: str | Path, **options) -> tuple[list[Reconstruction], dict]:
    """Run every stage; return the final models (``WORK/sparse/N``, largest first) and the
    report.  ``images=None`` starts from an existing ``WORK/database.db``.

    >>> models, report = reconstruct("photos", "work", max_cluster_size=50, workers=2)  # doctest: +SKIP
    """
    report = _run(Path(images) if images is not None else None, Path(workspace), make_options(**options))
    return [read_model(d) for d in numbered_folders(Path(workspace) / "sparse")], report


def extend(workspace: str | Path, images: str | Path | None, **options) -> tuple[list[Reconstruction], dict]:
    """Add new photos to the finished model ``WORK/sparse/0`` (``graphsfm extend``): extract
    and match them against the old images, cluster and reconstruct them, merge them into the
    model held as the anchor, refine the new part (``full_ba=True``: everything).  Returns the
    workspace's models (``WORK/sparse/N``; ``sparse/0`` the extended one) and the extension's
    summary.  ``images=None`` takes the database's images that no model registers.  Keyword
    options are those of :func:`reconstruct` and of ``ExtendOptions``.

    >>> models, summary = extend("work", "more_photos")  # doctest: +SKIP
    """
    summary = _extend(Path(workspace), Path(images) if images is not None else None,
                      ExtendRunOptions.from_values(options))
    return [read_model(d) for d in numbered_folders(Path(workspace) / "sparse")], summary


__all__ = ["reconstruct", "extend", "make_options", "export", "info", "align", "run_extract", "run_match", "run_cluster", "run_map", "run_merge",
           "ExtractOptions", "MatchOptions", "ClusterOptions", "MapperOptions", "MergeOptions", "ExecutionOptions",
           "RecordingOptions", "ExportOptions", "AlignOptions", "ExtendOptions", "Reconstruction", "read_model"]
