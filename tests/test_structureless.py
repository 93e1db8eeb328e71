"""Registration without PnP (sfm.mapper.structureless) on a synthetic street with exact ground truth."""

from __future__ import annotations

import numpy as np

from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MapperState
from sfm.stages.payloads import load_payloads
from sfm.mapper.structureless import register_structureless
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def _seeded_street(tmp_path, outlier_ratio: float):
    """A 10-image synthetic street with images 3 and 6 registered at their true poses and
    their points triangulated: (state, GT table, the two seed indices)."""
    run_synth(tmp_path, SynthOptions(scene="street", num_images=10, observations_per_image=600,
                                     outlier_ratio=outlier_ratio, seed=3))  # fmt: skip
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    seeds = [state.names.index(n) for n in ("street_00003.jpg", "street_00006.jpg")]
    for i in seeds:
        state.register(i, gt[state.names[i]].rotation, gt[state.names[i]].translation)
    state.triangulate_new(seeds[-1])
    return state, gt, seeds


def test_structureless_registration_recovers_pose_and_baseline(tmp_path):
    """Seeded with two images at their true poses and a tenth of their triangulated points
    (too few for PnP), the images registered from an essential matrix and the points they see
    get their true rotation and camera centre (the baseline length included)."""
    state, gt, seeds = _seeded_street(tmp_path, outlier_ratio=0.2)
    valid = np.flatnonzero(state.track_valid)
    state.track_valid[valid[np.arange(len(valid)) % 10 != 0]] = False  # too few points for PnP
    baseline = np.linalg.norm(_center(gt[state.names[seeds[0]]]) - _center(gt[state.names[seeds[1]]]))
    for _ in range(3):
        assert register_structureless(state)
        k = state.last_registered
        assert k not in seeds
        truth = gt[state.names[k]]
        assert _rotation_deg(state.R[k], truth.rotation) < 0.1
        assert np.linalg.norm(-state.R[k].T @ state.t[k] - _center(truth)) < 0.02 * baseline


def _center(pose) -> np.ndarray:
    return -pose.rotation.T @ pose.translation


def test_structureless_registration_needs_a_registered_neighbour(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="street", num_images=6, observations_per_image=400, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    assert not register_structureless(state)  # nothing registered yet


def test_structureless_registration_takes_images_pnp_failed_on_and_leaves_untried_ones(tmp_path):
    """An image seeing enough points for PnP is left to PnP until PnP has failed on it; then
    the fallback registers it at its true pose."""
    state, gt, seeds = _seeded_street(tmp_path, outlier_ratio=0.0)
    rich = [i for i in range(len(state.names)) if not state.registered[i]
            and len(state.visible_points(i)[0]) >= state.opts.abs_pose_min_num_inliers]
    assert rich
    for i in range(len(state.names)):  # only the PnP-ready images are left
        if not state.registered[i] and i not in rich:
            state.used[i] = True
    assert not register_structureless(state)  # PnP has not tried them
    k = rich[0]
    state.note_failure(k, len(state.visible_points(k)[0]))
    assert register_structureless(state)
    assert state.last_registered == k
    truth = gt[state.names[k]]
    assert _rotation_deg(state.R[k], truth.rotation) < 0.1
    baseline = np.linalg.norm(_center(gt[state.names[seeds[0]]]) - _center(gt[state.names[seeds[1]]]))
    assert np.linalg.norm(-state.R[k].T @ state.t[k] - _center(truth)) < 0.02 * baseline
