"""Multi-view triangulation, batched: DLT on normalised coordinates, angle and depth checks.

All functions take a flat list of observations grouped by point (``starts`` offsets, as in
``sfm.mapper.tracks.Tracks``): per observation the camera's ``cam_from_world`` (R, t) and the
normalised image coordinates of the keypoint (distortion removed).  Points with the same number
of observations are solved together with one batched SVD, so there is no Python loop over
points.
"""

from __future__ import annotations

import numpy as np


def triangulate_dlt(rotations: np.ndarray, translations: np.ndarray, xy_norm: np.ndarray,
                    starts: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of each group of observations ``starts[k]:starts[k+1]``.

    ``rotations`` (O,3,3), ``translations`` (O,3): cam_from_world of each observation's image;
    ``xy_norm`` (O,2) normalised coordinates.  Returns (P,3); groups with < 2 rows give NaN.
    Each row contributes ``x * P3 - P1`` and ``y * P3 - P2`` (rows of P = [R | t]), scaled to
    unit norm so that every view weighs the same.
    """
    lengths = np.diff(starts)
    out = np.full((len(lengths), 3), np.nan)
    P = np.concatenate([rotations, translations[:, :, None]], axis=2)  # (O,3,4)
    rows_x = xy_norm[:, 0:1] * P[:, 2] - P[:, 0]
    rows_y = xy_norm[:, 1:2] * P[:, 2] - P[:, 1]
    rows_x /= np.linalg.norm(rows_x, axis=1, keepdims=True)
    rows_y /= np.linalg.norm(rows_y, axis=1, keepdims=True)
    for n in np.unique(lengths):
        if n < 2:
            continue
        groups = np.flatnonzero(lengths == n)
        idx = starts[groups][:, None] + np.arange(n)[None, :]  # (G, n)
        A = np.concatenate([rows_x[idx], rows_y[idx]], axis=1)  # (G, 2n, 4)
        _, _, vt = np.linalg.svd(A)
        X = vt[:, -1, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[groups] = X[:, :3] / X[:, 3:4]
    return out


def max_triangulation_angles(centers: np.ndarray, points: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Largest angle (degrees) between the viewing rays of each point's observations.

    ``centers`` (O,3) camera centre of each observation, ``points`` (P,3).  Exact for up to
    ~30 views per point (all pairs, batched by group size).
    """
    lengths = np.diff(starts)
    out = np.zeros(len(lengths))
    point_of_row = np.repeat(np.arange(len(lengths)), lengths)
    rays = centers - points[point_of_row]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    for n in np.unique(lengths):
        if n < 2:
            continue
        groups = np.flatnonzero(lengths == n)
        idx = starts[groups][:, None] + np.arange(n)[None, :]
        r = rays[idx]  # (G, n, 3)
        cos = np.einsum("gik,gjk->gij", r, r)
        out[groups] = np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))
    return out


def depths(rotations: np.ndarray, translations: np.ndarray, points_per_row: np.ndarray) -> np.ndarray:
    """Depth (z in the camera frame) of each observation's point."""
    return np.einsum("oj,oj->o", rotations[:, 2, :], points_per_row) + translations[:, 2]


def refine_points(rotations: np.ndarray, translations: np.ndarray, xy_norm: np.ndarray, starts: np.ndarray,
                  points: np.ndarray, huber: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Each point's reprojection error minimised with its cameras held (Gauss-Newton, batched).

    Observations grouped by point as in :func:`triangulate_dlt`; ``points`` (P,3) the start;
    ``huber`` (O,) the Huber threshold of each observation in normalised units (pixels over
    focal length).  The error is measured on the normalised image plane, which is the pixel
    error over the focal length up to the (small) distortion.  Observations behind their camera
    weigh nothing; a point keeps its start if its normal equations are singular or its robust
    cost did not go down.
    """
    start = np.array(points, dtype=np.float64, copy=True)
    lengths = np.diff(starts)
    if len(start) == 0 or lengths.sum() == 0:
        return start
    owner = np.repeat(np.arange(len(start)), lengths)
    nonempty = lengths > 0
    first = starts[:-1][nonempty]

    def per_point(values: np.ndarray) -> np.ndarray:
        out = np.zeros((len(start),) + values.shape[1:])
        out[nonempty] = np.add.reduceat(values, first, axis=0)
        return out

    def residuals(X: np.ndarray):
        xc = (rotations @ X[owner][:, :, None])[:, :, 0] + translations
        front = xc[:, 2] > 1e-12
        z = np.where(front, xc[:, 2], 1.0)
        uv = xc[:, :2] / z[:, None]
        r = uv - xy_norm
        norm = np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2)
        rho = np.where(norm <= huber, 0.5 * norm**2, huber * (norm - 0.5 * huber))
        rho = np.where(front, rho, 0.5 * huber**2 + 1.0)  # behind the camera: worse than any inlier
        return r, norm, front, z, uv, per_point(rho)

    X, start_cost = start.copy(), None
    for _ in range(iterations):
        r, norm, front, z, uv, cost = residuals(X)
        start_cost = cost if start_cost is None else start_cost
        w = np.where(norm <= huber, 1.0, huber / np.maximum(norm, 1e-300)) * front
        # d(uv)/dX = (1/z) [[1, 0, -u], [0, 1, -v]] R: rows (R[0] - u R[2]) / z, (R[1] - v R[2]) / z
        j0 = rotations[:, 0, :] - uv[:, :1] * rotations[:, 2, :]
        j1 = rotations[:, 1, :] - uv[:, 1:] * rotations[:, 2, :]
        s = (w / z**2)[:, None]  # explicit products: cheaper than an einsum over 3 x 3 blocks
        H = per_point((s * j0)[:, :, None] * j0[:, None, :] + (s * j1)[:, :, None] * j1[:, None, :])
        g = per_point((w / z)[:, None] * (j0 * r[:, :1] + j1 * r[:, 1:]))
        scale = np.maximum(H[:, 0, 0] + H[:, 1, 1] + H[:, 2, 2], 1e-300)
        ok = np.abs(np.linalg.det(H)) > 1e-12 * scale**3
        step = np.zeros_like(X)
        step[ok] = -np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
        X = X + step
    worse = residuals(X)[-1] > (start_cost if start_cost is not None else residuals(start)[-1])
    X[worse] = start[worse]
    return X
