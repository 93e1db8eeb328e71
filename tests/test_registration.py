"""Registering an image whose camera is new to the model (``sfm.mapper.registration``): the focal
length searched when it is a guess, then refined with the pose (and the first radial term), as
COLMAP's mapper estimates a camera no registered image has refined; the BAs that follow refine
such cameras and hold given ones alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from backend.camera_models import project
from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.options import MapperOptions
from sfm.mapper.payload import CameraPrior
from sfm.mapper.registration import (FOCAL_SEARCH_CANDIDATES, FOCAL_SEARCH_RANGE, _significant, refine_pose_and_camera,
                                    register_next, search_focal)
from sfm.mapper.state import MapperState
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions

WIDTH, HEIGHT = 1200, 900
# half the ratio between neighbouring candidates of the search
HALF_STEP = 0.5 * np.log(FOCAL_SEARCH_RANGE[1] / FOCAL_SEARCH_RANGE[0]) / (FOCAL_SEARCH_CANDIDATES - 1)


def _view(rng, focal: float, k1: float, num: int = 800, outliers: float = 0.4, noise: float = 0.5):
    """Points in front of a camera (cam_from_world R, t) and their pixels through SIMPLE_RADIAL
    (f, centre, k1), with Gaussian noise and a share of the pixels replaced by random ones."""
    R = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    t = np.array([0.3, -0.1, 0.5])
    points_cam = np.column_stack([rng.uniform(-2, 2, num), rng.uniform(-1.5, 1.5, num), rng.uniform(4, 8, num)])
    X = (points_cam - t) @ R  # world = R^T (x_cam - t)
    params = np.array([focal, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, k1])
    pixels = project("SIMPLE_RADIAL", params, points_cam) + rng.normal(0, noise, (num, 2))
    bad = rng.random(num) < outliers
    pixels[bad] = rng.uniform([0, 0], [WIDTH, HEIGHT], (int(bad.sum()), 2))
    return X, pixels, R, t, params, ~bad


def test_the_focal_search_finds_the_focal_length_a_guess_missed_by_far():
    """A 1.2 x width guess of a 700 px lens (an error of 106%) and 40% outliers: the search
    picks the candidate nearest the truth."""
    rng = np.random.default_rng(1)
    X, pixels, _, _, _, _ = _view(rng, 700.0, 0.0)
    guess = 1.2 * WIDTH
    prior = CameraPrior("SIMPLE_RADIAL", WIDTH, HEIGHT, np.array([guess, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, 0.0]))
    x_norm = (pixels - prior.params[1:3]) / guess
    found = search_focal(X, x_norm, guess, prior, 12.0, seed=0)
    assert found is not None and abs(np.log(found / 700.0)) <= HALF_STEP + 1e-9


@pytest.mark.parametrize("level", ["focal_radial", "focal"])
def test_pose_focal_and_radial_term_refined_together_on_the_inliers(level):
    rng = np.random.default_rng(2)
    k1 = -0.08 if level == "focal_radial" else 0.0
    X, pixels, R, t, truth, inliers = _view(rng, 900.0, k1, outliers=0.0, noise=0.3)
    start = truth.copy()
    start[0], start[3] = 900.0 * 1.08, 0.0  # a search's candidate: up to 8% off, no distortion
    R0 = Rotation.from_rotvec([0.003, 0.0, -0.002]).as_matrix() @ R
    R1, t1, params, covariance = refine_pose_and_camera(X, pixels, np.ones(len(X)), R0, t * 1.01, "SIMPLE_RADIAL",
                                                        start, level, "huber", 1.0)
    assert covariance.shape == ((2, 2) if level == "focal_radial" else (1, 1))
    assert np.sqrt(covariance[0, 0]) < 5.0  # px: a near, wide view determines its focal length
    assert abs(params[0] / 900.0 - 1) < 1e-3
    assert abs(params[3] - k1) < 2e-3
    np.testing.assert_allclose(params[1:3], truth[1:3])  # principal point held
    assert np.degrees(Rotation.from_matrix(R1 @ R.T).magnitude()) < 0.01
    np.testing.assert_allclose(t1, t, atol=2e-3)


def test_a_far_narrow_view_does_not_determine_its_focal_length():
    """Points 40 units away and 1 deep, seen at 1% of their distance across: the focal length
    trades against the distance, so a 20% change of it is within its 3-sigma test, while the
    near view above pins it to a few pixels."""
    rng = np.random.default_rng(3)
    num = 400
    points_cam = np.column_stack([rng.uniform(-0.2, 0.2, num), rng.uniform(-0.15, 0.15, num), rng.uniform(40, 41, num)])
    params = np.array([20000.0, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, 0.0])
    pixels = project("SIMPLE_RADIAL", params, points_cam) + rng.normal(0, 0.5, (num, 2))
    _, _, refined, covariance = refine_pose_and_camera(points_cam, pixels, np.ones(num), np.eye(3), np.zeros(3),
                                                       "SIMPLE_RADIAL", params, "focal", "huber", 1.0)
    assert not _significant(np.array([0.2 * refined[0]]), covariance)


def test_an_image_whose_view_leaves_a_bogus_camera_registers_with_the_prior(tmp_path, monkeypatch):
    """When the estimate is a camera no lens has (here a focal length of 20 x the image side),
    the image registers as before, with its camera at the prior."""
    import sfm.mapper.registration as registration

    state, _, focal = _per_image_state(tmp_path, shared=False)
    original = registration.refine_pose_and_camera

    def bogus(*args, **kwargs):
        R, t, params, covariance = original(*args, **kwargs)
        params = params.copy()
        params[0] = 20 * max(state.priors[2].width, state.priors[2].height)
        return R, t, params, covariance

    monkeypatch.setattr(registration, "refine_pose_and_camera", bogus)
    assert register_next(state)
    c = state.cam_index[state.last_registered]
    np.testing.assert_array_equal(state.params[c], state.priors[c].params)
    assert state.camera_focal(c) == pytest.approx(1.2 * focal)


def _per_image_state(tmp_path, shared: bool, opts: MapperOptions = MapperOptions()) -> tuple[MapperState, dict, float]:
    """The orbit scene's first two images posed from the ground truth, each with the exact camera
    given (held); every other image with a camera of its own (or, ``shared``, one for all) whose
    focal length is the 1.2 x longer side guess."""
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=12, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    exact = dataclasses.replace(payload.cameras[payload.camera_ids[0]], fixed=True)  # given, held
    guess = np.array(exact.params, dtype=np.float64)
    guess[0] = 1.2 * max(exact.width, exact.height)
    guessed = dataclasses.replace(exact, params=guess, prior_focal_length=False, fixed=False)
    n = len(payload.names)
    cameras = {0: exact, 1: exact}
    for k in range(2, n):
        cameras[2 if shared else k] = guessed
    ids = [0, 1] + [2 if shared else k for k in range(2, n)]
    state = MapperState(dataclasses.replace(payload, camera_ids=ids, cameras=cameras), opts)
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    a, b = gt[payload.names[0]], gt[payload.names[1]]
    R = b.rotation @ a.rotation.T
    state.start_model(0, 1, R, b.translation - R @ a.translation)
    return state, gt, float(exact.params[0])


def test_an_image_with_a_camera_of_its_own_registers_with_its_focal_length_estimated(tmp_path):
    """Registered against the initial pair's two-view points, the image's focal length is within
    2% of the truth and its rotation within 0.5 degrees; the guess it started from was 20% off,
    and registered with the guess the rotation misses that bound."""
    state, gt, focal = _per_image_state(tmp_path, shared=False)
    assert register_next(state)
    i = state.last_registered
    assert state.camera_focal(state.cam_index[i]) == pytest.approx(focal, rel=0.02)
    first, image = gt[state.names[0]], gt[state.names[i]]  # the model's frame is image 0's camera
    error = Rotation.from_matrix(state.R[i] @ (image.rotation @ first.rotation.T).T).magnitude()
    assert np.degrees(error) < 0.5


def test_a_camera_the_model_already_uses_is_left_as_the_model_has_it(tmp_path):
    """The first image of a shared guessed camera estimates it; the next ones of that camera
    register with the model's values, unchanged."""
    state, _, focal = _per_image_state(tmp_path, shared=True)
    assert register_next(state)
    assert state.cam_index[state.last_registered] == 2
    estimated = state.params[2].copy()
    assert estimated[0] == pytest.approx(focal, rel=0.02)
    assert register_next(state) and state.cam_index[state.last_registered] == 2
    np.testing.assert_array_equal(state.params[2], estimated)


def _grown(tmp_path, registrations: int, opts: MapperOptions = MapperOptions()) -> MapperState:
    """The one-camera-per-image state with ``registrations`` more images registered and
    triangulated."""
    state, _, _ = _per_image_state(tmp_path, shared=False, opts=opts)
    for _ in range(registrations):
        assert register_next(state)
        state.triangulate_new(state.last_registered)
    return state


def _adjustments(monkeypatch) -> list:
    """The (problem, refine levels) of every BA the mapper runs from now on."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    seen = []
    original = mapper_ba.bundle_adjust_partitioned

    def spy(problem, parts, options, **kwargs):
        seen.append((problem, options.refine_intrinsics))
        return original(problem, parts, options, **kwargs)

    monkeypatch.setattr(mapper_ba, "bundle_adjust_partitioned", spy)
    return seen


def test_a_local_ba_refines_the_cameras_whose_images_are_all_free_and_never_a_given_one(tmp_path, monkeypatch):
    """After a registration, the local BA refines each camera all of whose registered images are
    free in it (here one camera per image: the free images' own); the exact, given camera of the
    initial pair stays held, and no longer holds the others with it."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    state = _grown(tmp_path, 8, MapperOptions(local_ba_num_images=2))
    seen = _adjustments(monkeypatch)
    built = []
    original_problem = mapper_ba.BundleAdjuster.problem

    def problem_spy(self, *args, **kwargs):
        built.append(original_problem(self, *args, **kwargs))
        return built[-1]

    monkeypatch.setattr(mapper_ba.BundleAdjuster, "problem", problem_spy)
    mapper_ba.BundleAdjuster(state).local(state.last_registered)
    [(problem, levels)] = seen
    [(_, _, _, cameras)] = built  # the state's camera of each of the problem's cameras
    image_camera = np.asarray(problem.image_camera)
    free = np.ones(len(image_camera), dtype=bool)
    free[list(problem.fixed_poses)] = False
    assert free.sum() == 2 and (~free).sum() >= 1
    for local_camera, level in enumerate(levels):
        images = np.flatnonzero(image_camera == local_camera)
        if state.priors[cameras[local_camera]].fixed or np.any(~free[images]):
            assert level == "none", (local_camera, images)
        else:
            assert level == "focal_radial", (local_camera, images)
    assert any(level == "focal_radial" for level in levels)


def test_a_given_camera_is_held_alone_in_a_global_ba(tmp_path, monkeypatch):
    """With the initial pair's exact camera given (held), a growing global BA still refines the
    focal lengths of the other images' cameras (it used to hold every camera with it)."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    state = _grown(tmp_path, 3)
    seen = _adjustments(monkeypatch)
    mapper_ba.BundleAdjuster(state).global_()
    cameras = np.unique(state.cam_index[state.registered])
    given = [state.priors[c].fixed for c in cameras]
    assert any(given) and not all(given)
    assert tuple(seen[0][1]) == tuple("none" if g else "focal_radial" for g in given)
