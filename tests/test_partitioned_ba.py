"""The consensus BA over random track parts (backend.partitioned_ba) against one BA over all."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _helpers_bundle_adjustment import perturb, ring_scene
from scipy.spatial.transform import Rotation

from backend.ba_problem import BAOptions, BAProblem
from backend.bundle_adjustment import bundle_adjust
from backend.partitioned_ba import bundle_adjust_partitioned

OPTIONS = BAOptions(loss="none", relative_tolerance=1e-10, absolute_tolerance=0.0, gauge_pose=0)
LONG_FOCAL = ("SIMPLE_RADIAL", np.array([1000.0, 640.0, 480.0, -0.05]))


def rotation_gaps(a, b) -> np.ndarray:
    """Angle (deg) between the rotations of two results, camera by camera (same gauge)."""
    rel = np.einsum("nij,nkj->nik", a.rotations, b.rotations)
    return np.rad2deg(Rotation.from_matrix(rel).magnitude())


def test_exact_observations_give_the_truth():
    truth = ring_scene(LONG_FOCAL, n_images=8, n_points=240)
    start = perturb(truth, keep=(0,))
    result = bundle_adjust_partitioned(BAProblem(**start), num_parts=3, options=OPTIONS)
    assert rotation_gaps(result, replace_truth(truth)).max() < 1e-6
    assert np.allclose(result.camera_params[0], truth["camera_params"][0], rtol=1e-7, atol=1e-9)
    full = bundle_adjust(BAProblem(**start), options=OPTIONS)  # same gauge: the anchor pose and its scale prior
    assert np.abs(result.points - full.points).max() < 1e-6
    assert np.abs(result.translations - full.translations).max() < 1e-6
    assert result.final_rms < 1e-6 and result.num_observations == len(truth["obs_image"])


def replace_truth(truth: dict):
    """The truth in the result's layout (rotations attribute) for ``rotation_gaps``."""
    return type("Truth", (), {"rotations": truth["rotations"]})


@pytest.mark.parametrize("seed", [3, 4])
def test_the_mean_of_the_parts_is_near_the_full_bundle_adjustment(seed):
    """Each part alone lands about sqrt(K - 1) standard errors from the full BA; the mean of the
    K parts lands close to it (the divide-and-conquer estimator): less than half a part's gap,
    for the poses and for focal length and distortion."""
    truth = ring_scene(LONG_FOCAL, n_images=12, n_points=900, noise=1.0, seed=seed)
    start = perturb(truth, seed=seed, keep=(0,))
    full = bundle_adjust(BAProblem(**start), options=OPTIONS)
    consensus = bundle_adjust_partitioned(BAProblem(**start), num_parts=3, options=OPTIONS, seed=seed)
    third = np.isin(start["obs_point"], np.arange(0, 900, 3))
    part = bundle_adjust(BAProblem(**{**start, **{k: start[k][third] for k in ("obs_image", "obs_point", "obs_xy")}}), options=OPTIONS)
    assert rotation_gaps(consensus, full).max() < 0.5 * rotation_gaps(part, full).max()
    gap_part = np.abs(part.camera_params[0] - full.camera_params[0])
    gap_consensus = np.abs(consensus.camera_params[0] - full.camera_params[0])
    assert np.all(gap_consensus[[0, 3]] < 0.5 * gap_part[[0, 3]])  # focal, k1
    assert consensus.final_rms < 1.05 * full.final_rms


def test_fixed_poses_and_unseen_images_are_returned_as_given():
    truth = ring_scene(LONG_FOCAL, n_images=8, n_points=240, noise=0.5)
    start = perturb(truth, keep=(0, 1))
    seen = start["obs_image"] != 7  # image 7 has no observation
    start = {**start, **{k: start[k][seen] for k in ("obs_image", "obs_point", "obs_xy")}}
    result = bundle_adjust_partitioned(BAProblem(**start, fixed_poses=(0, 1)), num_parts=2, options=replace(OPTIONS, gauge_pose=None))
    for i in (0, 1, 7):
        assert np.array_equal(result.rotations[i], start["rotations"][i])
        assert np.array_equal(result.translations[i], start["translations"][i])
    assert rotation_gaps(result, replace_truth(truth))[2:7].max() < 0.1


def test_one_part_is_the_plain_bundle_adjustment():
    start = perturb(ring_scene(LONG_FOCAL, n_images=6, n_points=120, noise=0.5))
    one = bundle_adjust_partitioned(BAProblem(**start), num_parts=1, options=OPTIONS)
    plain = bundle_adjust(BAProblem(**start), options=OPTIONS)
    assert np.array_equal(one.rotations, plain.rotations) and np.array_equal(one.points, plain.points)


def test_observation_sigmas_reach_every_part():
    """Every part weighs its observations by their own sigmas: 10% of the observations moved
    by 20 px and given a 1000 px sigma leave the parts' mean at the truth, where equal weights
    (no robust loss) are pulled away."""
    truth = ring_scene(LONG_FOCAL, n_images=8, n_points=240, seed=9)
    rng = np.random.default_rng(10)
    bad = rng.random(len(truth["obs_xy"])) < 0.1
    corrupted = {**truth, "obs_xy": truth["obs_xy"] + 20.0 * bad[:, None]}
    start = perturb(corrupted, keep=(0,))
    sigma = np.where(bad, 1000.0, 1.0)
    weighted = bundle_adjust_partitioned(BAProblem(**start, obs_sigma=sigma), num_parts=2, options=OPTIONS)
    plain = bundle_adjust_partitioned(BAProblem(**start), num_parts=2, options=OPTIONS)
    assert rotation_gaps(weighted, replace_truth(truth)).max() < 0.01
    assert rotation_gaps(plain, replace_truth(truth)).max() > 0.05
    with pytest.raises(ValueError, match="obs_sigma"):
        bundle_adjust_partitioned(BAProblem(**start, obs_sigma=sigma[:-1]), num_parts=2, options=OPTIONS)


def test_observation_budget_is_half_the_memory_over_the_bytes_per_observation(monkeypatch):
    """Without a budget, a BA is split only when one would take more than half of the
    machine's memory, at a cost per observation that grows with its track's length; unknown
    memory means no limit."""
    import backend.partitioned_ba as partitioned_ba

    per_obs = partitioned_ba.bytes_per_observation
    # every observation of a 5-view track costs 750 + 96 * 5 bytes; of a mix, the mean track of an observation
    assert per_obs(np.array([5, 5, 5])) == 750 + 96 * 5
    assert per_obs(np.array([2, 8])) == pytest.approx(750 + 96 * (4 + 64) / 10)
    assert per_obs() == 750 + 96 * 10
    short, long = np.full(1000, 5), np.full(100, 50)  # the same 5000 observations
    assert partitioned_ba.observations_in_memory(8 * 2**30, track_lengths=short) == int(2**32 / (750 + 480))
    assert partitioned_ba.observations_in_memory(8 * 2**30, track_lengths=long) == int(2**32 / (750 + 4800))
    assert partitioned_ba.observations_in_memory(8 * 2**30, share=0.25, track_lengths=short) == int(2**31 / 1230)
    monkeypatch.setattr(partitioned_ba, "physical_memory_bytes", lambda: 24 * 10**9)
    assert partitioned_ba.observations_in_memory(track_lengths=short) == int(12 * 10**9 / 1230)
    monkeypatch.setattr(partitioned_ba, "physical_memory_bytes", lambda: None)
    assert partitioned_ba.observations_in_memory() == 0
