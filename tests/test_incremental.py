"""Incremental SfM on synthetic databases with exact ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sfm.cli import main
from sfm.io.colmap_model import read_model
from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.incremental import reconstruct_incremental
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def test_orbit_with_outliers_is_fully_and_accurately_registered(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=24, observations_per_image=800, outlier_ratio=0.2, seed=0))
    assert main(["map", "--workspace", str(tmp_path)]) == 0
    model = read_model(tmp_path / "sparse" / "0")
    result = evaluate(model, read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt"))
    assert result.num_registered == 24
    assert result.median_rotation_error_deg < 0.05
    assert result.auc[1] > 0.9
    # ERROR column = each point's mean reprojection error; near the 0.5 px noise.
    errors = np.array([p.error for p in model.points3D.values()])
    assert 0.2 < errors.mean() < 1.0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["registered"] == 24 and report["images"] == 24
    assert not (tmp_path / "sparse" / "1").exists()


def test_final_ba_split_into_track_parts_when_over_budget(tmp_path, caplog):
    """``--ba-max-observations`` far below the scene's observations: each final BA is the
    consensus of BAs over random parts of the tracks (backend.partitioned_ba), then every
    point is re-estimated with the cameras held; every image stays registered, accurate, and
    every point stays near the 0.5 px noise."""
    caplog.set_level("INFO", logger="sfm.mapper.state")
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=24, observations_per_image=800, outlier_ratio=0.2, seed=0))
    assert main(["map", "--workspace", str(tmp_path), "--ba-max-observations", "4000"]) == 0
    model = read_model(tmp_path / "sparse" / "0")
    result = evaluate(model, read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt"))
    assert result.num_registered == 24
    assert result.median_rotation_error_deg < 0.1
    observations = sum(len(p.track) for p in model.points3D.values())
    assert observations > 3 * 4000  # every part's points are kept
    errors = np.array([p.error for p in model.points3D.values()])
    assert 0.2 < errors.mean() < 1.0
    assert "as the consensus of" in caplog.text
    ba = json.loads((tmp_path / "report.json").read_text())["models"][0]["final_ba"]
    assert ba["parts"] > 1 and ba["stopped"].endswith("parts)")
    # the RMS after is that of the points re-estimated for the pooled cameras: near the noise
    assert 0.3 < ba["rms_after_px"] < 1.0 and ba["rms_after_px"] < ba["rms_before_px"] + 0.05


def test_final_ba_budget_defaults_to_what_the_memory_holds(tmp_path, monkeypatch):
    """No ``--ba-max-observations``: the budget is ``observations_in_memory()`` of the machine
    that runs the BA, so a machine whose memory holds 4000 observations splits the same final
    BAs as ``--ba-max-observations 4000``, and a larger one runs each as one BA."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=2))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    parts = []
    original = mapper_ba.bundle_adjust_partitioned

    def spy(problem, num_parts, *args, **kwargs):
        parts.append(num_parts)
        return original(problem, num_parts, *args, **kwargs)

    monkeypatch.setattr(mapper_ba, "bundle_adjust_partitioned", spy)
    monkeypatch.setattr(mapper_ba, "observations_in_memory", lambda **_: 4000)
    reconstruct_incremental(payload, MapperOptions())
    small_machine = list(parts)
    parts.clear()
    reconstruct_incremental(payload, MapperOptions(ba_max_observations=4000))
    assert parts == small_machine and max(parts) > 1
    parts.clear()
    monkeypatch.setattr(mapper_ba, "observations_in_memory", lambda **_: 10**9)
    reconstruct_incremental(payload, MapperOptions())
    assert set(parts) == {1}


def test_two_unrelated_scenes_give_two_models(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=20, observations_per_image=500, seed=1))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    # Cut all pairs between the first and the last ten images: two disconnected scenes.
    first = set(range(10))
    pairs = [p for p in payload.pairs if (p[0] in first) == (p[1] in first)]
    split = type(payload)(**{**payload.__dict__, "pairs": pairs})
    models = reconstruct_incremental(split, MapperOptions())
    assert len(models) == 2
    assert sorted(len(m.images) for m in models) == [10, 10]


def test_no_pair_means_no_model(tmp_path):
    run_synth(tmp_path, SynthOptions(num_images=4, observations_per_image=100, seed=3))
    from sfm.errors import NoModelError

    with pytest.raises(NoModelError):
        run_map(tmp_path, MapperOptions(min_num_matches=100000))
