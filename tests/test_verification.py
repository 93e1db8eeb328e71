"""Two-view verification on synthetic correspondences with a known relative pose."""

from __future__ import annotations

import numpy as np
import pytest

from backend.camera_models import project
from sfm.io.database import Database
from sfm.io.database_schema import CameraRecord, TwoViewConfig
from backend.geometry import angle_between_deg, quaternion_to_rotation, rotation_about_axis, rotation_angle_deg
from sfm.matching.verification import (
    VerifyOptions,
    from_colmap_pixels,
    ransac_trials,
    refine_relative_pose,
    search_inliers,
    sampson_distances,
    sampson_gradients,
    to_colmap_pixels,
    verify_pair,
)

WIDTH, HEIGHT, FOCAL = 1600, 1200, 1000.0


def pinhole(prior: bool = True, model: str = "PINHOLE", k: float = 0.0) -> CameraRecord:
    cx, cy = (WIDTH - 1) / 2, (HEIGHT - 1) / 2
    params = [FOCAL, FOCAL, cx, cy] if model == "PINHOLE" else [FOCAL, cx, cy, k]
    return CameraRecord(1, model, WIDTH, HEIGHT, np.array(params), prior)


def two_view_scene(seed: int, camera: CameraRecord, n: int = 1000, outlier_ratio: float = 0.3,
                   noise_px: float = 0.5, planar: bool = False):  # fmt: skip
    """Keypoints of two views of n points (a plane when ``planar``), the first
    ``outlier_ratio * n`` matches replaced by random pixels in image 2. Returns
    (kp1, kp2, matches, is_true, c2_from_c1 rotation, translation)."""
    rng = np.random.default_rng(seed)
    rotation = rotation_about_axis(np.array([0.1, 1.0, 0.05]), 12.0)  # c2_from_c1
    translation = np.array([-1.5, 0.2, 0.3])
    u = rng.uniform(-0.7, 0.7, n)
    v = rng.uniform(-0.5, 0.5, n)
    depth = 6.0 + 0.3 * u + 0.2 * v if planar else rng.uniform(4.0, 10.0, n)
    points_c1 = np.stack([u * depth, v * depth, depth], axis=1)
    kp1 = project(camera.model, camera.params, points_c1)
    kp2 = project(camera.model, camera.params, points_c1 @ rotation.T + translation)
    kp1 += rng.normal(0, noise_px, kp1.shape)
    kp2 += rng.normal(0, noise_px, kp2.shape)
    num_out = int(outlier_ratio * n)
    kp2[:num_out] = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (num_out, 2))
    is_true = np.arange(n) >= num_out
    order = rng.permutation(n)  # matches in random order, keypoints indexed directly
    matches = np.stack([order, order], axis=1)
    return kp1.astype(np.float32), kp2.astype(np.float32), matches, is_true, rotation, translation


def inlier_stats(geometry, is_true):
    found = np.zeros(len(is_true), bool)
    found[geometry.inlier_matches[:, 0]] = True
    recall = np.count_nonzero(found & is_true) / np.count_nonzero(is_true)
    wrong = np.count_nonzero(found & ~is_true) / max(np.count_nonzero(found), 1)
    return recall, wrong


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_calibrated_pair_recovers_inliers_and_pose(seed):
    cam = pinhole()
    kp1, kp2, matches, is_true, rotation, translation = two_view_scene(seed, cam)
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=seed)
    assert g.config == TwoViewConfig.CALIBRATED
    recall, wrong = inlier_stats(g, is_true)
    assert recall >= 0.95 and wrong < 0.01
    # E on normalised coordinates satisfies the epipolar constraint of the true matches
    x1 = (kp1[is_true] - [cam.params[2], cam.params[3]]) / FOCAL
    x2 = (kp2[is_true] - [cam.params[2], cam.params[3]]) / FOCAL
    assert np.median(np.abs(sampson_distances(g.E, x1, x2))) * FOCAL < 0.5
    assert rotation_angle_deg(quaternion_to_rotation(g.qvec) @ rotation.T) < 0.1
    assert angle_between_deg(g.tvec, translation) < 1.0
    assert abs(np.linalg.norm(g.tvec) - 1.0) < 1e-9
    # E = [t]x R of the stored pose, F = K^-T E K^-1 (pixels, OpenCV convention)
    t = g.tvec
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    e_pose = tx @ quaternion_to_rotation(g.qvec)
    assert np.allclose(e_pose / np.linalg.norm(e_pose), g.E / np.linalg.norm(g.E), atol=1e-6)
    assert np.median(np.abs(sampson_distances(g.F, kp1[is_true], kp2[is_true]))) < 0.5


def test_calibrated_pair_with_radial_distortion():
    cam = pinhole(model="SIMPLE_RADIAL", k=-0.08)
    kp1, kp2, matches, is_true, rotation, _ = two_view_scene(3, cam)
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=3)
    recall, wrong = inlier_stats(g, is_true)
    assert g.config == TwoViewConfig.CALIBRATED and recall >= 0.95 and wrong < 0.01
    assert rotation_angle_deg(quaternion_to_rotation(g.qvec) @ rotation.T) < 0.1


def test_uncalibrated_pair_gives_accurate_fundamental_matrix():
    cam = pinhole(prior=False, model="SIMPLE_RADIAL")
    kp1, kp2, matches, is_true, _, _ = two_view_scene(4, cam)
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=4)
    assert g.config == TwoViewConfig.UNCALIBRATED and g.E is None and g.qvec is None
    recall, wrong = inlier_stats(g, is_true)
    assert recall >= 0.95 and wrong < 0.02
    # point-to-epipolar-line distance in image 2, true matches only
    h1 = np.c_[kp1[is_true], np.ones(is_true.sum())]
    lines = h1 @ g.F.T
    dist = np.abs(np.sum(lines[:, :2] * kp2[is_true], axis=1) + lines[:, 2]) / np.linalg.norm(
        lines[:, :2], axis=1
    )
    assert np.median(dist) < 1.0


def test_planar_scene_is_flagged_but_verified():
    cam = pinhole()
    kp1, kp2, matches, is_true, _, _ = two_view_scene(5, cam, planar=True)
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=5)
    assert g.config == TwoViewConfig.PLANAR_OR_PANORAMIC
    recall, wrong = inlier_stats(g, is_true)
    assert recall >= 0.95 and wrong < 0.01 and g.H is not None
    p = np.c_[kp1[is_true], np.ones(is_true.sum())] @ g.H.T
    assert np.median(np.linalg.norm(p[:, :2] / p[:, 2:] - kp2[is_true], axis=1)) < 1.0


def test_general_scene_is_not_planar():
    cam = pinhole()
    kp1, kp2, matches, _, _, _ = two_view_scene(6, cam)
    assert verify_pair(kp1, kp2, matches, cam, cam).config == TwoViewConfig.CALIBRATED


@pytest.mark.parametrize("prior", [True, False])
def test_too_few_or_random_matches_are_not_verified(prior):
    cam = pinhole(prior=prior, model="SIMPLE_RADIAL")
    kp1, kp2, matches, _, _, _ = two_view_scene(7, cam)
    few = verify_pair(kp1, kp2, matches[:10], cam, cam)
    assert few.config < 2 and few.num_inliers == 0
    kp1, kp2, matches, _, _, _ = two_view_scene(8, cam, n=200, outlier_ratio=1.0)
    rand = verify_pair(kp1, kp2, matches, cam, cam)
    assert rand.config < 2 and rand.num_inliers == 0
    strict = verify_pair(
        *two_view_scene(9, cam, n=100)[:3], cam, cam, VerifyOptions(min_num_inliers=80)
    )
    assert strict.config < 2 and strict.num_inliers == 0  # 70 true matches < 80


def test_ransac_trials_bound():
    # 5-point samples, half the matches needed, 99 %: log(0.01) / log(1 - 1/32) = 145.04
    assert ransac_trials(100, 50, 5, 0.99, 10_000) == 146
    assert ransac_trials(20, 15, 7, 0.999, 10_000) == 49  # 0.75^7 = 0.1335
    assert ransac_trials(1000, 15, 5, 0.999, 10_000) == 10_000  # the cap
    assert ransac_trials(15, 15, 5, 0.999, 10_000) == 1  # every match must be an inlier
    assert ransac_trials(0, 15, 5, 0.999, 10_000) == 1


def test_search_is_sized_for_the_weakest_trusted_edge():
    """GLOMAP's trusted edge (30 inliers, a quarter of the matches), at least min_num_inliers,
    half the matches below 60, so the search never shrinks as the matches grow."""
    assert search_inliers(20, 15) == 15 and search_inliers(30, 15) == 15
    assert search_inliers(40, 15) == 20 and search_inliers(60, 15) == 30 and search_inliers(64, 15) == 30
    assert search_inliers(200, 15) == 50 and search_inliers(1000, 15) == 250
    assert search_inliers(64, 40) == 40  # a stricter min_num_inliers wins
    counts = [search_inliers(n, 15) for n in range(15, 2000)]
    assert all(b >= a for a, b in zip(counts, counts[1:]))
    trials = [ransac_trials(n, search_inliers(n, 15), 5, 0.999, 10_000) for n in range(15, 2000)]
    assert all(b >= a for a, b in zip(trials, trials[1:]))
    # 64 chance matches: (30/64)^5 = 0.02263, log(0.001) / log(1 - 0.02263) = 301.8; sized for
    # 15 inliers the same pair would take 9,764 iterations
    assert trials[64 - 15] == 302


@pytest.mark.parametrize("seed", [30, 31, 32])
def test_pair_at_the_trusted_inlier_ratio_is_verified(seed):
    """120 matches of which 30 true (a quarter: the search is sized for exactly this)."""
    cam = pinhole(prior=True, model="SIMPLE_RADIAL")
    kp1, kp2, matches, is_true, _, _ = two_view_scene(seed, cam, n=120, outlier_ratio=0.75)
    assert is_true.sum() == 30
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=seed)
    assert g.config == TwoViewConfig.CALIBRATED
    recall, wrong = inlier_stats(g, is_true)
    assert recall >= 0.9 and wrong <= 0.1


@pytest.mark.parametrize("prior", [True, False])
@pytest.mark.parametrize("seed", [20, 21, 22])
def test_small_pair_with_enough_inliers_is_verified(prior, seed):
    """The trial bound keeps small true pairs: 40 matches of which 24 are true (E or F)."""
    cam = pinhole(prior=prior, model="SIMPLE_RADIAL")
    kp1, kp2, matches, is_true, _, _ = two_view_scene(seed, cam, n=40, outlier_ratio=0.4)
    g = verify_pair(kp1, kp2, matches, cam, cam, seed=seed)
    assert g.config == (TwoViewConfig.CALIBRATED if prior else TwoViewConfig.UNCALIBRATED)
    recall, wrong = inlier_stats(g, is_true)
    assert recall >= 0.75 and wrong <= 0.1  # as with 10,000 trials: small samples, noisy E


def test_same_seed_same_result():
    cam = pinhole()
    kp1, kp2, matches, _, _, _ = two_view_scene(10, cam, outlier_ratio=0.5)
    a = verify_pair(kp1, kp2, matches, cam, cam, seed=11)
    b = verify_pair(kp1, kp2, matches, cam, cam, seed=11)
    assert np.array_equal(a.inlier_matches, b.inlier_matches) and np.array_equal(a.E, b.E)


def test_pixel_convention_of_stored_models(tmp_path):
    """F and H written in COLMAP's convention hold for COLMAP-convention keypoints (+0.5)."""
    cam = pinhole(prior=False, model="SIMPLE_RADIAL")
    kp1, kp2, matches, is_true, _, _ = two_view_scene(12, cam, planar=True)
    g = verify_pair(kp1, kp2, matches, cam, cam)
    c = to_colmap_pixels(g)
    r_opencv = sampson_distances(g.F, kp1[is_true], kp2[is_true])
    r_colmap = sampson_distances(c.F, kp1[is_true] + 0.5, kp2[is_true] + 0.5)
    assert np.allclose(r_opencv, r_colmap, atol=1e-6)
    p = np.c_[kp1[is_true] + 0.5, np.ones(is_true.sum())] @ c.H.T
    q = np.c_[kp1[is_true], np.ones(is_true.sum())] @ g.H.T
    assert np.allclose(p[:, :2] / p[:, 2:], q[:, :2] / q[:, 2:] + 0.5, atol=1e-6)
    with Database(tmp_path / "database.db") as db:
        db.write_two_view_geometry(1, 2, c)
        back = from_colmap_pixels(db.read_two_view_geometry(1, 2))
    assert np.allclose(back.F, g.F, atol=1e-12) and np.allclose(back.H, g.H, atol=1e-9)


# ------------------------------------------------------------------------------ pose refinement
def _skew(t):
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def normalised_pairs(seed: int, n: int = 400, noise: float = 0.0, outliers: int = 0):
    """Normalised image coordinates of n points seen by two cameras (c2_from_c1 known), with
    Gaussian noise (normalised units) and the first ``outliers`` of view 2 replaced by random ones."""
    rng = np.random.default_rng(seed)
    rotation = rotation_about_axis(np.array([0.2, 1.0, -0.1]), 9.0)
    translation = np.array([-1.0, 0.15, 0.2]) / np.linalg.norm([-1.0, 0.15, 0.2])
    points = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 9, n)])
    in2 = points @ rotation.T + translation
    x1 = points[:, :2] / points[:, 2:] + rng.normal(0, noise, (n, 2))
    x2 = in2[:, :2] / in2[:, 2:] + rng.normal(0, noise, (n, 2))
    x2[:outliers] = rng.uniform(-0.5, 0.5, (outliers, 2))
    return x1, x2, rotation, translation


def test_sampson_gradients_are_the_derivatives_of_the_distances():
    x1, x2, rotation, translation = normalised_pairs(0, n=50, noise=0.01)
    E = _skew(translation) @ rotation + 0.01 * np.random.default_rng(1).normal(size=(3, 3))
    distances, gradients = sampson_gradients(E, x1, x2)
    np.testing.assert_allclose(distances, sampson_distances(E, x1, x2), rtol=1e-12, atol=1e-15)
    h = 1e-7
    for k in range(9):
        step = np.zeros(9)
        step[k] = h
        plus = sampson_distances(E + step.reshape(3, 3), x1, x2)
        minus = sampson_distances(E - step.reshape(3, 3), x1, x2)
        np.testing.assert_allclose(gradients[:, k], (plus - minus) / (2 * h), rtol=1e-5, atol=1e-8)


def test_refinement_recovers_the_pose_from_a_perturbed_start():
    x1, x2, rotation, translation = normalised_pairs(2)
    start_r = rotation_about_axis(np.array([1.0, -0.3, 0.5]), 1.5) @ rotation
    start_t = translation + np.array([0.05, -0.04, 0.02])
    r, t = refine_relative_pose(start_r, start_t, x1, x2, scale=1000.0)
    assert rotation_angle_deg(r @ rotation.T) < 1e-6
    assert angle_between_deg(t, translation) < 1e-6
    assert np.linalg.norm(t) == pytest.approx(1.0)


def test_refinement_is_a_stationary_point_of_the_robust_cost_despite_outliers():
    """With noise and 20% outliers the Cauchy cost's gradient vanishes at the result (a
    central difference along each of the five pose parameters), and the pose stays within a
    small angle of the truth (0.05 degrees without the outliers, from the noise alone)."""
    x1, x2, rotation, translation = normalised_pairs(3, n=500, noise=0.5e-3, outliers=100)
    r, t = refine_relative_pose(np.eye(3) @ rotation_about_axis(np.array([0, 1.0, 0]), 0.8) @ rotation,
                                translation, x1, x2, scale=1000.0)
    tangent = np.linalg.svd(t.reshape(3, 1))[0][:, 1:]

    def cost(x):
        rx = rotation_about_axis(x[:3], np.degrees(np.linalg.norm(x[:3]))) if np.linalg.norm(x[:3]) else np.eye(3)
        tx = t + tangent @ x[3:]
        e = 1000.0 * sampson_distances(_skew(tx / np.linalg.norm(tx)) @ rx @ r, x1, x2)
        return np.sum(np.log1p(e * e))

    h = 1e-6
    grad = [(cost(h * e) - cost(-h * e)) / (2 * h) for e in np.eye(5)]
    assert np.max(np.abs(grad)) < 1e-3 * cost(np.zeros(5))
    assert rotation_angle_deg(r @ rotation.T) < 0.15
