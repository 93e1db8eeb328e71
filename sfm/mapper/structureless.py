"""Registering an image that sees too few 3D points for PnP (COLMAP's structure-less fallback,
in a simpler form).

In forward motion (a street walked along) a new view shares most of its matches with the last
registered view, whose points are not triangulated yet: no candidate sees
``abs_pose_min_num_inliers`` triangulated points, PnP cannot start, and the model stops.
COLMAP 4 then registers from 2D-2D correspondences (``structure_less_registration_fallback``,
on by default).  Here, once PnP registers nothing, this takes the images PnP could not try
(fewer than ``abs_pose_min_num_inliers`` points seen) and those it tried and failed on (a
view that sees a few dozen points of a low-parallax pair may find fewer PnP inliers than it
needs); an image that failed here is retried once it sees 20% more points.  For each, the
essential matrix of the image with its best registered neighbour gives the
rotation and the direction of the baseline; its one missing degree of freedom, the
baseline's length, comes from the few triangulated points the image does see (each point gives
a 1-D estimate; their median, then again over the inliers).  Accepted when the essential matrix
has at least ``abs_pose_min_num_inliers`` inliers and at least :data:`MIN_SCALE_POINTS` points,
and ``abs_pose_min_inlier_ratio`` of those seen, reproject within ``abs_pose_max_error``
(PnP's registration threshold: the model's points carry its drift; the local BA and the
filtering at ``max_reproj_error`` that follow any registration refine the pose).
"""

from __future__ import annotations

import logging

import numpy as np

from sfm.mapper.initialization import relative_pose
from sfm.mapper.state import MapperState

log = logging.getLogger(__name__)

# Points that must agree on the baseline length (a median of 1-D estimates; OpenSfM registers
# with 10 inliers).
MIN_SCALE_POINTS = 10


def _best_registered_neighbours(state: MapperState) -> dict[int, tuple[int, np.ndarray]]:
    """For each unregistered image of the current model's candidates, the registered image
    with most verified matches to it (at least ``abs_pose_min_num_inliers``) and those
    matches as (keypoint in the registered image, keypoint in the other) rows.  One pass over
    the pairs."""
    best: dict[int, tuple[int, np.ndarray]] = {}
    open_image = ~state.registered & ~state.used
    for (a, b), (m, _config) in state.pair_matches.items():
        if len(m) < state.opts.abs_pose_min_num_inliers:
            continue
        if state.registered[a] and open_image[b]:
            j, i, rows = a, b, m
        elif state.registered[b] and open_image[a]:
            j, i, rows = b, a, m[:, ::-1]
        else:
            continue
        if i not in best or len(rows) > len(best[i][1]):
            best[i] = (j, rows)
    return best


def _baseline_length(state: MapperState, i: int, rows: np.ndarray, X: np.ndarray, R: np.ndarray,
                     t0: np.ndarray, d: np.ndarray):
    """(length, inlier count) of the baseline along ``d`` for image ``i`` with rotation ``R``
    (its translation is ``t0 + length * d``) from the points ``X`` it sees in ``rows``."""
    x = np.column_stack([state.obs_norm[rows], np.ones(len(rows))])
    a = X @ R.T + t0
    c, e = np.cross(x, a), np.cross(x, np.broadcast_to(d, a.shape))  # x × (a + s d) = 0
    s = -np.sum(c * e, axis=1) / np.maximum(np.sum(e * e, axis=1), 1e-18)
    if not np.any(s > 0):
        return None
    length = float(np.median(s[s > 0]))
    for attempt in range(3):  # the median of all positive estimates, then of the inliers twice
        xc = a + length * d
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(xc[:, :2] / xc[:, 2:] - x[:, :2], axis=1) * state.focal(i)
        inliers = (xc[:, 2] > 0) & (err < state.opts.abs_pose_max_error)
        if inliers.sum() < MIN_SCALE_POINTS:
            return None
        if attempt < 2:
            length = float(np.median(s[inliers]))
    return length, int(inliers.sum())  # the length these inliers were counted at


def register_structureless(state: MapperState) -> bool:
    """Register one unregistered image from its best registered neighbour's essential matrix
    (:func:`sfm.mapper.initialization.relative_pose`) and the points it sees (module
    docstring); False when no image passes."""
    opts = state.opts
    neighbours = _best_registered_neighbours(state)
    for i in sorted(neighbours, key=lambda k: (-len(neighbours[k][1]), k)):
        j, m = neighbours[i]
        rows, X = state.visible_points(i)
        seen = len(rows)
        if seen < MIN_SCALE_POINTS or (seen >= opts.abs_pose_min_num_inliers and not state.failed[i]):
            continue  # no baseline length to be had, or an image PnP has yet to try
        if seen <= 1.2 * state.structureless_failed.get(i, -1):
            continue  # failed here before, and sees hardly more points now
        rel = relative_pose(state, j, i, m, opts.seed + i)
        if rel is None or int(rel[2].sum()) < opts.abs_pose_min_num_inliers:
            state.structureless_failed[i] = seen
            continue
        R_rel, t_rel, _ = rel
        R = R_rel @ state.R[j]
        found = _baseline_length(state, i, rows, X, R, R_rel @ state.t[j], t_rel)
        if found is None or found[1] < opts.abs_pose_min_inlier_ratio * seen:
            state.structureless_failed[i] = seen
            continue
        length, n_inliers = found
        log.debug("%s: %s registered without PnP: from %s's essential matrix (%d inliers) and %d of %d points",
                  state.payload.label, state.names[i], state.names[j], int(rel[2].sum()), n_inliers, seen)
        state.register(i, R, R_rel @ state.t[j] + length * t_rel)
        return True
    return False
