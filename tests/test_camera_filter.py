"""COLMAP's image filter after global BA (sfm.mapper.state.MapperState.drop_degenerate_cameras)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MapperState
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
