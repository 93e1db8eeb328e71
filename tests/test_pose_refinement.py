"""Pose-only refinement (refine_pose in backend/pose_refinement.py) on the synthetic ring
scenes of _helpers_bundle_adjustment.py."""

from __future__ import annotations

import numpy as np
from _helpers_bundle_adjustment import perturb, ring_scene
from scipy.spatial.transform import Rotation

from backend.pose_refinement import refine_pose


def test_refine_pose_recovers_a_perturbed_pose():
    truth = ring_scene(n_points=200)
    image = 4
    rows = truth["obs_image"] == image
    model, params = truth["camera_models"][0], truth["camera_params"][0]
    start = perturb(truth, rot_deg=2.0, trans_frac=0.05, keep=())
    result = refine_pose(
        model,
        params,
        start["rotations"][image],
        start["translations"][image],
        truth["points"][truth["obs_point"][rows]],
        truth["obs_xy"][rows],
    )
    assert result.success and result.initial_rms > 5 and result.final_rms < 1e-8
    np.testing.assert_allclose(result.rotation, truth["rotations"][image], atol=1e-10)
    np.testing.assert_allclose(result.translation, truth["translations"][image], atol=1e-9)


def test_refine_pose_with_noise_and_outliers():
    truth = ring_scene(n_points=300, noise=0.5, seed=21)
    rows = np.flatnonzero(truth["obs_image"] == 2)
    xy = truth["obs_xy"][rows].copy()
    xy[::10] += 40.0
    start = perturb(truth, keep=())
    result = refine_pose(
        "SIMPLE_RADIAL",
        truth["camera_params"][0],
        start["rotations"][2],
        start["translations"][2],
        truth["points"][truth["obs_point"][rows]],
        xy,
        loss="cauchy",
    )
    angle = Rotation.from_matrix(result.rotation @ truth["rotations"][2].T).magnitude()
    assert np.rad2deg(angle) < 0.05
