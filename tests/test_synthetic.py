"""Synthetic scenes: exact geometry, simulated matching statistics, database and GT outputs."""

from __future__ import annotations

import numpy as np
import pytest

from sfm.io.database import Database
from sfm.io.database_schema import TwoViewConfig
from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import read_gt_table
from backend.geometry import rotation_about_axis
from sfm.errors import InputError
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import gt_reconstruction, make_scene
from sfm.synthetic.matching import essential_matrix, simulate_matching


@pytest.mark.parametrize("scene", ["orbit", "street", "aerial"])
def test_scene_geometry_is_exact(scene):
    opts = SynthOptions(scene=scene, num_images=30, observations_per_image=400, pixel_noise=0.0, seed=3)
    s = make_scene(opts)
    per_image = np.bincount(s.obs_image, minlength=30)
    assert abs(per_image.mean() - 400) < 0.15 * 400, per_image.mean()
    assert np.bincount(s.obs_point).min() >= 2  # every point is seen twice or more
    recon = gt_reconstruction(s)
    assert recon.mean_reprojection_error() < 1e-9  # keypoints are the exact projections
    for i in range(30):  # distractors are in the image too
        kp = s.keypoints[i]
        assert (kp >= 0).all() and (kp[:, 0] <= opts.width - 1).all() and (kp[:, 1] <= opts.height - 1).all()


def test_noise_level_is_the_requested_one():
    s = make_scene(SynthOptions(num_images=20, observations_per_image=500, pixel_noise=0.5, seed=1))
    err = gt_reconstruction(s).mean_reprojection_error()
    assert abs(err - 0.5 * np.sqrt(np.pi / 2)) < 0.03  # mean of a 2D Gaussian's norm


def _true_match_mask(s, i, j, matches):
    point_of = [dict(zip(s.obs_keypoint[s.obs_image == k].tolist(), s.obs_point[s.obs_image == k].tolist())) for k in (i, j)]
    return np.array([point_of[0].get(a, -1) == point_of[1].get(b, -2) for a, b in matches])


def test_matching_statistics():
    opts = SynthOptions(num_images=40, observations_per_image=600, outlier_ratio=0.2, seed=2)
    s = make_scene(opts)
    pairs = simulate_matching(s, opts)
    raw_true = raw_all = ver_true = ver_all = kept_true = pair_true = 0
    K_inv = np.linalg.inv(s.K)
    for p in pairs:
        for m in (p.raw_matches, p.inlier_matches):  # one-to-one, like mutual-check matches
            assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)
        t_raw = _true_match_mask(s, p.image1, p.image2, p.raw_matches)
        assert t_raw.sum() == p.num_true
        raw_true += t_raw.sum()
        raw_all += len(t_raw)
        if len(p.inlier_matches) == 0:
            continue
        assert len(p.inlier_matches) >= opts.min_inliers
        t_ver = _true_match_mask(s, p.image1, p.image2, p.inlier_matches)
        kept_true += t_ver.sum()
        pair_true += p.num_true
        ver_true += t_ver.sum()
        ver_all += len(t_ver)
        # Surviving outliers lie near the epipolar line (they fooled RANSAC).
        bad = p.inlier_matches[~t_ver]
        if len(bad):
            F = K_inv.T @ essential_matrix(s, p.image1, p.image2) @ K_inv
            x1 = np.column_stack([s.keypoints[p.image1][bad[:, 0]], np.ones(len(bad))])
            x2 = np.column_stack([s.keypoints[p.image2][bad[:, 1]], np.ones(len(bad))])
            lines = x1 @ F.T
            dist = np.abs(np.sum(lines * x2, 1)) / np.linalg.norm(lines[:, :2], axis=1)
            assert dist.max() < 2.0
    assert abs(1 - raw_true / raw_all - 0.2) < 0.02
    assert 0.84 < kept_true / pair_true < 0.91  # recall below 100%: mean of U(0.80, 0.95)
    assert 0.02 < 1 - ver_true / ver_all < 0.04


def test_same_seed_same_scene_and_matches():
    opts = SynthOptions(num_images=15, observations_per_image=300, outlier_ratio=0.1, seed=7)
    a, b = make_scene(opts), make_scene(opts)
    assert all(np.array_equal(x, y) for x, y in zip(a.keypoints, b.keypoints))
    pa, pb = simulate_matching(a, opts), simulate_matching(b, opts)
    assert all(np.array_equal(x.raw_matches, y.raw_matches) and np.array_equal(x.inlier_matches, y.inlier_matches) for x, y in zip(pa, pb))
    c = make_scene(SynthOptions(num_images=15, observations_per_image=300, seed=8))
    assert not np.array_equal(a.keypoints[0], c.keypoints[0])


def test_run_synth_database_and_gt(tmp_path):
    opts = SynthOptions(scene="aerial", num_images=25, observations_per_image=400, outlier_ratio=0.2, seed=0)
    summary = run_synth(tmp_path, opts)
    assert summary["images"] == 25 and summary["verified_pairs"] > 25
    scene = make_scene(opts)
    with Database(tmp_path / "database.db", readonly=True) as db:
        images = db.read_images()
        assert [images[i].name for i in sorted(images)] == scene.names
        np.testing.assert_allclose(db.read_keypoints(3), scene.keypoints[2], atol=1e-3)
        [cam] = db.read_cameras().values()
        assert cam.prior_focal_length and cam.model == "SIMPLE_RADIAL"
        np.testing.assert_allclose(cam.params, [scene.focal, (scene.width - 1) / 2, (scene.height - 1) / 2, 0.0])
        geoms = db.read_two_view_geometries()
        assert len(geoms) == summary["verified_pairs"]
        (i1, i2), g = next(iter(geoms.items()))
        assert g.config == TwoViewConfig.CALIBRATED
        # E holds for the stored inliers in normalised coordinates (true ones exactly up to noise).
        k1 = np.linalg.solve(scene.K, np.column_stack([db.read_keypoints(i1)[g.inlier_matches[:, 0]], np.ones(g.num_inliers)]).T).T
        k2 = np.linalg.solve(scene.K, np.column_stack([db.read_keypoints(i2)[g.inlier_matches[:, 1]], np.ones(g.num_inliers)]).T).T
        residual = np.abs(np.sum(k2 * (k1 @ g.E.T), axis=1))
        assert np.median(residual) < 2e-3
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    assert sorted(gt) == scene.names
    np.testing.assert_allclose(gt[scene.names[4]].rotation, scene.rotations[4], atol=1e-12)
    with pytest.raises(InputError, match="exists"):
        run_synth(tmp_path, opts)


def test_evaluate_recovers_a_known_rotation_error(tmp_path):
    """The GT model scores perfectly; rotating one camera by 1.5 degrees is measured exactly."""
    from sfm.io.colmap_model import read_model

    run_synth(tmp_path, SynthOptions(num_images=20, observations_per_image=300, seed=4))
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    model = read_model(tmp_path / "gt" / "model")
    perfect = evaluate(model, gt)
    assert perfect.auc[1] == pytest.approx(1.0, abs=1e-9) and perfect.median_rotation_error_deg < 1e-9
    image = model.image_by_name("orbit_00007.jpg")
    center = image.center  # rotate the camera about its own centre
    image.cam_from_world_rotation = rotation_about_axis([0.3, -1, 0.2], 1.5) @ image.cam_from_world_rotation
    image.cam_from_world_translation = -image.cam_from_world_rotation @ center
    result = evaluate(model, gt)
    assert result.rotation_errors_deg["orbit_00007.jpg"] == pytest.approx(1.5, abs=1e-6)
    assert result.auc[1] == pytest.approx(171 / 190, abs=1e-9)  # its 19 pairs now err by >= 1.5 deg


def test_street_twins_match_with_the_apparent_geometry(tmp_path):
    """A street with twins: each copy is its original moved along the street (twin 0) or turned
    to face it from across the street (twin 1), and a pair whose images see the two copies is
    verified with the twin's matches, which satisfy the apparent epipolar geometry (camera 2
    moved by the twin's motion).  Along a straight street that geometry can be the true one's
    too (a shift along the direction of travel moves no epipolar line), so a twin's pairs look
    right to two-view verification, as in photos of a street."""
    opts = SynthOptions(scene="street", num_images=120, observations_per_image=600, seed=4, twins=2)
    s = make_scene(opts)
    labels, counts = np.unique(s.appearance, return_counts=True)
    copied = labels[counts == 2]
    assert len(copied) > 100  # the twins' points, each with one copy
    section = (opts.num_images - 1) / (2 * opts.twins)
    moved = turned = 0
    for label in copied:
        a, b = np.flatnonzero(s.appearance == label)
        d = s.points[b] - s.points[a]
        if abs(d[1]) < 1e-9:  # along the street, on the same facade
            moved += 1
            assert abs(abs(d[0]) - section) < 1e-9 and abs(d[2]) < 1e-9
        else:  # across the street: y and the facade's normal flip, the height stays
            turned += 1
            assert abs(s.points[a, 1] + s.points[b, 1]) < 1e-9 and abs(d[2]) < 1e-9
    assert moved > 50 and turned > 50
    pairs = simulate_matching(s, opts)
    twin_pairs = [p for p in pairs if p.twin_motion is not None and len(p.inlier_matches)]
    assert len(twin_pairs) > 20
    assert any(p.twin_motion[0][0, 0] < 0 for p in twin_pairs)  # the turned twin's pairs too
    K_inv = np.linalg.inv(s.K)
    for p in twin_pairs[:20]:
        x1 = np.column_stack([s.keypoints[p.image1][p.inlier_matches[:, 0]], np.ones(len(p.inlier_matches))])
        x2 = np.column_stack([s.keypoints[p.image2][p.inlier_matches[:, 1]], np.ones(len(p.inlier_matches))])
        lines = x1 @ (K_inv.T @ essential_matrix(s, p.image1, p.image2, p.twin_motion) @ K_inv).T
        dist = np.abs(np.sum(lines * x2, 1)) / np.linalg.norm(lines[:, :2], axis=1)
        assert np.median(dist) < 1.5 and np.mean(dist < 2.0) > 0.9, (p.image1, p.image2)
        points1 = s.obs_point[(s.obs_image == p.image1) & np.isin(s.obs_keypoint, p.inlier_matches[:, 0])]
        assert np.isin(points1, s.obs_point[s.obs_image == p.image2]).mean() < 0.5  # mostly other points
    with pytest.raises(InputError, match="too short"):
        run_synth(tmp_path / "short", SynthOptions(scene="street", num_images=40, twins=2))
    with pytest.raises(InputError, match="only the survey and street"):
        run_synth(tmp_path / "orbit", SynthOptions(scene="orbit", num_images=40, twins=1))
