"""Options of the ``match`` stage: which pairs, descriptor matching, verification."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import Options, option
from sfm.matching.verification import VerifyOptions


@dataclass(frozen=True)
class MatchOptions(Options):
    """Options of the ``match`` stage (``graphsfm match``)."""

    pairs: str = option(
        "auto", "Which pairs to match: every pair (exhaustive), each image's top_k most similar by VLAD "
        "(retrieval), retrieval plus GPS neighbours (spatial), or exhaustive below exhaustive_threshold (auto).",
        choices=("auto", "exhaustive", "retrieval", "spatial"))
    top_k: int = option(30, "Retrieval matches each image with its top_k most similar images.", min=1)
    sequential: int = option(
        0, "Also match each image with the next N images in name order (video, drone strips); 0: off.", min=0)
    spatial_neighbors: int = option(
        50, "With pairs spatial: each image is also matched with this many nearest images by EXIF GPS "
        "(COLMAP's spatial matcher: 50).", min=1)
    spatial_max_distance: float = option(
        100.0, "With pairs spatial: GPS neighbours at most this many metres away (COLMAP: 100); 0: any.", min=0)
    exhaustive_threshold: int = option(
        200, "With pairs auto: the number of images from which retrieval replaces exhaustive matching.", min=2)
    matcher: str = option(
        "auto", "Nearest-neighbour search: exact (brute), an approximate inverted file per image (ivf), "
        "approximate KD-trees (flann), or ivf unless both images have few features (auto).",
        choices=("auto", "brute", "ivf", "flann"))
    max_ratio: float = option(0.8, "Lowe's ratio test on descriptor distances (COLMAP's max_ratio).", above=0, max=1)
    cross_check: bool = option(True, "Keep only mutual nearest neighbours.")
    max_error_px: float = option(
        VerifyOptions.max_error_px, "Verification's inlier threshold in pixels (Sampson distance for E and "
        "F, transfer error for H).", above=0)
    confidence: float = option(VerifyOptions.confidence, "RANSAC confidence of verification.", above=0, max=1)
    max_iterations: int = option(VerifyOptions.max_iterations, "RANSAC iteration cap of verification.", min=1)
    min_num_inliers: int = option(
        VerifyOptions.min_num_inliers, "A pair with fewer inliers is not a verified pair.", min=1)
    max_h_inlier_ratio: float = option(
        VerifyOptions.max_h_inlier_ratio, "A pair whose homography inliers exceed this share of its E or F "
        "inliers is marked planar or panoramic.", above=0, max=1)
    seed: int = option(0, "Seed of the vocabulary, FLANN and RANSAC: the same seed gives the same matches.", min=0)

    def verify_options(self) -> VerifyOptions:
        return VerifyOptions(self.max_error_px, self.confidence, self.max_iterations,
                             self.min_num_inliers, self.max_h_inlier_ratio)  # fmt: skip
