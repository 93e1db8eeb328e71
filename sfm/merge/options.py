"""Options of the ``merge`` stage (paper section 3.2)."""

from __future__ import annotations

from dataclasses import dataclass

from backend.similarity import SimilarityOptions
from sfm.core.options import Options, option


@dataclass(frozen=True)
class MergeOptions(Options):
    """Options of the ``merge`` stage (``graphsfm merge``)."""

    max_msd: float = option(
        SimilarityOptions.max_msd, "Cluster-graph edges whose MSD (Eq. 11, normalised by the common cameras' "
        "extent) exceeds this are not used: the paper's dotted edges.", above=0)
    min_common_cameras: int = option(
        2, "Registered images two local models must share to be aligned (two fix a scale).", min=2)


@dataclass(frozen=True)
class ExtendOptions(Options):
    """Options of ``graphsfm extend`` beyond those of the stages it runs again on the new images."""

    full_ba: bool = option(
        False, "Bundle-adjust every image and point after the merge (cost grows with the whole model), not only "
        "the new images' region with the rest held (a region of half the model or more gets it anyway).")
