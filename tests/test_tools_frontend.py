"""tools/check_matches.py: GT epipolar distances and pair recall, on cases with known answers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from sfm.execution.local import LocalExecutor
from sfm.io.database import Database
from sfm.io.database_schema import TwoViewGeometry
from sfm.features.options import ExtractOptions
from sfm.stages.extract import run_extract
from backend.geometry import look_at
from sfm.evaluation.ground_truth import GTPose, read_gt_table
from sfm.matching.options import MatchOptions
from sfm.stages.match import run_match
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from check_matches import (
    check_matches,
    format_report,
    gt_fundamental,
    optical_axis_angle_deg,
    symmetric_epipolar_distance,
    undistort_simple_radial,
)

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])


def pose(name: str, rotation: np.ndarray, translation) -> GTPose:
    return GTPose(name, 640, 480, K, rotation, np.asarray(translation, float))


def project(p: GTPose, X: np.ndarray) -> np.ndarray:
    x = (p.K @ (p.rotation @ X.T + p.translation[:, None])).T
    return x[:, :2] / x[:, 2:]


def test_rectified_pair_distance_is_the_vertical_offset() -> None:
    """Camera 2 is camera 1 moved along x: epipolar lines are the image rows, so moving x2 by
    delta px vertically gives a symmetric epipolar distance of exactly |delta|."""
    rng = np.random.default_rng(0)
    a, b = pose("a", np.eye(3), [0, 0, 0]), pose("b", np.eye(3), [-1.0, 0, 0])
    X = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-2, 2, 50), rng.uniform(4, 8, 50)])
    x1, x2 = project(a, X), project(b, X)
    F = gt_fundamental(a, b)
    assert np.max(symmetric_epipolar_distance(F, x1, x2)) < 1e-9
    delta = rng.uniform(-3, 3, 50)
    d = symmetric_epipolar_distance(F, x1, x2 + np.column_stack([rng.uniform(-9, 9, 50), delta]))
    np.testing.assert_allclose(d, np.abs(delta), atol=1e-9)


def test_general_pair_exact_points_lie_on_epipolar_lines() -> None:
    rng = np.random.default_rng(1)
    r1, t1 = look_at(np.array([0.0, -6, 0.5]), np.zeros(3), up=np.array([0.0, 0, 1]))
    r2, t2 = look_at(np.array([3.0, -5, 1.0]), np.array([0.2, 0, 0]), up=np.array([0.0, 0, 1]))
    a, b = pose("a", r1, t1), pose("b", r2, t2)
    X = rng.uniform(-1, 1, (100, 3))
    F = gt_fundamental(a, b)
    assert np.max(symmetric_epipolar_distance(F, project(a, X), project(b, X))) < 1e-8
    # swapping the images needs F^T: the same distances
    d_ab = symmetric_epipolar_distance(F, project(a, X), project(b, X) + 1.0)
    d_ba = symmetric_epipolar_distance(gt_fundamental(b, a), project(b, X) + 1.0, project(a, X))
    np.testing.assert_allclose(d_ab, d_ba, rtol=1e-9)
    assert abs(optical_axis_angle_deg(a, b) - optical_axis_angle_deg(b, a)) < 1e-12


def test_undistort_inverts_simple_radial_distortion() -> None:
    rng = np.random.default_rng(2)
    undistorted = rng.uniform([0, 0], [640, 480], (200, 2))
    n = (undistorted - K[:2, 2]) / K[0, 0]
    distorted = n * (1 - 0.05 * np.sum(n**2, axis=1, keepdims=True)) * K[0, 0] + K[:2, 2]
    assert np.max(np.abs(distorted - undistorted)) > 5.0  # the corners move by ~10 px
    np.testing.assert_allclose(undistort_simple_radial(distorted, K, -0.05), undistorted, atol=1e-6)
    np.testing.assert_array_equal(undistort_simple_radial(distorted, K, 0.0), distorted)


def yaw_pose(name: str, yaw_deg: float) -> GTPose:
    """A camera on a circle of radius 0.1 looking outwards at ``yaw_deg`` in the xy plane."""
    yaw = np.radians(yaw_deg)
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    r, t = look_at(0.1 * forward, forward, up=np.array([0.0, 0, 1]))
    return pose(name, r, t)


def test_overlap_recall_counts_selected_and_verified_pairs(tmp_path: Path) -> None:
    """Axes at 0, 20, 40, 100 deg: with 30 deg the overlapping pairs are (0,20) and (20,40).
    (0,20) has only a matches row (selected, not verified), (20,40) is verified, and (0,100) is
    verified but does not overlap; an image outside the GT is ignored."""
    gt = {n: yaw_pose(n, y) for n, y in (("i0", 0), ("i20", 20), ("i40", 40), ("i100", 100))}
    with Database(tmp_path / "database.db") as db:
        cam = db.add_camera("PINHOLE", 640, 480, [500, 500, 319.5, 239.5])
        ids = {n: db.add_image(n, cam) for n in ("i0", "i20", "i40", "i100", "extra")}
        for i in ids.values():
            db.write_keypoints(i, np.zeros((20, 2), np.float32))
        m = np.column_stack([np.arange(20), np.arange(20)])
        db.write_matches(ids["i0"], ids["i20"], m)
        db.write_two_view_geometry(ids["i20"], ids["i40"], TwoViewGeometry(3, m))
        db.write_two_view_geometry(ids["i0"], ids["i100"], TwoViewGeometry(3, m))
        db.write_two_view_geometry(ids["i0"], ids["extra"], TwoViewGeometry(3, m))
        check = check_matches(db, gt, min_inliers=15, overlap_deg=30)
    assert (check.num_gt_overlap, check.num_overlap_selected, check.num_overlap_verified) == (
        2,
        2,
        1,
    )
    assert check.recall_selected == 1.0 and check.recall_verified == 0.5
    assert check.num_selected == 4 and check.num_verified == 3 and check.num_checked == 2
    with Database(tmp_path / "database.db", readonly=True) as db:
        strict = check_matches(db, gt, min_inliers=15, overlap_deg=10)
    assert strict.num_gt_overlap == 0 and strict.missed_overlap == []
    assert "recall of GT-overlapping pairs among selected pairs | 100.0% (2/2)" in format_report(
        check
    )


@pytest.fixture(scope="module")
def rendered_workspace(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("rendered")
    info = write_rendered_scene(root, RenderOptions(num_images=4, texture_size=512))
    work = root / "work"
    run_extract(Path(info["image_dir"]), work, ExtractOptions(), LocalExecutor(1))
    run_match(work, MatchOptions(pairs="exhaustive"), LocalExecutor(1))
    return work, Path(info["gt_table"])


def test_rendered_scene_inliers_agree_with_the_rendering_gt(rendered_workspace) -> None:
    work, gt_table = rendered_workspace
    gt = read_gt_table(gt_table)
    with Database(work / "database.db", readonly=True) as db:
        check = check_matches(db, gt, overlap_deg=70)  # cameras are about 33 deg apart
    assert check.num_checked == check.num_verified >= 3
    assert len(check.distances) > 300
    assert check.median_px < 1.0 and check.p90_of_pair_medians_px < 1.5
    assert check.num_gt_overlap >= 3 and check.recall_selected == 1.0  # exhaustive: every pair


def test_rendered_scene_wrong_gt_is_caught(rendered_workspace) -> None:
    """Negative control: the same inliers against a GT whose k-th camera is tilted by 3 k
    degrees about its x axis (every pair's relative rotation off by >= 3 degrees) are several
    pixels off their epipolar lines (the true GT gives about 0.2 px; this about 6 px)."""
    work, gt_table = rendered_workspace
    gt = {}
    for k, (name, p) in enumerate(sorted(read_gt_table(gt_table).items())):
        c, s = np.cos(np.radians(3.0 * k)), np.sin(np.radians(3.0 * k))
        tilt = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        gt[name] = GTPose(name, p.width, p.height, p.K, tilt @ p.rotation, p.translation)
    with Database(work / "database.db", readonly=True) as db:
        check = check_matches(db, gt)
    assert check.num_checked >= 3
    assert check.median_px > 5.0 and min(check.pair_medians.values()) > 2.0
