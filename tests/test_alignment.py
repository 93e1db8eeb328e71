"""Tests of sfm.evaluation.alignment: the robust similarity between estimated and GT camera centres, alone
and through sfm.evaluation.metrics (outliers, small inputs, thresholds, collinear centres)."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers_evaluation import N_CAMS, SIM_EST_FROM_GT, UP, _estimate, _gt_of, _ring_scene

from sfm.evaluation.alignment import align_centers, default_alignment_threshold, scene_extent
from sfm.evaluation.metrics import evaluate
from backend.geometry import look_at
from backend.sim3 import umeyama
from sfm.evaluation.ground_truth import gt_from_reconstruction
from sfm.core.model import Camera, Image, Reconstruction


def _set_center(image: Image, center: np.ndarray) -> None:
    image.cam_from_world_translation = -image.cam_from_world_rotation @ center


# ------------------------------------------------------------------------- (d) outliers
def test_outlier_center_does_not_spoil_alignment():
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    est = _estimate(gt_recon)
    bad = est.image_by_name("seq/img_011.jpg")
    _set_center(bad, bad.center + np.array([60.0, -40.0, 25.0]))
    result = evaluate(est, gt)
    assert result.num_alignment_inliers == N_CAMS - 1
    for name, err in result.center_errors.items():
        assert err > 1.0 if name == bad.name else err < 1e-12
    assert max(result.rotation_errors_deg.values()) < 1e-9  # its rotation was not touched
    assert result.alignment.scale == pytest.approx(1 / 3.7, rel=1e-12)


def test_align_centers_many_outliers_random_sampling_is_exact_and_deterministic():
    rng = np.random.default_rng(5)
    gt_c = rng.normal(size=(60, 3)) * 10.0  # C(60, 3) > max_iterations: random samples
    est_c = SIM_EST_FROM_GT.apply(gt_c)
    outliers = rng.choice(60, 20, replace=False)
    est_c[outliers] += rng.normal(size=(20, 3)) * 30.0
    sim, mask = align_centers(est_c, gt_c, seed=3)
    sim2, mask2 = align_centers(est_c, gt_c, seed=3)
    assert np.array_equal(mask, mask2) and sim.scale == sim2.scale
    np.testing.assert_array_equal(sim.rotation, sim2.rotation)
    assert mask.sum() == 40 and not mask[outliers].any()
    inv = SIM_EST_FROM_GT.inverse()
    assert sim.scale == pytest.approx(inv.scale, rel=1e-12)
    np.testing.assert_allclose(sim.rotation, inv.rotation, atol=1e-12)
    np.testing.assert_allclose(sim.apply(est_c[mask]), gt_c[mask], atol=1e-10)


def test_align_centers_small_inputs_and_threshold():
    rng = np.random.default_rng(1)
    gt_c = rng.normal(size=(3, 3))
    est_c = SIM_EST_FROM_GT.apply(gt_c) + rng.normal(size=(3, 3)) * 0.01
    sim, mask = align_centers(est_c, gt_c, threshold=1e3)
    plain = umeyama(est_c, gt_c)
    assert sim.scale == pytest.approx(plain.scale, rel=1e-12) and mask.all()
    np.testing.assert_allclose(sim.rotation, plain.rotation, atol=1e-12)
    for n in (0, 1, 2):
        sim, mask = align_centers(gt_c[:n], gt_c[:n])
        assert sim is None and mask.shape == (n,) and not mask.any()
    with pytest.raises(ValueError):
        align_centers(np.zeros((4, 3)), np.zeros((5, 3)))
    # default threshold: 5% of the median distance to the median
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.stack([5 * np.cos(angles), 5 * np.sin(angles), np.zeros(8)], axis=1)
    assert default_alignment_threshold(ring) == pytest.approx(0.25)
    assert scene_extent(ring) == pytest.approx(10.0)


def test_collinear_centers_still_fit_and_are_flagged():
    recon = Reconstruction()
    recon.add_camera(Camera(1, "PINHOLE", 640, 480, [500.0, 500.0, 319.5, 239.5]))
    for k in range(6):  # a straight street: centres on the x axis, looking along +y
        center = np.array([2.0 * k, 0.0, 0.0])
        rotation, translation = look_at(center, center + np.array([0.0, 1.0, 0.0]), UP)
        recon.add_image(Image(k + 1, f"s{k}.jpg", 1, rotation, translation))
    gt = gt_from_reconstruction(recon)
    result = evaluate(_estimate(recon), gt)
    assert result.alignment_degenerate
    assert max(result.center_errors.values()) < 1e-12
    assert result.auc[1] == pytest.approx(1.0, abs=1e-9)  # relative poses need no alignment
