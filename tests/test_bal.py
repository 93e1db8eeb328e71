"""The BAL reader (backend/bal.py): agreement with gtsam's reader, and bundle adjustment of
small BAL problems from ../shared/data/bal_small."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from backend.bal import read_bal
from backend.ba_problem import BAOptions
from backend.bundle_adjustment import bundle_adjust, cam_from_world_from_pose3


def test_bal_reader_agrees_with_gtsam(shared_data):
    path = shared_data / "bal_small" / "door_initialization.bal"
    problem = read_bal(path)
    assert (
        len(problem.rotations) == 12 and len(problem.points) == 2140 and len(problem.obs_xy) == 4519
    )
    sfm_data = gtsam.SfmData.FromBalFile(str(path))
    for i in (0, 11):
        rotation, translation = cam_from_world_from_pose3(sfm_data.camera(i).pose())
        np.testing.assert_allclose(problem.rotations[i], rotation, atol=1e-12)
        np.testing.assert_allclose(problem.translations[i], translation, atol=1e-12)
        assert problem.camera_params[i][0] == pytest.approx(sfm_data.camera(i).calibration().fx())
    track = sfm_data.track(5)
    np.testing.assert_allclose(problem.points[5], track.point3())
    cam, xy = track.measurement(0)
    rows = np.flatnonzero((problem.obs_point == 5) & (problem.obs_image == cam))
    np.testing.assert_allclose(problem.obs_xy[rows[0]], xy)


@pytest.mark.parametrize(
    "name, refine, initial, bound",
    [
        ("door_initialization.bal", "focal_radial", 2.5786, 0.47),
        ("dubrovnik-3-7-pre.txt", "none", 17.0579, 0.52),
    ],
)
def test_bal_problems_converge(shared_data, name, refine, initial, bound):
    problem = read_bal(shared_data / "bal_small" / name)
    result = bundle_adjust(problem, options=BAOptions(loss="none", refine_intrinsics=refine))
    assert result.success
    assert result.initial_rms == pytest.approx(initial, abs=1e-4)
    assert result.final_rms < bound < result.initial_rms
