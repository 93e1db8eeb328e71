"""Registering the next image of a growing model by PnP (COLMAP's incremental mapper).

Candidates come from :meth:`sfm.mapper.state.MapperState.next_image_candidates` (most visible
triangulated points, best spread first).  A candidate is registered when OpenCV's USAC PnP
RANSAC finds at least ``abs_pose_min_num_inliers`` inliers, and ``abs_pose_min_inlier_ratio``
of the points it sees, within ``abs_pose_max_error`` pixels; its pose is then refined by least
squares on those inliers.  When PnP registers nothing, ``sfm.mapper.structureless`` tries the
images from 2D-2D matches.
"""

from __future__ import annotations

import cv2
import numpy as np

from sfm.mapper.state import MapperState


def register_next(state: MapperState) -> bool:
    """Register the best unregistered image that PnP accepts; False when none can be.  After
    the ready candidates come the failed images worth a retry when nothing else registers
    (``MapperState.next_image_candidates(stalled=True)``)."""
    opts = state.opts
    for i in state.next_image_candidates(stalled=True):
        rows, X = state.visible_points(i)
        if len(rows) < opts.abs_pose_min_num_inliers:
            continue
        x = state.obs_norm[rows]
        usac = cv2.UsacParams()
        usac.threshold = opts.abs_pose_max_error / state.focal(i)
        usac.confidence = 0.9999
        usac.maxIterations = 10000
        usac.randomGeneratorState = opts.seed + i
        usac.isParallel = False
        ok, _, rvec, tvec, inliers = cv2.solvePnPRansac(X, x, np.eye(3), None, params=usac)
        if not ok or inliers is None:
            state.note_failure(i, len(rows))
            continue
        inliers = inliers.ravel()
        if len(inliers) < opts.abs_pose_min_num_inliers or len(inliers) < opts.abs_pose_min_inlier_ratio * len(rows):
            state.note_failure(i, len(rows))
            continue
        # Least squares on the RANSAC inliers, in normalised coordinates like the RANSAC (the
        # local BA that follows refines the pose again, robustly and in pixels).
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], np.eye(3), None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        state.register(i, R, tvec.ravel())
        return True
    return False
