"""Choosing and reconstructing the initial pair of a model (COLMAP's incremental mapper).

The first two images fix the model's frame and scale, so they should share many inliers, see a
wide triangulation angle, and not be a homography-dominated (planar or panoramic) pair.  Their
relative pose comes from the essential matrix (OpenCV's USAC MAGSAC on normalised coordinates),
and the pair is scored by how many of its matches triangulate in front of both cameras within
the reprojection threshold.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from sfm.mapper.state import MapperState
from sfm.mapper.triangulation import triangulate_dlt

log = logging.getLogger(__name__)

PLANAR_CONFIGS = (4, 5, 6)  # PLANAR, PANORAMIC, PLANAR_OR_PANORAMIC


def relative_pose(state: MapperState, i: int, j: int, matches: np.ndarray, seed: int):
    """cam_j_from_cam_i (R, t with |t| = 1) from the matches' essential matrix, and its inliers."""
    thr = state.opts.max_reproj_error / np.mean([state.focal(i), state.focal(j)])
    return pose_from_essential(state.norm_of(i, matches[:, 0]), state.norm_of(j, matches[:, 1]), thr, seed)


def pose_from_essential(x1: np.ndarray, x2: np.ndarray, threshold: float, seed: int):
    """cam_2_from_cam_1 (R, t with |t| = 1) from the essential matrix of the matched normalised
    coordinates ``x1``, ``x2`` (MAGSAC at ``threshold``, in normalised units), and a mask of
    its inliers over the rows; None when fewer than 8 rows are usable or inliers."""
    # rows a degenerate camera cannot unproject count as outliers
    num_rows = len(x1)
    kept = np.flatnonzero(np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1))
    if len(kept) < 8:
        return None
    x1, x2 = x1[kept], x2[kept]
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=threshold, maxIters=10000)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    if n < 8:
        return None
    inl = np.zeros(num_rows, dtype=bool)
    inl[kept[mask.ravel() > 0]] = True
    return R, t.ravel() / np.linalg.norm(t), inl


def two_view_score(state: MapperState, i: int, j: int, R: np.ndarray, t: np.ndarray, matches: np.ndarray) -> tuple[int, float]:
    """Points of a candidate initial pair that pass depth and reprojection checks, and their
    median triangulation angle (degrees)."""
    if len(matches) == 0:
        return 0, 0.0
    x = np.concatenate([state.norm_of(i, matches[:, 0]), state.norm_of(j, matches[:, 1])])
    m = len(matches)
    rot = np.concatenate([np.tile(np.eye(3), (m, 1, 1)), np.tile(R, (m, 1, 1))])
    tra = np.concatenate([np.zeros((m, 3)), np.tile(t, (m, 1))])
    order = np.r_[np.arange(m), np.arange(m) + m].reshape(2, m).T.ravel()  # interleave views
    starts = np.arange(0, 2 * m + 1, 2)
    X = triangulate_dlt(rot[order], tra[order], x[order], starts)
    z1 = X[:, 2]
    z2 = (X @ R.T + t)[:, 2]
    proj1 = X[:, :2] / z1[:, None]
    x2c = X @ R.T + t
    proj2 = x2c[:, :2] / z2[:, None]
    err = np.maximum(np.linalg.norm(proj1 - x[:m], axis=1) * state.focal(i), np.linalg.norm(proj2 - x[m:], axis=1) * state.focal(j))
    ok = (z1 > 0) & (z2 > 0) & (err < state.opts.max_reproj_error)
    if ok.sum() == 0:
        return 0, 0.0
    c2 = -R.T @ t
    r1 = X[ok] / np.linalg.norm(X[ok], axis=1, keepdims=True)
    r2 = (X[ok] - c2) / np.linalg.norm(X[ok] - c2, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(np.sum(r1 * r2, axis=1), -1, 1)))
    good = angles >= state.opts.min_tri_angle
    return int(good.sum()), float(np.median(angles))


def ray_angles(state: MapperState, i: int, j: int, R: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """Triangulation angle (degrees) of each match between images ``i`` and ``j`` of relative
    rotation ``R`` (cam_j_from_cam_i), without triangulating: the angle at a point between its
    rays from the two centres is the angle between its viewing directions expressed in one
    frame, whatever the baseline (exact for noise-free matches)."""
    d1 = state.norm_of(i, matches[:, 0])
    d2 = state.norm_of(j, matches[:, 1])
    d1 = np.column_stack([d1, np.ones(len(d1))])
    d2 = np.column_stack([d2, np.ones(len(d2))]) @ R  # rows R^T d2: the rays of j in i's frame
    cos = np.sum(d1 * d2, axis=1) / (np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


# A candidate initial pair whose inliers' median ray angle is below this share of the angle
# threshold is not triangulated unless every threshold relaxation needs it: the median over the
# points that pass the checks is the same angle over slightly fewer rows, far from a 20% gap.
_DEFER_ANGLE_SHARE = 0.8


def try_initial_pair(state: MapperState, tried: set) -> bool:
    """Find and reconstruct an initial pair among unregistered images.

    Candidates are the pairs with the most inliers (at least ``init_min_num_inliers`` when any
    has that many), up to ``init_max_pairs``; each gets its relative pose once (E).  The pair
    with the most well-triangulated points among those whose median triangulation angle
    reaches ``init_min_tri_angle`` wins; if none does, the angle is halved, up to three times
    (COLMAP relaxes twice; a camera moving forward along a street sees most points close to
    its direction of motion, so median angles of only a few degrees even between frames a
    few steps apart, and BA widens the baseline as the model grows).  Candidates come in order
    of inliers and a score never exceeds a pair's inliers, so the search stops once a pair
    passing the first angle threshold scores more than the next candidate has inliers: the
    same winner, fewer two-view reconstructions.  The two-view
    triangulation that scores a pair (:func:`two_view_score`) waits until a threshold needs it
    for pairs whose rays are clearly too parallel for the first one (:func:`ray_angles`): on
    a ring of views, most pairs with many matches are neighbours a few degrees apart."""
    opts = state.opts
    cands = [
        (len(m), i, j, m)
        for (i, j), (m, config) in state.pair_matches.items()
        if not state.registered[i] and not state.registered[j] and not state.used[i] and not state.used[j]
        and (i, j) not in tried and config not in PLANAR_CONFIGS
        and len(m) >= max(opts.abs_pose_min_num_inliers, opts.min_num_matches)
    ]
    cands.sort(key=lambda c: (-c[0], c[1], c[2]))
    if sum(c[0] >= opts.init_min_num_inliers for c in cands) >= 1:
        cands = [c for c in cands if c[0] >= opts.init_min_num_inliers]
    evaluated, deferred = [], []
    best_wide = -1  # best score so far among pairs that pass the first angle threshold

    def score(i, j, R, t, m):
        points, angle = two_view_score(state, i, j, R, t, m)
        log.debug("init candidate %s-%s: %d inliers, median angle %.1f deg, %d points",
                  state.names[i], state.names[j], len(m), angle, points)
        if points >= opts.abs_pose_min_num_inliers:
            evaluated.append((points, angle, i, j, R, t))
        return points, angle

    for n_inl, i, j, m in cands[: opts.init_max_pairs]:
        if best_wide > n_inl:
            break  # a score counts inliers of these matches: no later pair can beat it
        rel = relative_pose(state, i, j, m, opts.seed)
        if rel is None:
            continue
        R, t, inl = rel
        if np.median(ray_angles(state, i, j, R, m[inl])) < _DEFER_ANGLE_SHARE * opts.init_min_tri_angle:
            deferred.append((i, j, R, t, m[inl]))
            continue
        points, angle = score(i, j, R, t, m[inl])
        if points >= opts.abs_pose_min_num_inliers and angle >= opts.init_min_tri_angle:
            best_wide = max(best_wide, points)
    for min_angle in (opts.init_min_tri_angle, opts.init_min_tri_angle / 2, opts.init_min_tri_angle / 4,
                      opts.init_min_tri_angle / 8):
        if min_angle < opts.init_min_tri_angle:
            for args in deferred:
                score(*args)
            deferred = []
        ok = [e for e in evaluated if e[1] >= min_angle]
        if ok:
            points, angle, i, j, R, t = max(ok, key=lambda e: (e[0], -e[2], -e[3]))
            tried.add((i, j))
            state.start_model(i, j, R, t)
            return True
    return False
