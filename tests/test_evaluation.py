"""Tests of sfm.evaluation.metrics (pose errors, pair errors, AUC, structure metrics) on synthetic scenes
with known answers. The alignment is tested in test_alignment.py, the GT input in
test_ground_truth.py."""

from __future__ import annotations

import json
import math
from itertools import combinations

import numpy as np
import pytest
from _helpers_evaluation import N_CAMS, SIM_EST_FROM_GT, _estimate, _gt_of, _ring_scene

from sfm.evaluation.metrics import auc, evaluate, relative_pose_errors
from backend.geometry import angle_between_deg, quaternion_to_rotation, rotation_about_axis, rotation_angle_deg
from sfm.evaluation.ground_truth import GTPose
from sfm.core.model import Image, Reconstruction

N_PAIRS = N_CAMS * (N_CAMS - 1) // 2


def _arrays(est: Reconstruction, gt: dict[str, GTPose]):
    names = sorted(gt)
    images = {im.name: im for im in est.images.values()}
    return (
        names,
        np.stack([images[k].cam_from_world_rotation for k in names]),
        np.stack([images[k].cam_from_world_translation for k in names]),
        np.stack([gt[k].rotation for k in names]),
        np.stack([gt[k].translation for k in names]),
    )


def _set_rotation_keep_center(image: Image, rotation: np.ndarray) -> None:
    center = image.center
    image.cam_from_world_rotation = rotation
    image.cam_from_world_translation = -rotation @ center


# ------------------------------------------------------------------------- (a) exact model
def test_exact_model_under_sim3_has_zero_error_and_unit_auc():
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    result = evaluate(_estimate(gt_recon), gt)

    assert result.num_gt_images == N_CAMS and result.num_registered == N_CAMS
    assert result.registered_ratio == 1.0
    assert result.num_pairs == N_PAIRS
    assert len(result.rotation_errors_deg) == N_CAMS
    assert max(result.rotation_errors_deg.values()) < 1e-9
    assert max(result.center_errors.values()) < 1e-12
    assert abs(result.median_rotation_error_deg) < 1e-9
    assert abs(result.mean_rotation_error_deg) < 1e-9
    for t in (1, 5, 10):
        assert result.auc[t] == pytest.approx(1.0, abs=1e-9)
    # the alignment is the inverse of the applied similarity
    expected = SIM_EST_FROM_GT.inverse()
    assert result.alignment.scale == pytest.approx(expected.scale, rel=1e-12)
    np.testing.assert_allclose(result.alignment.rotation, expected.rotation, atol=1e-12)
    np.testing.assert_allclose(result.alignment.translation, expected.translation, atol=1e-10)
    assert result.num_alignment_inliers == N_CAMS and not result.alignment_degenerate
    # structure metrics
    assert result.num_points == 30 and result.mean_track_length == N_CAMS
    assert result.mean_reprojection_error < 1e-9
    # extent: the largest distance between two GT centres
    centers = np.stack([p.center for p in gt.values()])
    brute = max(np.linalg.norm(a - b) for a, b in combinations(centers, 2))
    assert result.scene_extent == pytest.approx(brute, rel=1e-12)
    # JSON round trip, strict (no NaN)
    d = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert d["auc@1"] == pytest.approx(1.0, abs=1e-9) and d["num_registered"] == N_CAMS
    assert d["alignment"]["scale"] == pytest.approx(1 / 3.7)
    assert set(d["rotation_errors_deg"]) == set(gt)
    assert "rotation_errors_deg" not in result.to_dict(per_image=False)


def test_exact_model_pair_errors_are_zero():
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    _, re, te, rg, tg = _arrays(_estimate(gt_recon), gt)
    errors = relative_pose_errors(re, te, rg, tg)
    assert errors.shape == (N_PAIRS,)
    assert errors.max() < 1e-9


# ------------------------------------------------------------------------- (b) one rotated camera
def test_one_camera_rotated_by_two_degrees():
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    est = _estimate(gt_recon)
    bad = est.image_by_name("seq/img_007.jpg")
    delta = rotation_about_axis([0.2, 0.9, -0.4], 2.0)
    _set_rotation_keep_center(bad, delta @ bad.cam_from_world_rotation)

    result = evaluate(est, gt)
    for name, err in result.rotation_errors_deg.items():
        if name == bad.name:
            assert err == pytest.approx(2.0, abs=1e-6)
        else:
            assert err < 1e-9
    assert max(result.center_errors.values()) < 1e-12
    assert result.mean_rotation_error_deg == pytest.approx(2.0 / N_CAMS, abs=1e-9)

    names, re, te, rg, tg = _arrays(est, gt)
    errors = relative_pose_errors(re, te, rg, tg)
    k = names.index(bad.name)
    for e, (i, j) in zip(errors, zip(*np.triu_indices(N_CAMS, 1))):
        assert e == pytest.approx(2.0, abs=1e-6) if k in (i, j) else e < 1e-9

    # 171 pairs at ~0 and 19 pairs at 2.0 degrees, by hand (trapezoids of the recall curve):
    good = (N_CAMS - 1) * (N_CAMS - 2) // 2
    assert result.auc[1] == pytest.approx(good / N_PAIRS, abs=1e-9)  # 0.9
    # (0, good/n) -> (2, (good+1)/n) trapezoid, then recall 1 from 2 to X
    ramp = 2.0 * (2 * good + 1) / (2 * N_PAIRS)
    assert result.auc[5] == pytest.approx((ramp + 3.0) / 5.0, abs=1e-9)
    assert result.auc[10] == pytest.approx((ramp + 8.0) / 10.0, abs=1e-9)


# ------------------------------------------------------------------------- (c) unregistered images
@pytest.mark.parametrize("how", ["flag", "remove"])
def test_unregistered_images_reduce_ratio_and_auc(how):
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    est = _estimate(gt_recon)
    k = 3
    for image_id in (2, 9, 15):
        if how == "flag":
            est.images[image_id].registered = False
            est.images[image_id].cam_from_world_translation = np.full(3, np.nan)
        else:
            est.remove_image(image_id)
    result = evaluate(est, gt)
    assert result.num_registered == N_CAMS - k
    assert result.registered_ratio == pytest.approx((N_CAMS - k) / N_CAMS)
    assert len(result.rotation_errors_deg) == N_CAMS - k
    assert result.num_pairs == N_PAIRS
    expected = (N_CAMS - k) * (N_CAMS - k - 1) / 2 / N_PAIRS  # 136 / 190
    for t in (1, 5, 10):
        assert result.auc[t] == pytest.approx(expected, abs=1e-9)
    assert max(result.rotation_errors_deg.values()) < 1e-9

    names, re, te, rg, tg = _arrays(_estimate(gt_recon), gt)
    removed = {"seq/img_001.jpg", "seq/img_008.jpg", "seq/img_014.jpg"}  # image ids 2, 9, 15
    registered = np.array([n not in removed for n in names])
    errors = relative_pose_errors(re, te, rg, tg, registered)
    assert np.isinf(errors).sum() == N_PAIRS - (N_CAMS - k) * (N_CAMS - k - 1) // 2


def test_extra_images_not_in_gt_are_only_counted():
    gt_recon = _ring_scene()
    gt = _gt_of(gt_recon)
    del gt["seq/img_004.jpg"]
    result = evaluate(_estimate(gt_recon), gt)
    assert result.num_gt_images == N_CAMS - 1 and result.num_registered == N_CAMS - 1
    assert result.num_registered_not_in_gt == 1 and result.auc[1] == pytest.approx(1.0, abs=1e-9)




# ------------------------------------------------------------------------- pair errors
def _reference_pair_errors(re, te, rg, tg, registered):
    """Per pair, straight from the definition (arccos-based helpers of backend.geometry)."""
    out = []
    for i, j in zip(*np.triu_indices(len(re), 1)):
        if not (registered[i] and registered[j]):
            out.append(np.inf)
            continue
        rel_e = re[j] @ re[i].T
        rel_g = rg[j] @ rg[i].T
        t_e = te[j] - rel_e @ te[i]
        t_g = tg[j] - rel_g @ tg[i]
        out.append(max(rotation_angle_deg(rel_e @ rel_g.T), float(angle_between_deg(t_e, t_g))))
    return np.array(out)


def test_relative_pose_errors_match_definition_and_are_block_independent():
    from sfm.evaluation.metrics import _pair_error_blocks, _prepare_poses

    rng = np.random.default_rng(7)
    n = 13
    rg = np.stack([quaternion_to_rotation(rng.normal(size=4)) for _ in range(n)])
    tg = rng.normal(size=(n, 3)) * 3
    re = np.stack([quaternion_to_rotation(rng.normal(size=4)) for _ in range(n)])
    te = rng.normal(size=(n, 3)) * 3
    registered = np.ones(n, dtype=bool)
    registered[[4, 9]] = False
    errors = relative_pose_errors(re, te, rg, tg, registered)
    expected = _reference_pair_errors(re, te, rg, tg, registered)
    np.testing.assert_allclose(errors, expected, atol=1e-9)
    rot_e, c_e, reg = _prepare_poses(re, te, registered)
    rot_g, c_g, _ = _prepare_poses(rg, tg, None)
    for block_size in (1, 5, 12, 40):
        blocks = np.concatenate(list(_pair_error_blocks(rot_e, c_e, rot_g, c_g, reg, block_size)))
        # equal up to rounding: numpy's vectorised kernels may sum in another order per block shape
        np.testing.assert_allclose(blocks, errors, rtol=0, atol=1e-12)


def test_zero_baselines():
    r0 = np.eye(3)
    r1 = rotation_about_axis([0, 0, 1], 10.0)
    # GT: cameras 0 and 1 share a centre (pure rotation); 2 elsewhere
    rg = np.stack([r0, r1, r0])
    cg = np.array([[0.0, 0, 0], [0, 0, 0], [1.0, 0, 0]])
    tg = -np.einsum("nij,nj->ni", rg, cg)
    # estimate: same rotations, pair (0, 1) exact; camera 2 put onto camera 0's centre
    re = np.stack([r0, rotation_about_axis([0, 0, 1], 13.0), r0])
    ce = np.array([[0.0, 0, 0], [0, 0, 0], [0.0, 0, 0]])
    te = -np.einsum("nij,nj->ni", re, ce)
    errors = relative_pose_errors(re, te, rg, tg)
    # (0,1): GT baseline zero -> rotation error only (3 deg);
    # (0,2), (1,2): estimated baseline zero, GT not -> 90
    np.testing.assert_allclose(errors, [3.0, 90.0, 90.0], atol=1e-9)


# ------------------------------------------------------------------------- (e) auc
def _hloc_pose_auc(errors, thresholds):
    """The reference implementation (hloc / SuperGlue), verbatim apart from np.trapz."""
    sort_idx = np.argsort(errors)
    errors = np.array(errors.copy())[sort_idx]
    recall = (np.arange(len(errors)) + 1) / len(errors)
    errors = np.r_[0.0, errors]
    recall = np.r_[0.0, recall]
    aucs = []
    for t in thresholds:
        last_index = np.searchsorted(errors, t)
        r = np.r_[recall[:last_index], recall[last_index - 1]]
        e = np.r_[errors[:last_index], t]
        aucs.append(np.sum(np.diff(e) * (r[1:] + r[:-1]) / 2) / t)
    return aucs


def test_auc_hand_computed():
    # recall curve (0,0) (0.5,.25) (2,.5) (3,.75) (20,1):
    # @1: .5*.25/2 + .5*.25 = .1875; @5: .0625 + 1.5*.75/2 + 1*1.25/2 + 2*.75 = 2.75 -> .55;
    # @10: .0625 + .5625 + .625 + 7*.75 = 6.5 -> .65
    assert auc([20.0, 0.5, 3.0, 2.0], [1, 5, 10]) == pytest.approx([0.1875, 0.55, 0.65], abs=1e-15)
    # all zero -> 1; all failures -> 0; errors equal to the threshold do not count
    assert auc([0.0, 0.0], [1.0]) == [1.0]
    assert auc([np.inf, np.nan, 7.0], [1, 5]) == [0.0, 0.0]
    assert auc([1.0, 1.0], [1.0]) == [0.0]
    # [1, inf]: @2: (0,0) (1,.5) then flat .5 to 2: .25 + .5 = .75 -> .375
    assert auc([1.0, np.inf], [2.0]) == pytest.approx([0.375])
    assert all(math.isnan(a) for a in auc([], [1, 5]))
    with pytest.raises(ValueError):
        auc([1.0], [0.0])


def test_auc_matches_reference_implementation():
    rng = np.random.default_rng(11)
    for _ in range(20):
        e = np.round(rng.exponential(4.0, size=rng.integers(1, 60)), 1)  # ties and exact hits
        e[rng.random(len(e)) < 0.2] = np.inf
        thresholds = [1.0, 2.5, 5.0, 10.0]
        np.testing.assert_allclose(auc(e, thresholds), _hloc_pose_auc(e, thresholds), atol=1e-12)



def test_absolute_rotation_angles_accurate_at_every_angle():
    from backend.geometry import rotation_angle_deg

    rng = np.random.default_rng(2)
    base = np.stack([quaternion_to_rotation(rng.normal(size=4)) for _ in range(7)])
    angles = np.array([0.0, 1e-7, 0.5, 2.0, 90.0, 179.9999, 180.0])
    deltas = np.stack([rotation_about_axis(rng.normal(size=3), a) for a in angles])
    measured = rotation_angle_deg(deltas @ base, base)
    np.testing.assert_allclose(measured, angles, atol=1e-10, rtol=1e-9)
