"""The whole divide-and-conquer path from a database: cluster, map (parallel), merge, refine."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sfm.api import make_options, reconstruct
from sfm.cli import main
from sfm.io.colmap_model import read_model
from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import read_gt_table
from sfm.viz.recorder import entity_paths
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def test_reconstruct_from_database_with_clusters(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=90, observations_per_image=600, outlier_ratio=0.2, seed=0))
    assert main(["reconstruct", "--workspace", str(tmp_path), "--max-cluster-size", "35", "--workers", "2"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["num_clusters"] >= 3 and report["num_models"] == 1
    for key in ("cluster", "map", "merge", "final_ba"):
        assert report["times_s"][key] > 0
    assert report["times_s"]["total"] == pytest.approx(sum(v for k, v in report["times_s"].items() if k != "total"),
                                                      abs=0.01)
    assert report["executor"] == "local" and all(c["worker"] for c in report["clusters"])
    model = read_model(tmp_path / "sparse" / "0")
    result = evaluate(model, read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt"))
    assert result.num_registered == 90
    assert result.median_rotation_error_deg < 0.1
    merge = json.loads((tmp_path / "merge.json").read_text())
    [component] = merge["components"]
    assert len(component["minst"]) == len(merge["nodes"]) - 1
    assert component["anchor"] in component["clusters"]
    assert all(e["msd"] >= 0 for e in merge["edges"])
    paths = entity_paths(tmp_path / "recording.rrd")
    assert {"/graph/images", "/graph/clusters", "/graph/merge", "/world/points", "/tour"} <= paths
    assert any(p.startswith("/clusters/C0/model0/cams/") for p in paths) and any(p.startswith("/merge/") for p in paths)
    assert any(p.startswith("/world/cams/") for p in paths)


def test_python_api_and_unknown_option(tmp_path):
    run_synth(tmp_path, SynthOptions(num_images=16, observations_per_image=400, seed=2))
    models, report = reconstruct(None, tmp_path, workers=1, seed=0, max_cluster_size=100)
    assert len(models) == 1 and len(models[0].images) == 16 and report["num_clusters"] == 1
    with pytest.raises(ValueError, match=r"unknown option 'max_clustr_size' \(did you mean 'max_cluster_size'\?\)"):
        make_options(max_clustr_size=5)


def test_two_disconnected_scenes_give_two_models(tmp_path):
    """Two synthetic scenes in one database (no pair between them): two complete models."""
    from sfm.io.database import Database

    a, b = tmp_path / "a", tmp_path / "b"
    run_synth(a, SynthOptions(scene="orbit", num_images=14, observations_per_image=400, seed=1))
    run_synth(b, SynthOptions(scene="aerial", num_images=12, observations_per_image=400, seed=2))
    work = tmp_path / "both"
    work.mkdir()
    with Database(work / "database.db") as out:
        for src, offset in ((a, 0), (b, 100)):
            with Database(src / "database.db", readonly=True) as db:
                cams = db.read_cameras()
                images = db.read_images()
                cam_map = {c: out.add_camera(r.model, r.width, r.height, r.params, r.prior_focal_length) for c, r in cams.items()}
                for i, rec in images.items():
                    out.add_image(rec.name, cam_map[rec.camera_id], image_id=i + offset)
                    out.write_keypoints(i + offset, db.read_keypoints(i))
                for (i, j), g in db.read_two_view_geometries().items():
                    out.write_two_view_geometry(i + offset, j + offset, g)
    models, report = reconstruct(None, work, workers=1, max_cluster_size=8)
    assert sorted(len(m.images) for m in models) == [12, 14]
    assert report["num_models"] == 2 and report["warnings"]
    assert np.all([len(m.points3D) > 100 for m in models])
