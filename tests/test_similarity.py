"""Pairwise similarity of two local models (paper 3.2.1) and its MSD weight (3.2.2, Eq. 10-11).

Scene: 20 cameras on a sphere of radius 8 looking at 500 points in a cube of side 4; model b is
model a mapped by a known Sim3 (scale 2.7), written independently of the module's helpers.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from backend.similarity import SimilarityOptions, estimate_similarity, mean_square_distance

SCALE = 2.7


def rot(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def angle_deg(r1, r2):
    return np.degrees(np.arccos(np.clip((np.trace(r1.T @ r2) - 1) / 2, -1, 1)))


def look_at(centre):
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])  # rows: camera axes in world -> cam_from_world R


def scene(rng, n_cams=20, n_points=500):
    dirs = rng.normal(size=(n_cams, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.2
    centres = 8 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    rotations = np.array([look_at(c) for c in centres])
    translations = -np.einsum("nij,nj->ni", rotations, centres)
    points = rng.uniform(-2, 2, size=(n_points, 3))
    return rotations, translations, points


def transform(sim_rot, sim_t, rotations, translations, points, scale=SCALE):
    """Model b of model a under X_b = s R X_a + t: R_b = R_a R^T, C_b = s R C_a + t."""
    centres = -np.einsum("nji,nj->ni", rotations, translations)
    rb = rotations @ sim_rot.T
    cb = scale * centres @ sim_rot.T + sim_t
    return rb, -np.einsum("nij,nj->ni", rb, cb), scale * points @ sim_rot.T + sim_t


@pytest.fixture
def pair():
    rng = np.random.default_rng(7)
    ra, ta, pa = scene(rng)
    sim_rot, sim_t = rot(rng.normal(size=3), 73.0), np.array([3.0, -1.5, 10.0])
    rb, tb, pb = transform(sim_rot, sim_t, ra, ta, pa)
    return {"ra": ra, "ta": ta, "pa": pa, "rb": rb, "tb": tb, "pb": pb, "R": sim_rot, "t": sim_t}


def centres_of(rotations, translations):
    return -np.einsum("nji,nj->ni", rotations, translations)


def with_centres(rotations, centres):
    return rotations, -np.einsum("nij,nj->ni", rotations, centres)


def test_exact_recovery(pair):
    p = pair
    res = estimate_similarity(p["ra"], p["ta"], p["rb"], p["tb"], p["pa"], p["pb"])
    assert res is not None
    assert abs(res.scale - SCALE) < 1e-9
    assert np.abs(res.rotation - p["R"]).max() < 1e-9
    assert np.allclose(res.translation, p["t"], atol=1e-9)
    assert res.camera_inliers.all() and res.num_inliers == 20 and res.num_points == 500
    assert res.msd < 1e-12 and res.mse_ab < 1e-12 and res.mse_ba < 1e-12
    assert res.extent_b == pytest.approx(SCALE * res.extent_a, rel=1e-9)


def test_noisy_recovery(pair):
    p, rng = pair, np.random.default_rng(1)
    cb = centres_of(p["rb"], p["tb"]) + rng.normal(
        scale=0.02 * SCALE, size=(20, 3)
    )  # ~0.3% of extent
    rb = np.array([r @ rot(rng.normal(size=3), 0.1) for r in p["rb"]])
    pb = p["pb"] + rng.normal(scale=0.01 * SCALE, size=p["pb"].shape)
    res = estimate_similarity(p["ra"], p["ta"], *with_centres(rb, cb), p["pa"], pb)
    assert res is not None and res.camera_inliers.all()
    assert abs(res.scale / SCALE - 1) < 0.005
    assert angle_deg(res.rotation, p["R"]) < 0.1
    assert np.linalg.norm(res.translation - p["t"]) < 0.05 * SCALE
    assert 0 < res.msd < SimilarityOptions().max_msd


def test_outlier_cameras_rejected_and_inliers_exact(pair):
    """30% of the common cameras corrupted: 3 moved far, 3 rotated by 30 degrees."""
    p, rng = pair, np.random.default_rng(2)
    cb, rb = centres_of(p["rb"], p["tb"]), p["rb"].copy()
    bad = np.zeros(20, bool)
    bad[[1, 5, 9, 13, 15, 18]] = True
    for k in (1, 9, 15):
        direction = rng.normal(size=3)
        cb[k] += 40.0 * SCALE * direction / np.linalg.norm(direction)
    for k in (5, 13, 18):
        rb[k] = rb[k] @ rot(rng.normal(size=3), 30.0)
    res = estimate_similarity(p["ra"], p["ta"], *with_centres(rb, cb), p["pa"], p["pb"])
    assert res is not None
    assert np.array_equal(res.camera_inliers, ~bad) and res.num_inliers == 14
    assert abs(res.scale - SCALE) < 1e-9
    assert np.abs(res.rotation - p["R"]).max() < 1e-9
    assert np.allclose(res.translation, p["t"], atol=1e-9)
    assert res.msd < 1e-12


def test_anchored_median_scale_survives_where_global_median_fails(pair):
    """8 of 20 cameras moved far: only 66/190 pairs join two inliers, so the paper's global
    median of Eq. 2 is wrong; the median anchored at an inlier camera is still exact."""
    p, rng = pair, np.random.default_rng(3)
    ca, cb = centres_of(p["ra"], p["ta"]), centres_of(p["rb"], p["tb"])
    bad = np.arange(20) % 5 < 2
    cb[bad] += 40.0 * SCALE * rng.normal(size=(8, 3))
    i, j = np.triu_indices(20, 1)
    global_median = np.median(
        np.linalg.norm(cb[i] - cb[j], axis=1) / np.linalg.norm(ca[i] - ca[j], axis=1)
    )
    assert abs(global_median / SCALE - 1) > 0.2
    res = estimate_similarity(p["ra"], p["ta"], *with_centres(p["rb"], cb))
    assert res is not None and np.array_equal(res.camera_inliers, ~bad)
    assert abs(res.scale - SCALE) < 1e-9


@pytest.mark.parametrize("refit", [False, True])
def test_two_common_cameras_use_orientations(pair, refit):
    p = pair
    opts = SimilarityOptions(refit_rotation_on_centres=refit)
    res = estimate_similarity(p["ra"][:2], p["ta"][:2], p["rb"][:2], p["tb"][:2], options=opts)
    assert res is not None and res.num_inliers == 2 and res.num_points == 0
    assert abs(res.scale - SCALE) < 1e-9
    assert np.abs(res.rotation - p["R"]).max() < 1e-9
    assert np.allclose(res.translation, p["t"], atol=1e-9)


def test_collinear_centres_keep_orientation_rotation(pair):
    p = pair
    centres = np.outer(np.arange(5.0), [1.0, 0.5, 0.0]) + [0.0, 0.0, 6.0]
    ra, ta = with_centres(p["ra"][:5], centres)
    rb, tb, _ = transform(p["R"], p["t"], ra, ta, np.zeros((0, 3)))
    res = estimate_similarity(
        ra, ta, rb, tb, options=SimilarityOptions(refit_rotation_on_centres=True)
    )
    assert res is not None and np.abs(res.rotation - p["R"]).max() < 1e-9


def test_refit_rotation_on_centres_is_exact_and_close_under_noise(pair):
    p, rng = pair, np.random.default_rng(4)
    opts = SimilarityOptions(refit_rotation_on_centres=True)
    res = estimate_similarity(p["ra"], p["ta"], p["rb"], p["tb"], options=opts)
    assert np.abs(res.rotation - p["R"]).max() < 1e-9
    cb = centres_of(p["rb"], p["tb"]) + rng.normal(scale=0.02 * SCALE, size=(20, 3))
    res = estimate_similarity(p["ra"], p["ta"], *with_centres(p["rb"], cb), options=opts)
    assert res.camera_inliers.all() and 0 < angle_deg(res.rotation, p["R"]) < 0.2


def test_too_few_cameras_or_inliers_give_none(pair):
    p = pair
    assert estimate_similarity(p["ra"][:1], p["ta"][:1], p["rb"][:1], p["tb"][:1]) is None
    assert (
        estimate_similarity(
            np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3))
        )
        is None
    )
    opts = SimilarityOptions(min_common_cameras=3)
    assert (
        estimate_similarity(p["ra"][:2], p["ta"][:2], p["rb"][:2], p["tb"][:2], options=opts)
        is None
    )
    rb = p["rb"][:3].copy()
    rb[1] = rb[1] @ rot([0, 0, 1], 30.0)
    rb[2] = rb[2] @ rot([1, 0, 0], 30.0)  # every camera disagrees with the others
    assert estimate_similarity(p["ra"][:3], p["ta"][:3], rb, p["tb"][:3]) is None
    same = np.repeat(p["ta"][:1], 3, axis=0)  # three cameras at one centre: no scale
    assert (
        estimate_similarity(
            np.repeat(p["ra"][:1], 3, 0),
            same,
            np.repeat(p["rb"][:1], 3, 0),
            np.repeat(p["tb"][:1], 3, 0),
        )
        is None
    )


def test_msd_grows_with_point_noise(pair):
    p, rng = pair, np.random.default_rng(5)
    noise = rng.normal(size=p["pb"].shape)
    msds = []
    for sigma in (0.0, 0.01, 0.05, 0.2):
        res = estimate_similarity(
            p["ra"], p["ta"], p["rb"], p["tb"], p["pa"], p["pb"] + sigma * noise
        )
        msds.append(res.msd)
        assert abs(res.scale - SCALE) < 1e-9  # the transform comes from the cameras alone
    assert msds[0] < 1e-12 and all(x < y for x, y in itertools.pairwise(msds))
    # Eq. 10 literally, normalised by the target extent: 1/(2n) sqrt(sum |e|^2) / extent_b.
    n = 500 + 20  # common points plus inlier camera centres
    expected = 0.2 * np.sqrt((noise**2).sum()) / (2 * n) / res.extent_b
    assert res.mse_ab == pytest.approx(expected, rel=1e-9)


def test_msd_is_scale_invariant(pair):
    p, rng = pair, np.random.default_rng(6)
    cb = centres_of(p["rb"], p["tb"]) + rng.normal(scale=0.02, size=(20, 3))
    rb, tb = with_centres(p["rb"], cb)
    pb = p["pb"] + rng.normal(scale=0.05, size=p["pb"].shape)
    res1 = estimate_similarity(p["ra"], p["ta"], rb, tb, p["pa"], pb)
    res10 = estimate_similarity(p["ra"], 10 * p["ta"], rb, 10 * tb, 10 * p["pa"], 10 * pb)
    assert res1.msd > 1e-6
    assert res10.msd == pytest.approx(res1.msd, rel=1e-9)
    assert res10.scale == pytest.approx(res1.scale, rel=1e-9)
    assert np.allclose(res10.translation, 10 * res1.translation, atol=1e-8)


def test_mean_square_distance_literal_and_symmetric_max(pair):
    # One point: T X_a = (2,0,0) vs X_b = (3,0,0): |e| = 1, 1/(2n) = 1/2; back: T^-1 X_b = 1.5 vs 1.
    ab, ba = mean_square_distance(2.0, np.eye(3), np.zeros(3), [[1.0, 0, 0]], [[3.0, 0, 0]])
    assert (ab, ba) == pytest.approx((0.5, 0.25))
    ab, ba = mean_square_distance(
        1.0, np.eye(3), np.zeros(3), [[0.0, 0, 0], [0, 0, 0]], [[3.0, 0, 0], [0, 4.0, 0]]
    )
    assert (ab, ba) == pytest.approx((5 / 4, 5 / 4))
    assert mean_square_distance(
        1.0, np.eye(3), np.zeros(3), np.zeros((0, 3)), np.zeros((0, 3))
    ) == (0.0, 0.0)
    p, rng = pair, np.random.default_rng(8)
    cb = centres_of(p["rb"], p["tb"]) + rng.normal(scale=0.05, size=(20, 3))
    rb, tb = with_centres(p["rb"], cb)
    pb = p["pb"] + rng.normal(scale=0.05, size=p["pb"].shape)
    res = estimate_similarity(p["ra"], p["ta"], rb, tb, p["pa"], pb)
    assert res.mse_ab != res.mse_ba and res.msd == max(res.mse_ab, res.mse_ba)
    swapped = estimate_similarity(rb, tb, p["ra"], p["ta"], pb, p["pa"])  # a_from_b
    assert swapped.scale == pytest.approx(1 / res.scale, rel=1e-12)
    assert np.allclose(swapped.rotation, res.rotation.T, atol=1e-12)
    assert (swapped.mse_ab, swapped.mse_ba) == pytest.approx((res.mse_ba, res.mse_ab), rel=1e-9)
    assert swapped.msd == pytest.approx(res.msd, rel=1e-9)


def test_deterministic(pair):
    p, rng = pair, np.random.default_rng(9)
    cb = centres_of(p["rb"], p["tb"]) + rng.normal(scale=0.05, size=(20, 3))
    args = (p["ra"], p["ta"], *with_centres(p["rb"], cb), p["pa"], p["pb"])
    r1, r2 = estimate_similarity(*args), estimate_similarity(*args)
    assert r1.scale == r2.scale and r1.msd == r2.msd
    assert np.array_equal(r1.rotation, r2.rotation) and np.array_equal(
        r1.translation, r2.translation
    )
    # More cameras than max_hypotheses: a seeded sample, the same for the same seed.
    ra, ta, _ = scene(np.random.default_rng(10), n_cams=60, n_points=1)
    rb, tb, _ = transform(p["R"], p["t"], ra, ta, np.zeros((0, 3)))
    rb[::4] = rb[::4] @ rot([0, 1, 0], 30.0)
    opts = SimilarityOptions(max_hypotheses=10, seed=3)
    r1, r2 = (
        estimate_similarity(ra, ta, rb, tb, options=opts),
        estimate_similarity(ra, ta, rb, tb, options=opts),
    )
    assert np.array_equal(r1.camera_inliers, r2.camera_inliers) and r1.num_inliers == 45
    assert np.abs(r1.rotation - p["R"]).max() < 1e-9


def test_helpers_move_cameras_and_points(pair):
    p = pair
    res = estimate_similarity(p["ra"], p["ta"], p["rb"], p["tb"])
    sim = res.sim_b_from_a
    assert np.allclose(sim.apply(p["pa"]), p["pb"], atol=1e-9)
    for k in range(3):
        r, t = sim.transform_pose(p["ra"][k], p["ta"][k])
        assert np.allclose(r, p["rb"][k], atol=1e-12) and np.allclose(t, p["tb"][k], atol=1e-9)
    back = sim.inverse()
    assert np.allclose(back.apply(p["pb"]), p["pa"], atol=1e-9)
    with pytest.raises(ValueError):
        estimate_similarity(p["ra"], p["ta"], p["rb"], p["tb"], p["pa"], p["pb"][:10])
