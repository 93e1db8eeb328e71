"""Georegistration: a model moved onto GPS positions, or onto any table of reference centres.

A reconstruction is defined up to a similarity; GPS fixes it: :func:`georegister` estimates the
robust similarity ``enu_from_model`` from each image's camera centre to its GPS position in a
local east-north-up frame (``sfm.core.geodesy``; origin: the mean latitude, longitude and
altitude of the images with GPS, so coordinates stay small), in metres, with
:func:`sfm.evaluation.alignment.align_centers` (RANSAC over 3-point Umeyama fits, MSAC scoring,
refinement), inliers within ``max_error`` metres of their GPS position.  :func:`register_to_reference`
does the same for any reference table (COLMAP's model_aligner).

When it is not done (the model keeps its frame, and the reason is logged):

- fewer than three images of the model carry GPS, or fewer than three are inliers;
- the GPS positions spread over no more than ``max_error`` (the noise would set the scale).

Centres on (nearly) one line, a street walked along, leave the rotation about that line to the
GPS noise: when the inliers' GPS positions stray from their line by less than ``max_error``
(RMS), the rotation about it is taken instead from the cameras, held upright as people and
drones hold them (OpenSfM's "horizontal" orientation prior): their mean up direction (camera
-y) is turned towards ENU up.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from backend.geometry import rotation_about_axis
from backend.sim3 import Sim3
from sfm.core.geodesy import enu_from_wgs84
from sfm.core.model import Reconstruction
from sfm.evaluation.alignment import align_centers, scene_extent

logger = logging.getLogger(__name__)

#: Default inlier distance of GPS positions in metres: twice the 4.9 m (95%) horizontal accuracy
#: of the GPS standard positioning service, which phone and drone receivers reach in the open.
DEFAULT_GPS_MAX_ERROR = 10.0


@dataclass(frozen=True)
class Registration:
    """``target_from_model`` and how well it fits: images with a reference, inliers, RMS
    distance of the inliers' centres to their reference after the move (reference units),
    whether the rotation about the centres' line came from the upright cameras, and (GPS) the
    ENU origin ``(lat, lon, alt)``."""

    target_from_model: Sim3
    num_references: int
    num_inliers: int
    rms_error: float
    roll_from_upright: bool
    origin: tuple[float, float, float] | None = None

    def to_json(self) -> dict:
        out = {}
        if self.origin is not None:
            out.update({"frame": "ENU", "origin_lat": self.origin[0], "origin_lon": self.origin[1],
                        "origin_alt": self.origin[2]})
        return {**out, "units": "metres" if self.origin is not None else "reference units",
                "scale": self.target_from_model.scale, "num_gps_images" if self.origin else "num_reference_images":
                self.num_references, "num_inliers": self.num_inliers, "rms_error": self.rms_error,
                "roll_from_upright_cameras": self.roll_from_upright}


def _upright_roll(sim: Sim3, centers: np.ndarray, up_in_model: np.ndarray) -> Sim3:
    """``sim`` turned about the line of the moved ``centers`` (through their mean) so that the
    cameras' mean up direction points as close to +z as it can."""
    moved = sim.apply(centers)
    mid = moved.mean(axis=0)
    axis = np.linalg.svd(moved - mid)[2][0]
    up = (up_in_model @ sim.rotation.T).mean(axis=0)
    up_perp = up - (up @ axis) * axis
    z_perp = np.array([0.0, 0.0, 1.0]) - axis[2] * axis
    if np.linalg.norm(up_perp) < 1e-6 or np.linalg.norm(z_perp) < 1e-6:
        return sim  # the line is vertical, or the cameras look along it up or down: nothing to hold
    a, b = up_perp / np.linalg.norm(up_perp), z_perp / np.linalg.norm(z_perp)
    angle = np.degrees(np.arctan2(np.cross(a, b) @ axis, a @ b))
    turn = rotation_about_axis(axis, angle)
    return Sim3(sim.scale, turn @ sim.rotation, turn @ (sim.translation - mid) + mid)


def register_to_reference(centers: np.ndarray, up_in_model: np.ndarray, reference: np.ndarray,
                          max_error: float, seed: int = 0) -> tuple[Registration | None, str]:
    """The robust ``reference_from_model`` of camera ``centers`` (N, 3) onto ``reference``
    (N, 3), inliers within ``max_error`` (module docstring); ``up_in_model`` (N, 3): each
    camera's up direction.  ``(None, why)`` when it cannot be done."""
    centers, reference = np.asarray(centers, np.float64), np.asarray(reference, np.float64)
    if len(centers) < 3:
        return None, f"{len(centers)} image(s) with a reference position (3 needed)"
    spread = scene_extent(reference)
    if spread <= max_error:
        return None, f"the reference positions spread over {spread:.3g}, within their noise ({max_error:g})"
    sim, inliers = align_centers(centers, reference, threshold=max_error, seed=seed)
    if sim is None or inliers.sum() < 3:
        return None, f"{int(inliers.sum())} of {len(centers)} positions agree with the model (3 needed)"
    ref_in = reference[inliers]
    sv = np.linalg.svd(ref_in - ref_in.mean(axis=0), compute_uv=False)
    off_line = float(np.sqrt((sv[1:] ** 2).sum() / len(ref_in)))
    roll = off_line < max_error
    if roll:
        sim = _upright_roll(sim, centers[inliers], up_in_model[inliers])
    residuals = np.linalg.norm(sim.apply(centers[inliers]) - ref_in, axis=1)
    rms = float(np.sqrt(np.mean(residuals**2)))
    return Registration(sim, len(centers), int(inliers.sum()), rms, roll), ""


def model_centers_and_up(recon: Reconstruction, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres and up directions (camera -y in the world) of the named images."""
    images = [recon.image_by_name(n) for n in names]
    rotations = np.array([im.cam_from_world_rotation for im in images]).reshape(-1, 3, 3)
    translations = np.array([im.cam_from_world_translation for im in images]).reshape(-1, 3)
    centers = -np.einsum("nji,nj->ni", rotations, translations)
    return centers, -rotations[:, 1, :]


def georegister(recon: Reconstruction, gps: dict[str, np.ndarray], max_error: float = DEFAULT_GPS_MAX_ERROR,
                seed: int = 0) -> tuple[Registration | None, str]:
    """Georegister ``recon`` in place (module docstring): ``gps`` maps image names to
    ``(lat, lon, alt)``; images of the model without GPS are moved with the rest.  Returns the
    registration, or ``(None, why)`` and the model unchanged."""
    names = sorted(im.name for im in recon.images.values() if im.registered and im.name in gps)
    if len(names) < 3:
        return None, f"{len(names)} registered image(s) with GPS (3 needed)"
    lla = np.array([gps[n] for n in names], np.float64)
    origin = tuple(float(v) for v in lla.mean(axis=0))
    enu = enu_from_wgs84(lla, np.array(origin))
    centers, up = model_centers_and_up(recon, names)
    reg, why = register_to_reference(centers, up, enu, max_error, seed)
    if reg is None:
        return None, why
    reg = Registration(reg.target_from_model, reg.num_references, reg.num_inliers, reg.rms_error,
                       reg.roll_from_upright, origin)
    recon.transform(reg.target_from_model)
    logger.info("georegistered: %d of %d GPS positions within %g m, RMS %.2f m, scale %.4g%s", reg.num_inliers,
                reg.num_references, max_error, reg.rms_error, reg.target_from_model.scale,
                " (rotation about the street from upright cameras)" if reg.roll_from_upright else "")
    return reg, ""
