"""The self-contained input of one local SfM run (a cluster) and its camera priors.

A :class:`MapperInput` holds everything incremental SfM needs (image names and ids, camera
priors, keypoints, the verified matches of its pairs) and no paths into the caller's disk, so
it can be pickled to a worker process or another machine (``sfm.execution``).  Its options are
:class:`sfm.mapper.options.MapperOptions`.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    colors: list[np.ndarray] | None = None  # per image (K_k, 3) uint8 RGB at each keypoint, or (0, 3): unknown
    # per image (K_k,): each keypoint's verified matches over every pair of the database that
    # holds the image, inside the cluster or not (None: counted over ``pairs``)
    match_counts: list[np.ndarray] | None = None
    label: str = "C0"
