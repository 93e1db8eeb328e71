"""The self-contained input of one local SfM run (a cluster), and its options.

A :class:`MapperInput` holds everything incremental SfM needs (image names and ids, camera
priors, keypoints, the verified matches of its pairs) and no paths into the caller's disk, so
it can be pickled to a worker process or another machine (DESIGN.md, "Execution").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class CameraPrior:
    """A camera group: COLMAP model name, size, parameters (OpenCV pixel convention), whether
    the focal length comes from EXIF or the user, and whether the intrinsics are held fixed."""

    model: str
    width: int
    height: int
    params: np.ndarray
    prior_focal_length: bool = False
    fixed: bool = False


@dataclass(frozen=True)
class MapperInput:
    """One cluster's payload.  Image ``k`` has database id ``image_ids[k]``, name ``names[k]``,
    camera ``camera_ids[k]`` (a key of ``cameras``) and keypoints ``keypoints[k]`` (K_k, 2), or
    (K_k, 3) whose third column is each keypoint's detection scale in pixels (the BA weighs by it);
    ``pairs`` lists ``(k1, k2, inlier_matches (M,2), config)`` with local indices k1 < k2."""

    image_ids: list[int]
    names: list[str]
    camera_ids: list[int]
    cameras: dict[int, CameraPrior]
    keypoints: list[np.ndarray]
    pairs: list[tuple[int, int, np.ndarray, int]]
    colors: list[np.ndarray] | None = None  # per image (K_k, 3) uint8 RGB at each keypoint
    label: str = "C0"


@dataclass(frozen=True)
class MapperOptions:
    """Options of incremental SfM (COLMAP's documented defaults where they apply).

    min_num_matches: pairs with fewer verified inliers are ignored.
    init_min_tri_angle: median triangulation angle (degrees) wanted of the initial pair; it is
        halved twice if no pair reaches it (COLMAP: 16).
    init_min_num_inliers: inliers an initial pair should have, when some pair has them
        (COLMAP: 100).
    init_max_pairs: initial-pair candidates examined per attempt (most inliers first).
    abs_pose_min_num_inliers: PnP inliers needed to register an image (COLMAP: 30).
    abs_pose_min_inlier_ratio: share of PnP inliers needed (COLMAP: 0.25).
    abs_pose_max_error: PnP RANSAC inlier threshold in pixels (COLMAP: 12): looser than
        ``max_reproj_error`` because the 3D points of a growing model carry its drift; the
        registered image keeps only the observations within ``max_reproj_error``.
    max_reproj_error: pixel error above which an observation is an outlier (COLMAP: 4).
    min_tri_angle: smallest triangulation angle (degrees) of a point (COLMAP: 1.5).
    local_ba_num_images: images optimised by the local BA after each registration (COLMAP: 6).
    global_ba_ratio: a global BA runs when the model has grown by this factor (OpenSfM's 1.2;
        COLMAP's 1.1 doubles the number of global BAs for little accuracy: the local BA after
        every image and the final global BAs do the fine work).
    refine_intrinsics: one of none|focal|focal_radial|all: what global BA refines of cameras
        whose intrinsics were not given by the user.
    refine_given_intrinsics: also refine intrinsics given with --intrinsics (held fixed
        otherwise).
    loss: one of huber|cauchy|none, the robust loss of every BA (and of the point
        re-estimation after a BA on a track subset).
    loss_scale: scale of the local BAs' robust loss in pixels (times the observation's sigma;
        COLMAP's local BA: soft-L1 at 1 px).
    global_loss_scale: scale in pixels (times the observation's sigma) of the robust loss of
        a model's global BAs (growing and final; the refinement of merged poses keeps
        ``loss_scale``, see ``sfm.mapper.incremental.refine_with_poses``).  None: ``max_reproj_error``
        for a model that is final (all images in one cluster), ``loss_scale`` for the models of
        clusters that are merged.  Every observation a global BA sees reprojected within
        ``max_reproj_error`` when it joined the model and after the BA before it, so at that
        scale the loss is least squares on all of them (COLMAP's global BA) and only bounds an
        observation the BA pushes beyond it, where at 1 px it re-weights the inliers at every
        iteration and converges linearly in the tail.  temple_ring (default intrinsics): final
        BAs 2 + 2 iterations instead of 3 + 3, the young model's 110 instead of 151, a fifth
        less BA work; median rotation error 0.546 -> 0.528 deg, AUC@5 0.816 -> 0.817;
        lund_door AUC@1 0.975 both.  The merged synthetic aerial blocks did not gain: with the
        threshold in the clusters' BAs they came out at 0.0282, 0.0526 and 0.0302 deg (500,
        1,000, 2,000 images; 0.0212, 0.0879, 0.0191 with 1 px in the merged refinement only)
        against 0.0211, 0.0528 and 0.0231 deg with 1 px throughout.
    scale_weights: every BA weighs each observation by its keypoint's detection scale:
        standard deviation ``max(1, scale / 0.8)`` px (``sfm.features.sift.localization_sigma``: SIFT's
        positional error grows with its scale, the finest level counts as 1 px); keypoints
        without a scale count 1 px.  temple_ring mapped with the GT intrinsics: AUC@1 0.728 ->
        0.810, median rotation error 0.164 -> 0.105 deg (its plaster gives many coarse blobs
        that locate poorly); the rendered demo scene 0.931 -> 0.918.  Off: 1 px everywhere
        (COLMAP's choice).
    ba_max_observations: the most observations one GTSAM bundle adjustment holds (GTSAM needs
        about 1.2-1.7 KB each while it optimises: 1.5 GB at the default 1,000,000).  A final
        global BA over more is the consensus of BAs over random disjoint parts of the tracks,
        each within the budget (``backend.partitioned_ba``: the mean of the part estimates),
        then every point is re-estimated with the cameras held.  On the synthetic aerial block
        the median rotation error went 0.058 -> 0.041 deg at 1,000 images (two parts) but
        0.019 -> 0.052 deg at 4,000 (five parts), for 8.4 -> 3.4 GB.  0: no limit.
    min_model_size: smallest number of registered images kept as a model.
    max_num_models: the most models made from one input.
    seed: seed of every random choice (PnP sampling).
    """

    min_num_matches: int = 15
    init_min_tri_angle: float = 16.0
    init_min_num_inliers: int = 100
    init_max_pairs: int = 100
    abs_pose_min_num_inliers: int = 30
    abs_pose_min_inlier_ratio: float = 0.25
    abs_pose_max_error: float = 12.0
    max_reproj_error: float = 4.0
    min_tri_angle: float = 1.5
    local_ba_num_images: int = 6
    global_ba_ratio: float = 1.2
    refine_intrinsics: str = "focal_radial"
    refine_given_intrinsics: bool = False
    loss: str = "huber"
    loss_scale: float = 1.0
    global_loss_scale: float | None = None
    scale_weights: bool = True
    ba_max_observations: int = 1_000_000
    min_model_size: int = 3
    max_num_models: int = 50
    seed: int = 0

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

