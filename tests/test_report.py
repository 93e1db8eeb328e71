"""``WORK/report.json`` has one schema whatever the run (one cluster or several), documented key
by key in the README; ``WORK/log.txt`` is at INFO (DEBUG with ``-v``) and holds the worker
processes' messages, each saying which cluster it comes from; progress events reach the parent
from the workers (``sfm.io.report``, ``sfm.console``, ``sfm.execution.logs``)."""

from __future__ import annotations

import datetime
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import sfm
import sfm.cli as cli
from sfm.core import progress
from sfm.io.database import Database
from sfm.io.database_schema import TwoViewGeometry
from sfm.io.report import SCHEMA, check_report
from sfm.io.workspace import read_json
from sfm.mapper.growth import Growth, ModelGrowth
from sfm.stages.map import several_models_warning
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def one_cluster(tmp_path_factory):
    """16 images in one cluster, plus an image without keypoints, one without any pair, and one
    whose only pair (20 inliers, with the first image) shows it too few of the model's points
    for PnP."""
    ws = tmp_path_factory.mktemp("one")
    run_synth(ws, SynthOptions(num_images=16, observations_per_image=400, seed=2))
    with Database(ws / "database.db") as db:
        camera = next(iter(db.read_cameras()))
        db.add_image("zz_blank.jpg", camera)
        lonely = db.add_image("zz_lonely.jpg", camera)
        db.write_keypoints(lonely, np.random.default_rng(0).uniform(0, 500, (50, 2)))
        first = min(db.read_images())
        weak = db.add_image("zz_weak.jpg", camera)
        db.write_keypoints(weak, db.read_keypoints(first)[:20, :2])
        pairs = np.stack([np.arange(20), np.arange(20)], axis=1)
        db.write_two_view_geometry(first, weak, TwoViewGeometry(2, pairs))
    assert cli.main(["reconstruct", "--workspace", str(ws), "--no-recording", "--workers", "1", "-v"]) == 0
    return ws


@pytest.fixture(scope="module")
def clusters(tmp_path_factory):
    """40 images cut into several clusters, mapped by two worker processes and merged; the
    progress events the run's parent received."""
    ws = tmp_path_factory.mktemp("several")
    run_synth(ws, SynthOptions(scene="aerial", num_images=40, observations_per_image=500, seed=1))
    events = []
    with progress.listen(lambda event, task: events.append((task, event))):
        assert cli.main(["reconstruct", "--workspace", str(ws), "--no-recording", "--workers", "2",
                         "--max-cluster-size", "16"]) == 0
    return ws, events


def test_one_schema_for_one_cluster_and_several(one_cluster, clusters):
    one, several = read_json(one_cluster / "report.json"), read_json(clusters[0] / "report.json")
    assert check_report(one) == [] and check_report(several) == []
    assert list(one) == list(several) == list(SCHEMA)
    assert one["schema_version"] == several["schema_version"] == 1
    assert one["graphsfm_version"] == sfm.__version__
    assert (one["num_clusters"], one["merged"], one["merge_components"], one["num_local_models"]) == (1, False, 0, 1)
    assert several["num_clusters"] >= 3 and several["merged"] and several["merge_components"] == 1
    assert several["num_local_models"] >= several["num_clusters"]
    for report, ws in ((one, one_cluster), (several, clusters[0])):
        assert report["status"] == "finished" and report["command"].startswith(f"graphsfm reconstruct --workspace {ws}")
        started, finished = (datetime.datetime.fromisoformat(report[k]) for k in ("started", "finished"))
        assert started <= finished and started.tzinfo is not None
        assert report["workspace"] == str(ws.resolve()) and report["models"][0]["path"] == str(ws.resolve() / "sparse" / "0")
        assert report["files"]["database"] == str(ws.resolve() / "database.db")
        assert report["files"]["log"] == str(ws.resolve() / "log.txt") and report["files"]["recording"] is None
        times = report["times_s"]
        assert set(times) == {"extract", "match", "cluster", "map", "merge", "final_ba", "extend", "total"}
        assert times["total"] == pytest.approx(sum(v for k, v in times.items() if k != "total"), abs=0.01)
        assert report["pairs_tried"] >= report["pairs_verified"] > 0 and report["median_inliers"] > 0
        assert report["registered"] == report["models"][0]["registered"] and report["accuracy"] is None
        assert report["executor"] == "local" and report["scheduler"] is None
        ba = report["models"][0]["final_ba"]  # the last final BA: the local model's, or the merged one's
        assert ba["images"] == report["registered"] and ba["parts"] == 1 and ba["iterations"] >= 1
        assert ba["cost_after"] <= ba["cost_before"] and ba["rms_after_px"] <= ba["rms_before_px"]
        assert ba["stopped"].startswith(("relative decrease below tolerance", "decrease below absolute"))
        assert ba["observations"] >= 3 * report["points"] * 0.5 and ba["time_s"] > 0
        log_text = (ws / "log.txt").read_text()
        assert re.search(r"final BA over \d+ images and \d+ observations: cost \S+ -> \S+, RMS", log_text)
    assert one["files"]["clusters"] == str(one_cluster.resolve() / "clusters.json") and one["files"]["merge"] is None
    assert several["files"]["merge"] == str(clusters[0].resolve() / "merge.json")
    assert several["registered"] == 40 and several["unregistered"] == [] and several["workers"] == 2
    kp = several["keypoints_per_image"]
    assert kp["min"] <= kp["median"] <= kp["max"] and kp["min"] <= kp["mean"] <= kp["max"] and kp["min"] > 0


def test_images_left_unregistered_are_listed_with_the_reason(one_cluster):
    report = read_json(one_cluster / "report.json")
    assert report["images"] == 19 and report["registered"] == 16
    assert report["unregistered"][:2] == [{"name": "zz_blank.jpg", "reason": "no keypoints"},
                                          {"name": "zz_lonely.jpg", "reason": "no verified pair with another image"}]
    weak = report["unregistered"][2]
    seen = re.fullmatch(r"sees (\d+) points of the model, fewer than the 30 registration needs", weak["reason"])
    assert weak["name"] == "zz_weak.jpg" and seen and 10 <= int(seen.group(1)) <= 20, weak
    assert len(report["unregistered"]) == 3
    assert report["clusters"][0]["left_out"] == {"zz_weak.jpg": weak["reason"]}
    assert report["keypoints_per_image"]["min"] == 0


def test_the_readme_documents_every_key_of_the_report():
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## The workspace"):readme.index("## Command line")]
    missing = [k for k in SCHEMA if f"`{k}`" not in section]
    assert not missing, missing
    assert "`schema_version`" in section


def test_log_file_at_info_with_every_workers_lines_tagged_by_cluster(clusters):
    ws, _ = clusters
    lines = (ws / "log.txt").read_text().splitlines()
    assert lines and not any(" DEBUG " in ln for ln in lines)
    pattern = re.compile(r"^\S+ \S+ (INFO|WARNING|ERROR) (\d+) (\S+?)(?: \[(C\d+)\])?: (.*)$")
    parsed = [pattern.match(ln) for ln in lines]
    assert all(parsed), [ln for ln, m in zip(lines, parsed) if not m][:3]
    initial = [m for m in parsed if "initial pair" in m.group(5)]
    labels = {c["cluster"] for c in read_json(ws / "report.json")["clusters"]}
    assert {m.group(4) for m in initial} == labels  # every cluster's start, tagged with its label
    assert all(int(m.group(2)) != os.getpid() for m in initial)  # written by the worker processes
    assert any(int(m.group(2)) == os.getpid() for m in parsed)  # and the parent's own lines


def test_verbose_puts_debug_lines_in_the_log(one_cluster):
    text = (one_cluster / "log.txt").read_text()
    assert " DEBUG " in text and " INFO " in text


def test_progress_events_come_from_the_workers(clusters):
    ws, events = clusters
    sizes = {c["cluster"]: c["images"] for c in read_json(ws / "report.json")["clusters"]}
    registered = {}
    for task, event in events:
        if event["kind"] == "registered":
            assert event["total"] == sizes[task]
            registered.setdefault(task, []).append(event["done"])
    assert set(registered) == set(sizes)
    for task, counts in registered.items():
        assert counts[0] == 2 and counts == sorted(counts) and counts[-1] <= sizes[task]
    ba = [e for _, e in events if e["kind"] == "final_ba"]
    assert ba and all(e["cost"] >= 0 and e["done"] >= 1 for e in ba)
    pairs = [e for _, e in events if e["kind"] == "model_pairs"]
    assert pairs[-1]["done"] == pairs[-1]["total"] == len(sizes) * (len(sizes) - 1) // 2


def test_quiet_shows_warnings_only(tmp_path, capsys):
    run_synth(tmp_path, SynthOptions(num_images=16, observations_per_image=400, seed=2))
    capsys.readouterr()
    assert cli.main(["reconstruct", "--workspace", str(tmp_path), "--no-recording", "-q", "--workers", "1"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and '"registered": 16' in captured.out


def test_projection_overflow_warns_nobody():
    from backend.camera_models import project, unproject

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        px = project("SIMPLE_RADIAL", np.array([500.0, 320.0, 240.0, 0.1]), np.array([[1e200, 1e200, 1e-200]]))
        assert not np.all(np.isfinite(px))
        uv = unproject("SIMPLE_RADIAL", np.array([500.0, 320.0, 240.0, 50.0]), np.array([[1e6, 1e6]]))
        assert uv.shape == (1, 2)


def test_warnings_go_to_the_log_not_to_stderr(tmp_path):
    code = ("import sys, warnings; sys.path.insert(0, sys.argv[1]); import numpy as np\n"
            "from sfm.console import setup_logging\n"
            "setup_logging(sys.argv[2], 'normal')\n"
            "np.float64(1e308) * np.float64(10)\n"
            "warnings.warn('a library warning', UserWarning)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(ROOT), str(tmp_path)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and proc.stderr == ""
    log = (tmp_path / "log.txt").read_text()
    assert "RuntimeWarning: overflow encountered" in log and "UserWarning: a library warning" in log


def test_why_an_image_is_not_in_the_largest_model():
    """Per image, the reason the cluster's largest kept model gave when it closed; an image only
    a dropped (too small) model took says so; no model at all: no initial pair."""
    names = ["a", "b", "c", "d", "e", "f"]
    small = ModelGrowth(rank=1, size=2, registered=np.array([0, 1]), left_out={"c": "x", "d": "x", "e": "x", "f": "x"})
    dropped = ModelGrowth(rank=-1, size=1, registered=np.array([5]))
    largest = ModelGrowth(rank=0, size=3, registered=np.array([2, 3, 4]),
                          left_out={"a": "registered in an earlier model", "b": "registered in an earlier model",
                                    "f": "sees 4 points of the model, fewer than the 30 registration needs"})
    growth = Growth("C3", names, 0, models=[small, largest, dropped], min_size=2)
    assert growth.left_out() == {
        "a": "registered in an earlier model", "b": "registered in an earlier model",
        "f": "registered only in a model of 1 images, fewer than the 2 a kept model needs"}
    assert Growth("C3", names, 0).left_out() == dict.fromkeys(names, "no initial pair could be reconstructed")


def test_several_models_say_why_the_others_images_are_not_in_the_largest():
    left_out = {f"im{k}.jpg": f"reason {k}" for k in range(5)}
    assert several_models_warning([20, 3], [{"im1.jpg", "im0.jpg"}], left_out) == (
        "2 models: the images did not form one connected reconstruction (sizes 20, 3); "
        "not in the largest: im0.jpg (reason 0), im1.jpg (reason 1)")
    assert several_models_warning([9, 3, 2], [{"im2.jpg", "im3.jpg", "im4.jpg"}, {"im0.jpg", "im1.jpg"}], left_out) == (
        "3 models: the images did not form one connected reconstruction (sizes 9, 3, 2); not in the largest: "
        "im0.jpg (reason 0), im1.jpg (reason 1), im2.jpg (reason 2) and 2 more")
    assert several_models_warning([4, 4], [{"zz.jpg"}], {}) == (
        "2 models: the images did not form one connected reconstruction (sizes 4, 4)")
    unjoined = ["model 1 (3 images) did not join model 0 as a whole: why"]
    assert several_models_warning([20, 3], [{"im0.jpg"}], left_out, unjoined) == (
        "2 models: the images did not form one connected reconstruction (sizes 20, 3); not in the largest: "
        "im0.jpg (reason 0); model 1 (3 images) did not join model 0 as a whole: why")


def test_why_a_kept_model_did_not_join_the_largest():
    """The reason the later of two kept models found when it tried to join the earlier, whichever
    of them is the largest; none for a model that did not try (nothing recorded)."""
    first = ModelGrowth(rank=1, size=4, registered=np.arange(4))
    largest = ModelGrowth(rank=0, size=9, registered=np.arange(4, 13), unjoined={0: "too few rays"})
    later = ModelGrowth(rank=2, size=3, registered=np.arange(13, 16), unjoined={0: "other", 1: "no pair"})
    silent = ModelGrowth(rank=3, size=2, registered=np.arange(16, 18))
    growth = Growth("C0", [f"i{k}" for k in range(18)], 0, models=[first, largest, later, silent], min_size=2)
    assert growth.unjoined() == ["model 1 (4 images) did not join model 0 as a whole: too few rays",
                                 "model 2 (3 images) did not join model 0 as a whole: no pair"]
