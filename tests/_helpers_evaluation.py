"""Synthetic scenes with known answers shared by test_evaluation.py, test_alignment.py and
test_ground_truth.py: a ring of cameras, its GT poses, and the estimate as a known similarity of it."""

from __future__ import annotations

import numpy as np

from backend.camera_models import project
from backend.geometry import look_at, rotation_about_axis
from backend.sim3 import Sim3
from sfm.evaluation.ground_truth import GTPose
from sfm.core.model import Camera, Image, Reconstruction

N_CAMS = 20
SIM_EST_FROM_GT = Sim3(
    3.7, rotation_about_axis([0.3, -1.0, 0.5], 73.0), np.array([4.0, -2.5, 11.0])
)
UP = np.array([0.0, 0.0, 1.0])


def _ring_scene(n: int = N_CAMS, num_points: int = 30, seed: int = 0) -> Reconstruction:
    """``n`` cameras on a wavy ring of radius 5 looking at the origin, points near the origin
    seen by every camera at their exact projections (zero reprojection error)."""
    rng = np.random.default_rng(seed)
    recon = Reconstruction()
    recon.add_camera(Camera(1, "PINHOLE", 640, 480, [500.0, 510.0, 319.5, 239.5]))
    points = rng.uniform(-1.0, 1.0, size=(num_points, 3))
    for k in range(n):
        a = 2 * np.pi * k / n
        center = np.array([5 * np.cos(a), 5 * np.sin(a), 1.0 + 0.5 * np.sin(3 * a)])
        rotation, translation = look_at(center, np.zeros(3), UP)
        kps = project("PINHOLE", recon.cameras[1].params, points @ rotation.T + translation)
        recon.add_image(Image(k + 1, f"seq/img_{k:03d}.jpg", 1, rotation, translation, kps))
    for p, xyz in enumerate(points):
        recon.add_point3D(xyz, [(k + 1, p) for k in range(n)])
    return recon


def _gt_of(recon: Reconstruction) -> dict[str, GTPose]:
    k = recon.cameras[1].K
    return {
        im.name: GTPose(
            im.name, 640, 480, k, im.cam_from_world_rotation, im.cam_from_world_translation
        )
        for im in recon.images.values()
    }


def _estimate(recon: Reconstruction) -> Reconstruction:
    est = recon.copy()
    est.transform(SIM_EST_FROM_GT)
    return est
