"""What a model holds, as COLMAP's ``model_analyzer`` prints it (``graphsfm info``)."""

from __future__ import annotations


import numpy as np

from sfm.core.model import Reconstruction
from sfm.io.pixel_convention import params_to_colmap
from backend.camera_models import model_spec


def model_info(recon: Reconstruction, georegistration: dict | None = None) -> dict:
    """Cameras (model, size, parameters by name in COLMAP's pixel convention), registered
    images, points, observations, track length and observations per image, reprojection error
    (mean and median, pixels), and the georegistration (None: not georegistered)."""
    track = np.array([len(p.track) for p in recon.points3D.values()], np.int64)
    registered = recon.registered_image_ids
    per_image = np.array([recon.images[i].num_points3D for i in registered], np.int64)
    _, errors = recon.reprojection_errors()
    cameras = []
    for cam in sorted(recon.cameras.values(), key=lambda c: c.camera_id):
        values = params_to_colmap(cam.model, cam.params)
        cameras.append({"camera_id": cam.camera_id, "model": cam.model, "width": cam.width, "height": cam.height,
                        "params": dict(zip(model_spec(cam.model).param_names, (float(v) for v in values)))})
    return {
        "cameras": cameras,
        "images": len(recon.images),
        "registered_images": len(registered),
        "points": len(recon.points3D),
        "observations": int(track.sum()),
        "mean_track_length": float(track.mean()) if len(track) else 0.0,
        "mean_observations_per_image": float(per_image.mean()) if len(per_image) else 0.0,
        "mean_reprojection_error": float(errors.mean()) if len(errors) else float("nan"),
        "median_reprojection_error": float(np.median(errors)) if len(errors) else float("nan"),
        "georegistered": georegistration is not None,
        "georegistration": georegistration,
    }
