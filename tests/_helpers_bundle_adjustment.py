"""Synthetic bundle-adjustment scenes shared by the bundle-adjustment tests.

A ring of cameras looking at a cube of points, every point seen by every camera, observations
exact or with Gaussian pixel noise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from backend.camera_models import project

SIMPLE_RADIAL = ("SIMPLE_RADIAL", np.array([500.0, 320.0, 240.0, -0.05]))


def ring_scene(model=SIMPLE_RADIAL, n_images=10, n_points=300, noise=0.0, seed=0) -> dict:
    """Cameras on a (wavy) ring of radius 6 looking at the origin; points in a 3 m cube."""
    rng = np.random.default_rng(seed)
    rotations, translations = [], []
    for a in np.linspace(0, 2 * np.pi, n_images, endpoint=False):
        centre = np.array([6 * np.cos(a), 6 * np.sin(a), 0.5 * np.sin(3 * a)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        rotation = np.stack([x, np.cross(z, x), z])
        rotations.append(rotation)
        translations.append(-rotation @ centre)
    scene = {
        "camera_models": [model[0]],
        "camera_params": [model[1].copy()],
        "image_camera": np.zeros(n_images, int),
        "rotations": np.array(rotations),
        "translations": np.array(translations),
        "points": rng.uniform(-1.5, 1.5, (n_points, 3)),
        "obs_image": np.repeat(np.arange(n_images), n_points),
        "obs_point": np.tile(np.arange(n_points), n_images),
    }
    xy = observe(scene)
    scene["obs_xy"] = xy + rng.normal(0.0, noise, xy.shape)
    return scene


def observe(scene: dict) -> np.ndarray:
    """The exact pixel (M, 2) of every observation of ``scene`` (NaN behind its camera)."""
    x_cam = np.einsum("mij,mj->mi", scene["rotations"][scene["obs_image"]], scene["points"][scene["obs_point"]])
    x_cam += scene["translations"][scene["obs_image"]]
    cams = np.asarray(scene["image_camera"])[scene["obs_image"]]
    xy = np.zeros((len(x_cam), 2))
    for c in np.unique(cams):
        sel = cams == c
        xy[sel] = project(scene["camera_models"][c], scene["camera_params"][c], x_cam[sel])
    return xy


def perturb(scene: dict, seed=1, rot_deg=1.0, trans_frac=0.03, point_sigma=0.05, keep=(0,)) -> dict:
    """Rotate each pose by ~rot_deg, move it by trans_frac of |t|, jitter the points."""
    rng = np.random.default_rng(seed)
    rotations, translations = scene["rotations"].copy(), scene["translations"].copy()
    for i in range(len(rotations)):
        if i in keep:
            continue
        axis = rng.normal(size=3)
        delta = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(rot_deg))
        rotations[i] = delta.as_matrix() @ rotations[i]
        translations[i] += (
            rng.normal(size=3) / np.sqrt(3) * trans_frac * np.linalg.norm(translations[i])
        )
    points = scene["points"] + rng.normal(0.0, point_sigma, scene["points"].shape)
    return {**scene, "rotations": rotations, "translations": translations, "points": points}
