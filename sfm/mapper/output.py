"""What :class:`sfm.mapper.state.MapperState` gives out: the model as a
:class:`sfm.core.model.Reconstruction`, and the growing model for the Rerun viewer."""

from __future__ import annotations

import itertools

import numpy as np

from backend.camera_models import calibration_matrix
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.state import MapperState
from sfm.core.model import Camera, Image, Point3D, Reconstruction
from sfm.viz.recorder import Recorder, log_camera


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
    grey = np.full(3, 128, np.uint8)
    images, kps = image_of_row.tolist(), kp_of_row.tolist()
    for k, (s, e) in enumerate(itertools.pairwise(starts.tolist())):
        color = grey
        if state.payload.colors is not None:
            color = np.asarray(state.payload.colors[state.obs_image[rows[s]]][kps[s]], dtype=np.uint8)
        recon.points3D[k + 1] = Point3D(xyz[k], list(zip(images[s:e], kps[s:e])), color)
    recon._next_point_id = len(lengths) + 1
    recon.update_point_errors()
    return recon


def log_progress(state: MapperState, adjuster: BundleAdjuster, recorder: Recorder) -> None:
    """``clusters/<label>/points``, the new camera and the last BA's RMS on the
    ``registration`` timeline: the model growing image by image."""
    if not recorder.enabled:
        return
    import rerun as rr

    label = state.payload.label
    recorder.set_time("registration", state.num_registered)
    recorder.log(f"clusters/{label}/points", rr.Points3D(state.track_xyz[state.track_valid]))
    recorder.log(f"clusters/{label}/ba_rms_px", rr.Scalars(adjuster.last_rms))
    i = state.last_registered
    if i >= 0:
        c = state.cam_index[i]
        log_camera(recorder, f"clusters/{label}/cams/{state.names[i]}", state.R[i], state.t[i],
                   calibration_matrix(state.priors[c].model, state.params[c]), state.priors[c].width, state.priors[c].height)
