"""Track subset selection for large bundle adjustments, and re-estimating the other points with
the cameras held (backend/track_subset.py, sfm/mapper/triangulation.py: refine_points)."""

from __future__ import annotations

import numpy as np

from backend.track_subset import select_tracks
from backend.geometry import look_at
from sfm.mapper.triangulation import refine_points


def _random_observations(seed: int = 0, images: int = 6, points: int = 400):
    rng = np.random.default_rng(seed)
    obs_image, obs_point = [], []
    for p in range(points):
        seen = rng.choice(images, size=int(rng.integers(2, images + 1)), replace=False)
        obs_image += seen.tolist()
        obs_point += [p] * len(seen)
    obs_image, obs_point = np.array(obs_image), np.array(obs_point)
    xy = rng.uniform([0, 0], [640, 480], size=(len(obs_image), 2))
    err = rng.uniform(0, 2, size=len(obs_image))
    return obs_image, obs_point, xy, np.tile([640.0, 480.0], (images, 1)), err


def test_budget_above_the_observations_keeps_every_track():
    obs_image, obs_point, xy, size, err = _random_observations()
    sel = select_tracks(obs_image, obs_point, xy, size, err, 400, max_observations=len(obs_image))
    assert sel.all()


def test_first_level_is_the_longest_best_track_of_every_cell():
    obs_image, obs_point, xy, size, err = _random_observations()
    sel = select_tracks(obs_image, obs_point, xy, size, err, 400, max_observations=0, grid=4)
    length = np.bincount(obs_point)
    mean_err = np.bincount(obs_point, weights=err) / length
    cell = (obs_image * 4 + np.minimum(xy[:, 1] / 480 * 4, 3).astype(int)) * 4 + np.minimum(xy[:, 0] / 640 * 4, 3).astype(int)
    for c in np.unique(cell):
        pts = obs_point[cell == c]
        best = min(pts.tolist(), key=lambda p: (-length[p], mean_err[p], p))
        assert sel[best]
    assert sel.sum() < 400  # a subset, not everything


def test_larger_budgets_give_supersets_within_the_budget():
    obs_image, obs_point, xy, size, err = _random_observations(seed=1)
    floor = select_tracks(obs_image, obs_point, xy, size, err, 400, max_observations=0, grid=4)
    previous = floor
    for budget in (int(np.bincount(obs_point)[floor].sum()), 1500, 2000, 2500):
        sel = select_tracks(obs_image, obs_point, xy, size, err, 400, max_observations=budget, grid=4)
        assert np.all(sel[previous])  # nothing dropped as the budget grows
        assert np.bincount(obs_point)[sel].sum() <= budget
        previous = sel


def test_refine_points_with_held_cameras_is_exact_and_robust():
    rng = np.random.default_rng(3)
    centres = rng.uniform(-5, 5, size=(8, 3)) + [0, 0, -20]
    poses = [look_at(c, np.zeros(3), np.array([0.0, -1.0, 0.0])) for c in centres]
    rotations = np.array([r for r, _ in poses])
    translations = np.array([t for _, t in poses])
    truth = rng.uniform(-3, 3, size=(50, 3))
    owner = np.repeat(np.arange(50), 8)
    cam = np.tile(np.arange(8), 50)
    xc = np.einsum("oij,oj->oi", rotations[cam], truth[owner]) + translations[cam]
    xy = xc[:, :2] / xc[:, 2:]
    starts = np.arange(0, 401, 8)
    start = truth + rng.normal(scale=0.05, size=truth.shape)
    huber = np.full(len(xy), 1.0 / 1000)
    got = refine_points(rotations[cam], translations[cam], xy, starts, start, huber)
    np.testing.assert_allclose(got, truth, atol=1e-9)
    # One wild observation per point (100 px at f = 1000): Huber keeps the point near the truth,
    # plain least squares does not.
    wild = xy.copy()
    wild[starts[:-1]] += 0.1
    robust = refine_points(rotations[cam], translations[cam], wild, starts, start, huber, iterations=10)
    plain = refine_points(rotations[cam], translations[cam], wild, starts, start, np.full(len(xy), 1e6), iterations=10)
    err_robust = np.linalg.norm(robust - truth, axis=1)
    err_plain = np.linalg.norm(plain - truth, axis=1)
    assert np.median(err_robust) < 0.5 * np.median(err_plain)
