"""Which tracks a bundle adjustment needs (TheiaSfM's track subset selection).

A camera's pose is fixed as well by a few hundred well-spread, well-measured points as by all
of its thousands: past that, more observations cost time and memory in every LM iteration for
a gain in accuracy that shrinks like one over the square root of their number.  So the global
BAs while a model grows optimise the cameras on a subset of the tracks, and every other point
is re-estimated afterwards with the cameras held (:func:`sfm.mapper.triangulation.refine_points`),
which is exact for it: with its cameras fixed, a point is its own small problem.  (A final BA over too many observations is split instead,
``backend.partitioned_ba``: on a nearly flat problem one subset's optimum lies too far from
the full one.)

The subset: each image is cut into a ``grid`` x ``grid`` grid; within each cell the image ranks
the tracks it sees, longest first (a long track ties many cameras together) and, among equally
long ones, smallest mean reprojection error first.  A track's priority is its best rank in any
image and cell.  Tracks are taken by priority (every cell of every image gets its best track
before any cell gets its second) until the next priority level would exceed the budget.
"""

from __future__ import annotations

import numpy as np


def select_tracks(obs_image: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray,
                  image_size: np.ndarray, obs_error: np.ndarray, num_points: int,
                  max_observations: int, grid: int = 10) -> np.ndarray:
    """Boolean mask over the ``num_points`` points: the tracks to bundle-adjust, with at most
    ``max_observations`` observations (at least every cell's best track, whatever the budget).

    ``obs_image`` (M,), ``obs_point`` (M,), ``obs_xy`` (M,2) pixels, ``image_size`` (N,2)
    width and height of each image, ``obs_error`` (M,) reprojection error in pixels.
    """
    obs_image = np.asarray(obs_image, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    selected = np.zeros(num_points, dtype=bool)
    if len(obs_image) == 0:
        return selected
    length = np.bincount(obs_point, minlength=num_points)
    if len(obs_image) <= max_observations:
        selected[length > 0] = True
        return selected
    mean_err = np.bincount(obs_point, weights=obs_error, minlength=num_points) / np.maximum(length, 1)
    size = np.asarray(image_size, np.float64)[obs_image]
    cell_xy = np.clip((np.asarray(obs_xy, np.float64) / size * grid).astype(np.int64), 0, grid - 1)
    cell = (obs_image * grid + cell_xy[:, 1]) * grid + cell_xy[:, 0]
    order = np.lexsort((obs_point, mean_err[obs_point], -length[obs_point], cell))
    sorted_cell = cell[order]
    first = np.r_[True, sorted_cell[1:] != sorted_cell[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
    priority = np.full(num_points, np.iinfo(np.int64).max)
    np.minimum.at(priority, obs_point[order], np.arange(len(order)) - start)
    seen = np.flatnonzero(length > 0)
    # Whole priority levels while they fit; level 0 always.
    levels = np.unique(priority[seen])
    level_obs = np.bincount(priority[seen], weights=length[seen])
    cumulative = np.cumsum(level_obs[levels])
    last = levels[max(int(np.searchsorted(cumulative, max_observations, side="right")) - 1, 0)]
    selected[seen[priority[seen] <= last]] = True
    return selected
