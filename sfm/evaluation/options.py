"""Options of ``graphsfm evaluate``."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option


@dataclass(frozen=True)
class EvaluateOptions(Options):
    """Options of ``graphsfm evaluate``."""

    seed: int = option(0, "Seed of the robust (RANSAC) Sim3 alignment to the ground truth.", min=0)
    per_image: bool = option(False, "Also print each image's rotation and centre error.")
