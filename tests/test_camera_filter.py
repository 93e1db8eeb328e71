"""COLMAP's image filter after global BA: images of degenerate cameras
(sfm.mapper.state.MapperState.drop_degenerate_cameras) and images left without the points that
fix their poses (MapperState.drop_unsupported_images) leave the model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.incremental import grow_and_refine
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MAX_REG_TRIALS, MIN_POSE_POINTS, MapperState
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    path = tmp_path_factory.mktemp("orbit")
    run_synth(path, SynthOptions(scene="orbit", num_images=24, observations_per_image=300, seed=5))
    return path


def _registered_state(path) -> MapperState:
    """Every image registered at its true pose, points triangulated."""
    gt = read_gt_table(path / "gt" / "cameras_gt_opencv.txt")
    [payload] = load_payloads(path / "database.db", None, fixed_intrinsics=False, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    for i, name in enumerate(state.names):
        state.register(i, gt[name].rotation, gt[name].translation)
    state.retriangulate()
    return state


def test_a_degenerate_camera_takes_its_images_out(orbit):
    state = _registered_state(orbit)
    prior = state.priors[0].params.copy()
    state.params[0] = prior * [20.0, 1, 1, 1]  # focal 20x the prior: > 10x the image size
    state.drop_degenerate_cameras()
    assert state.num_registered == 0 and not state.registered.any()
    assert not state.obs_inlier.any()
    np.testing.assert_array_equal(state.params[0], prior)  # back to the prior
    assert np.all(state.failed == 1)


def test_camera_filter_spares_young_models_fixed_cameras_and_merges(orbit):
    state = _registered_state(orbit)
    state.params[0] = state.priors[0].params * [20.0, 1, 1, 1]
    state.camera_filter = False  # the refinement of merged poses
    state.drop_degenerate_cameras()
    assert state.num_registered == 24
    state.camera_filter = True
    state.registered[20:] = False
    state.num_registered = 20 - 1  # below COLMAP's 20 images: the calibration still moves
    state.drop_degenerate_cameras()
    assert state.num_registered == 19
    fixed = _registered_state(orbit)
    fixed.priors[0] = dataclasses.replace(fixed.priors[0], fixed=True)  # given with --intrinsics
    fixed.params[0] = fixed.priors[0].params * [20.0, 1, 1, 1]
    fixed.drop_degenerate_cameras()  # the user's intrinsics are never reset
    assert fixed.num_registered == 24
    bogus_prior = _registered_state(orbit)
    bogus_prior.priors[0] = dataclasses.replace(bogus_prior.priors[0], params=bogus_prior.params[0] * [20.0, 1, 1, 1])
    bogus_prior.params[0] = bogus_prior.priors[0].params.copy()
    bogus_prior.drop_degenerate_cameras()  # already outside the limits as given: nothing to go back to
    assert bogus_prior.num_registered == 24


def _keep_rows(state: MapperState, i: int, count: int) -> None:
    """Image ``i`` keeps only ``count`` of its inlier rows, as after a BA's filtering."""
    rows = state.image_rows[i][state.obs_inlier[state.image_rows[i]]]
    state.obs_inlier[rows[count:]] = False


def test_an_image_left_with_too_few_points_leaves_and_may_register_again(orbit):
    state = _registered_state(orbit)
    _keep_rows(state, 3, MIN_POSE_POINTS - 1)  # two points: six pose unknowns, four equations
    _keep_rows(state, 7, MIN_POSE_POINTS)  # three: determined
    assert state.drop_unsupported_images() == [3]
    assert state.num_registered == 23 and not state.registered[3] and state.registered[7]
    assert not state.obs_inlier[state.image_rows[3]].any()
    assert state.unsupported[3] == 1 and state.failed[3] == 0
    assert 3 in state.next_image_candidates()  # PnP may take it again at once
    for drop in range(2, MAX_REG_TRIALS + 1):  # registered again and dropped again
        state.register(3, state.R[3], state.t[3])
        _keep_rows(state, 3, 0)
        assert state.drop_unsupported_images() == [3] and state.unsupported[3] == drop
    assert state.failed[3] == 1  # now a failed registration: retried once it sees 20% more points
    assert 3 not in state.next_image_candidates()
    assert state.structureless_failed[3] == state.fail_visible[3] > 0  # structure-less registration waits too
    assert state.drop_unsupported_images() == []


def test_the_point_filter_spares_merges_and_two_image_models(orbit):
    state = _registered_state(orbit)
    _keep_rows(state, 3, 0)
    state.camera_filter = False  # the refinement of merged poses: nothing registers it again
    assert state.drop_unsupported_images() == [] and state.registered[3]
    state.camera_filter = True
    state.registered[2:] = False
    state.num_registered = 2
    _keep_rows(state, 0, 0)
    assert state.drop_unsupported_images() == []  # a model keeps two images


def test_a_registered_image_whose_points_all_failed_is_posed_again_by_pnp(orbit):
    gt = read_gt_table(orbit / "gt" / "cameras_gt_opencv.txt")
    state = _registered_state(orbit)
    adjuster = BundleAdjuster(state)
    tilt = np.array([[1, 0, 0], [0, np.cos(1.0), -np.sin(1.0)], [0, np.sin(1.0), np.cos(1.0)]])
    state.R[5] = tilt @ state.R[5]  # a pose 57 degrees off, as a wrong join leaves it
    _keep_rows(state, 5, 0)  # every row it saw rejected
    grow_and_refine(state, adjuster, None, lambda: None)
    assert state.registered[5] and state.num_registered == 24
    assert state.unsupported[5] == 1
    errors = [np.degrees(np.arccos(np.clip((np.trace(state.R[i] @ gt[n].rotation.T) - 1) / 2, -1, 1)))
              for i, n in enumerate(state.names)]
    # registered where the others are: its error is theirs (the model's frame drifts from the
    # GT's in the final BA), not the 57 degrees it held
    assert errors[5] < 2 * np.median(errors) + 0.01
    assert state.obs_inlier[state.image_rows[5]].sum() >= 30
