"""What :class:`sfm.mapper.state.MapperState` gives out: the model as a
:class:`sfm.core.model.Reconstruction`, each point coloured by the mean colour of the keypoints
that observe it (COLMAP colours its points so)."""

from __future__ import annotations

import itertools

import numpy as np

from sfm.mapper.state import MapperState
from sfm.core.model import Camera, Image, Point3D, Reconstruction


def to_reconstruction(state: MapperState) -> Reconstruction:
    """The current model as a :class:`Reconstruction` (points with >= 2 inlier rows)."""
    recon = Reconstruction()
    for c, key in enumerate(state.cam_keys):
        prior = state.priors[c]
        if np.any(state.registered & (state.cam_index == c)):
            recon.add_camera(Camera(key, prior.model, prior.width, prior.height, state.params[c].copy()))
    for i in np.flatnonzero(state.registered):
        recon.add_image(Image(state.payload.image_ids[i], state.names[i], state.cam_keys[state.cam_index[i]],
                              state.R[i].copy(), state.t[i].copy(), np.ascontiguousarray(np.asarray(state.payload.keypoints[i])[:, :2])))
    rows = np.flatnonzero(state.obs_inlier & state.registered[state.obs_image] & state.track_valid[state.obs_track])
    tr = state.obs_track[rows]
    order = np.argsort(tr, kind="stable")
    rows, tr = rows[order], tr[order]
    lengths = np.diff(np.flatnonzero(np.r_[True, tr[1:] != tr[:-1], True])) if len(tr) else np.zeros(0, np.int64)
    kept = np.repeat(lengths >= 2, lengths)  # a point needs two inlier rows
    rows, tr, lengths = rows[kept], tr[kept], lengths[lengths >= 2]
    starts = np.r_[0, np.cumsum(lengths)]
    point_of_row = np.repeat(np.arange(1, len(lengths) + 1), lengths)
    image_of_row = np.asarray(state.payload.image_ids)[state.obs_image[rows]]
    kp_of_row = state.obs_kp[rows]
    by_image = np.argsort(image_of_row, kind="stable")  # one pass per image, not a mask over all rows
    image_ids, first = np.unique(image_of_row[by_image], return_index=True)
    for iid, sel in zip(image_ids.tolist(), np.split(by_image, first[1:])):
        recon.images[iid].point3D_ids[kp_of_row[sel]] = point_of_row[sel]
    xyz = state.track_xyz[tr[starts[:-1]]]
    colors = mean_colors(state, rows, starts)
    images, kps = image_of_row.tolist(), kp_of_row.tolist()
    for k, (s, e) in enumerate(itertools.pairwise(starts.tolist())):
        recon.points3D[k + 1] = Point3D(xyz[k], list(zip(images[s:e], kps[s:e])), colors[k])
    recon._next_point_id = len(lengths) + 1
    recon.update_point_errors()
    return recon


def row_colors(state: MapperState, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The keypoint colour of each observation row ``(R, 3)`` uint8, and whether it is known
    (the payload has colours for the row's image)."""
    colors = state.payload.colors
    rgb = np.zeros((len(rows), 3), np.uint8)
    if colors is None:
        return rgb, np.zeros(len(rows), bool)
    sizes = np.array([len(c) for c in colors], dtype=np.int64)
    flat = np.concatenate([np.asarray(c, np.uint8).reshape(-1, 3) for c in colors] + [np.zeros((0, 3), np.uint8)])
    image, kp = state.obs_image[rows], state.obs_kp[rows]
    known = kp < sizes[image]
    rgb[known] = flat[(np.cumsum(sizes) - sizes)[image[known]] + kp[known]]
    return rgb, known


def mean_colors(state: MapperState, rows: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """``(P, 3)`` uint8: the mean keypoint colour of each group ``rows[starts[k]:starts[k+1]]``
    (a point's track), rounded half up in integers so that it is exact and the same on every
    machine; grey (128) for a point none of whose images has colours."""
    num = len(starts) - 1
    out = np.full((num, 3), 128, np.uint8)
    if num <= 0 or state.payload.colors is None:
        return out
    rgb, known = row_colors(state, rows)
    owner = np.repeat(np.arange(num), np.diff(starts))
    sums = np.stack([np.bincount(owner[known], weights=rgb[known, c], minlength=num) for c in range(3)],
                    axis=1).astype(np.int64)  # float64 sums of bytes: exact
    counts = np.bincount(owner[known], minlength=num).astype(np.int64)
    has = counts > 0
    out[has] = ((2 * sums[has] + counts[has, None]) // (2 * counts[has, None])).astype(np.uint8)
    return out
