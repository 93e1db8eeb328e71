"""Options of ``graphsfm evaluate`` and ``graphsfm align``."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option
from sfm.evaluation.georegistration import DEFAULT_GPS_MAX_ERROR


@dataclass(frozen=True)
class EvaluateOptions(Options):
    """Options of ``graphsfm evaluate`` and ``graphsfm align``."""

    seed: int = option(0, "Seed of the robust (RANSAC) Sim3 alignment to the ground truth.", min=0)
    per_image: bool = option(False, "Also print each image's rotation and centre error.")


@dataclass(frozen=True)
class AlignOptions(Options):
    """Options of ``graphsfm align`` (COLMAP's model_aligner)."""

    max_error: float = option(
        DEFAULT_GPS_MAX_ERROR, "Inlier distance between a camera centre and its reference position, in the "
        "reference's units (metres for GPS: twice civil GPS's 4.9 m (95%) accuracy).", above=0)
    seed: int = option(0, "Seed of the robust (RANSAC) Sim3 estimation.", min=0)
    overwrite: bool = option(False, "Replace OUT when it exists (otherwise an existing OUT is an error).")
