"""Options of incremental SfM (:mod:`sfm.mapper`), the ``map`` stage's options."""

from __future__ import annotations

from dataclasses import dataclass, replace

from sfm.core.options import Options, option
from sfm.evaluation.georegistration import DEFAULT_GPS_MAX_ERROR


@dataclass(frozen=True)
class MapperOptions(Options):
    """Options of incremental SfM (``graphsfm map``; COLMAP's documented defaults where they apply)."""

    min_num_matches: int = option(15, "Pairs with fewer verified inliers are ignored.", min=1)
    init_min_tri_angle: float = option(
        16.0, "Median triangulation angle in degrees wanted of the initial pair; halved up to three times when "
        "no pair reaches it (COLMAP: 16).", above=0)
    init_min_num_inliers: int = option(
        100, "Inliers an initial pair should have, when some pair has them (COLMAP: 100).", min=1)
    init_max_pairs: int = option(100, "Initial-pair candidates examined per attempt, most inliers first.", min=1)
    abs_pose_min_num_inliers: int = option(30, "PnP inliers needed to register an image (COLMAP: 30).", min=4)
    abs_pose_min_inlier_ratio: float = option(
        0.25, "Share of the points an image sees that must be PnP inliers (COLMAP: 0.25).", min=0, max=1)
    abs_pose_max_error: float = option(
        12.0, "PnP RANSAC inlier threshold in pixels (COLMAP: 12): looser than max_reproj_error, since a "
        "growing model's points carry its drift.", above=0)
    max_reproj_error: float = option(
        4.0, "Reprojection error in pixels above which an observation is an outlier (COLMAP: 4).", above=0)
    min_tri_angle: float = option(1.5, "Smallest triangulation angle in degrees of a point (COLMAP: 1.5).", min=0)
    ignore_two_view_tracks: bool = option(
        True, "Triangulate a track seen by only two images only in the initial pair (COLMAP: "
        "tri_ignore_two_view_tracks 1).")
    local_ba_num_images: int = option(
        6, "Images the local BA after each registration optimises (COLMAP: 6).", min=1)
    global_ba_ratio: float = option(
        1.2, "A global BA runs when the model has grown by this factor (OpenSfM: 1.2).", above=1)
    intrinsics_refinement: str = option(
        "auto", "What global BAs refine of cameras not given: none, focal, focal_radial (COLMAP's), all "
        "(principal point too), or auto: focal_radial, but in the final BAs the distortion and the principal "
        "point only where the photos determine them.",
        choices=("none", "focal", "focal_radial", "all", "auto"))
    refine_given_intrinsics: bool = option(
        False, "Also refine intrinsics given with --intrinsics (held fixed otherwise).")
    loss: str = option(
        "huber", "The robust loss of every BA (and of point re-estimation).", choices=("huber", "cauchy", "none"))
    loss_scale: float = option(
        1.0, "Scale in pixels (times the observation's sigma) of the local BAs' robust loss (COLMAP: soft-L1 "
        "at 1 px).", above=0)
    global_loss_scale: float | None = option(
        None, "Scale in pixels of the global BAs' robust loss; default: max_reproj_error for a model that is "
        "final (least squares on its inliers, as COLMAP's global BA), loss_scale for clusters that are "
        "merged.", above=0)
    scale_weights: bool = option(
        True, "Weigh each observation by its keypoint's detection scale (sigma max(1, scale / 0.8) px); "
        "off: 1 px everywhere, as COLMAP.")
    ba_max_observations: int | None = option(
        None, "The most observations one bundle adjustment holds in memory; a larger final BA is the "
        "consensus of BAs over random track parts. Default: what half of the machine's memory holds "
        "(each observation costs more the longer its track). "
        "0: no limit.", min=0)
    min_model_size: int = option(3, "Smallest number of registered images kept as a model.", min=2)
    max_num_models: int = option(50, "The most models made from one input.", min=1)
    georegister: bool = option(
        True, "Move each final model into a local east-north-up frame in metres when three or more of its "
        "images carry EXIF GPS (origin in report.json).")
    gps_max_error: float = option(
        DEFAULT_GPS_MAX_ERROR, "Georegistration's inlier distance in metres between a camera and its GPS position (twice the "
        "4.9 m (95%) accuracy of civil GPS).", above=0)
    seed: int = option(0, "Seed of every random choice (RANSAC sampling).", min=0)

    def for_model(self, final: bool) -> MapperOptions:
        """These options with ``global_loss_scale`` resolved for a model that is final
        (``max_reproj_error``) or one that will be merged (``loss_scale``)."""
        if self.global_loss_scale is not None:
            return self
        return replace(self, global_loss_scale=self.max_reproj_error if final else self.loss_scale)

    def smallest_model(self, num_images: int) -> int:
        """The fewest registered images a model of ``num_images`` input images keeps: COLMAP's
        min(min_model_size, 0.8 N), never below 2 (a two-image input gives a two-view model)."""
        return max(2, min(self.min_model_size, int(0.8 * num_images)))

