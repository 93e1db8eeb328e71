"""tools/bench_scale.py: the ground truth's co-visibility and the projection, on known answers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from backend.geometry import look_at
from sfm.evaluation.ground_truth import GTPose

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_scale import finished_runs, overlap_matrix, part_projection  # noqa: E402


def nadir(name: str, x: float, height: float = 100.0) -> GTPose:
    """A camera ``height`` above the ground at (x, 0) looking straight down; with focal = width
    its footprint is ``height`` metres wide."""
    rotation, translation = look_at(np.array([x, 0.0, height]), np.array([x, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    K = np.array([[400.0, 0, 199.5], [0, 400.0, 149.5], [0, 0, 1]])
    return GTPose(name, 400, 300, K, rotation, translation)


def test_overlap_is_the_share_of_the_footprint_both_photos_see():
    # footprints 100 m wide: shifted by 50 m they share half, by 150 m nothing
    gt = {"a": nadir("a", 0.0), "b": nadir("b", 50.0), "c": nadir("c", 150.0)}
    names, share = overlap_matrix(gt, grid=(41, 31))
    assert names == ["a", "b", "c"]
    assert share[0, 1] == pytest.approx(0.5, abs=0.03)
    assert share[1, 0] == pytest.approx(0.5, abs=0.03)
    assert share[0, 2] == 0.0 and share[2, 0] == 0.0
    assert np.all(np.diag(share) == 0.0)


def test_ground_seen_from_directions_too_far_apart_is_not_co_visible():
    """Two cameras 100 m up, 250 m either side of the origin, both looking at it: the ground
    there is seen from directions about 136 degrees apart, beyond what SIFT matches."""
    K = np.array([[400.0, 0, 199.5], [0, 400.0, 149.5], [0, 0, 1]])
    poses = {}
    for name, x in (("east", 250.0), ("west", -250.0)):
        rotation, translation = look_at(np.array([x, 0.0, 100.0]), np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
        poses[name] = GTPose(name, 400, 300, K, rotation, translation)
    _, share = overlap_matrix(poses)
    _, share_any_angle = overlap_matrix(poses, max_angle_deg=180.0)
    assert share_any_angle[0, 1] > 0.1
    assert share[0, 1] == 0.0


def test_the_projection_scales_linear_stages_and_keeps_merge_on_one_machine():
    runs = [{"photos": 1000, "extract_s": 100, "match_s": 200, "cluster_s": 1, "map_s": 50, "merge_s": 10, "final_ba_s": 10},
            {"photos": 2000, "extract_s": 200, "match_s": 400, "cluster_s": 2, "map_s": 100, "merge_s": 40, "final_ba_s": 40}]
    rows = {(r["photos"], r["machines"]): r for r in part_projection(runs)}
    one, ten = rows[(10_000, 1)], rows[(10_000, 10)]
    assert one["merge+BA exponent"] == pytest.approx(2.0)
    assert one["match_h"] == pytest.approx(400 * 5 / 3600, abs=0.01)
    assert ten["match_h"] == pytest.approx(400 * 5 / 3600 / 10, abs=0.01)
    assert ten["merge_h"] == one["merge_h"] == pytest.approx(40 * 25 / 3600, abs=0.01)  # (10000/2000)^2
    assert one["bound by"] == "match" and rows[(50_000, 10)]["bound by"] in ("merge", "final_ba")


def test_a_resumed_run_sums_the_stage_times_of_both_invocations():
    """The unfinished invocation's stages plus the finishing one's; wall and peak its own;
    a run without an earlier invocation is left as it is."""
    results = {
        "endtoend": {"1000": {"photos": 1000, "wall_s": 977, "peak_rss_gb": 8.39, "extract_s": 0, "match_s": 42,
                              "map_s": 1, "merge_s": 32, "final_ba_s": 898, "total_s": 973},
                     "200": {"photos": 200, "wall_s": 500, "extract_s": 100, "total_s": 490}},
        "endtoend_partial": {"1000": {"photos": 1000, "extract_s": 786, "match_s": 2098, "cluster_s": 1,
                                      "map_s": 566, "total_s": 3451, "status": "running"}},
    }
    small, big = finished_runs(results)
    assert small == results["endtoend"]["200"]
    assert (big["extract_s"], big["match_s"], big["cluster_s"], big["map_s"]) == (786, 2140, 1, 567)
    assert (big["merge_s"], big["final_ba_s"], big["total_s"]) == (32, 898, 4424)
    assert (big["wall_s"], big["peak_rss_gb"], big["invocations"]) == (977, 8.39, 2)
