"""The predicted-convergence stop of bundle adjustment (``BAOptions.predictive_stop``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _helpers_bundle_adjustment import perturb, ring_scene
from scipy.spatial.transform import Rotation

from backend.ba_problem import BAOptions, BAProblem
from backend.bundle_adjustment import bundle_adjust
from backend.gtsam_solver import predicted_rest


def test_predicted_rest_is_the_tail_of_a_geometric_series():
    assert predicted_rest([0.5, 0.05]) == pytest.approx(0.05 * 0.1 / 0.9)
    assert predicted_rest([0.9, 0.3, 0.1]) == pytest.approx(0.1 * (1 / 3) / (2 / 3))
    assert predicted_rest([0.5]) == float("inf")  # one iteration says nothing of the rate
    assert predicted_rest([0.01, 0.02]) == float("inf")  # decreases growing
    assert predicted_rest([0.01, 0.01]) == float("inf")  # a steady creep is never cut short
    assert predicted_rest([0.0, 0.0]) == float("inf")
    assert predicted_rest([0.5, -0.1]) == float("inf")  # the cost rose


@pytest.mark.parametrize("optimizer, keep, refine", [("lm", (0,), "focal_radial"),
                                                     ("gauss_newton_or_lm", (0, 4), "none")])
def test_predictive_stop_skips_the_confirming_iteration(optimizer, keep, refine):
    """From a perturbed start the decreases shrink fast: the predictive stop ends one iteration
    before the relative tolerance would, with that iteration's values (those of a run capped
    there), not the start's."""
    start = perturb(ring_scene(noise=0.5, seed=5), keep=keep)
    base = BAOptions(refine_intrinsics=refine, optimizer=optimizer, relative_tolerance=1e-3)
    problem = BAProblem(**start, fixed_poses=keep if len(keep) > 1 else ())
    plain = bundle_adjust(problem, options=base)
    early = bundle_adjust(problem, options=replace(base, predictive_stop=True))
    assert early.success and early.converged
    assert 2 <= early.iterations < plain.iterations
    capped = bundle_adjust(problem, options=replace(base, max_iterations=early.iterations))
    np.testing.assert_array_equal(early.points, capped.points)
    np.testing.assert_array_equal(early.rotations, capped.rotations)
    assert early.final_rms == capped.final_rms
    assert early.final_rms < 0.5 * early.initial_rms
    # what the skipped iteration would have changed is far below the noise (0.5 px on a 500 px
    # focal length: pose errors of a few hundredths of a degree)
    turn = Rotation.from_matrix(early.rotations) * Rotation.from_matrix(plain.rotations).inv()
    assert np.degrees(turn.magnitude()).max() < 3e-3
