"""Interrupted runs, stale results and determinism: ``graphsfm reconstruct`` as a user runs it.

The rendered scene (16 images, at least 3 clusters at ``--max-cluster-size 6``) is reconstructed once
without interruption; that model is the reference.  Then one workspace is killed (SIGKILL, no
chance to clean up) during extract, match, map and merge in turn, each time rerun; the run that
finally finishes must say what it reused and give the reference model byte for byte.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene

NUM_IMAGES = 16
PAIRS = NUM_IMAGES * (NUM_IMAGES - 1) // 2  # exhaustive matching
ARGS = ["--max-cluster-size", "6", "--seed", "0", "--no-recording"]


def command(images: Path, ws: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "sfm", "reconstruct", "--images", str(images), "--workspace", str(ws),
            *ARGS, *extra]


def run(images: Path, ws: Path, *extra: str) -> str:
    """A finished run; returns its stderr (the log)."""
    proc = subprocess.run(command(images, ws, *extra), capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    return proc.stderr


def model_files(ws: Path) -> dict[str, bytes]:
    folder = ws / "sparse" / "0"
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def count(ws: Path, table: str) -> int:
    try:
        conn = sqlite3.connect(f"{(ws / 'database.db').resolve().as_uri()}?mode=ro", uri=True, timeout=0.05)
        try:
            return conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
        finally:
            conn.close()
    except sqlite3.Error:  # not created yet, or locked by the writer this instant
        return -1


def num_clusters(ws: Path) -> int:
    try:
        return len(json.loads((ws / "clusters.json").read_text())["clusters"])
    except (OSError, ValueError):
        return 10**9


def ledger(ws: Path) -> dict:
    try:
        return json.loads((ws / "stages.json").read_text())
    except (OSError, ValueError):
        return {}


def run_and_kill(images: Path, ws: Path, during, what: str, *extra: str) -> str:
    """Start a run and SIGKILL it (no chance to clean up) as soon as ``during(ws)`` holds,
    polled every 5 ms; returns what the run logged until then."""
    proc = subprocess.Popen(command(images, ws, *extra), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []  # read by a thread, so the child never blocks on a full pipe
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline:
        if during(ws):
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            reader.join(5)
            return "".join(lines)
        time.sleep(0.005)
    proc.kill()
    reader.join(5)
    pytest.fail(f"the run ended before it was seen {what}: {''.join(lines)[-2000:]}")


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene")
    return Path(write_rendered_scene(out, RenderOptions(num_images=NUM_IMAGES, seed=3))["image_dir"])


@pytest.fixture(scope="module")
def reference(images, tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("reference") / "ws"
    run(images, ws, "--workers", "1")
    return ws


def test_killed_in_every_stage_resumes_to_the_same_model(images, reference, tmp_path):
    ws = tmp_path / "ws"
    pairs = PAIRS
    # One extraction process, so the database fills image by image.
    slow = ("--workers", "1")
    run_and_kill(images, ws, lambda w: 0 < count(w, "keypoints") < NUM_IMAGES, "extracting", *slow)
    kept = count(ws, "keypoints")
    log = run_and_kill(images, ws, lambda w: 0 < count(w, "two_view_geometries") < pairs, "matching", *slow)
    assert f"{kept} of {NUM_IMAGES} images already have features" in log
    verified = count(ws, "two_view_geometries")
    assert 0 < verified < pairs

    def mapping(w: Path) -> bool:
        done = ledger(w).get("map", {}).get("clusters", {})
        return 1 <= len(done) < num_clusters(w)

    log = run_and_kill(images, ws, mapping, "mapping", *slow)
    assert f"{verified} already verified (resumed)" in log
    mapped = sorted(ledger(ws)["map"]["clusters"])
    log = run_and_kill(images, ws, lambda w: ledger(w).get("merge", {}).get("done") is False, "merging", *slow)
    n = num_clusters(ws)
    assert n >= 3 and "clusters.json is current" in log
    assert f"{len(mapped)} of {n} clusters finished by an earlier run with the same options: skipped ({', '.join(mapped)})" in log
    assert not (ws / "sparse" / "0").exists()
    log = run(images, ws, *slow)
    assert f"{NUM_IMAGES} of {NUM_IMAGES} images already have features" in log and f"{pairs} already verified" in log
    assert "clusters.json is current" in log and f"{n} of {n} clusters finished by an earlier run" in log
    assert "merge: runs again: the earlier run did not finish" in log
    assert model_files(ws) == model_files(reference)
    report = json.loads((ws / "report.json").read_text())
    assert report["registered"] == NUM_IMAGES and report["num_models"] == 1



def test_same_seed_gives_identical_files_with_one_or_two_workers(images, reference, tmp_path):
    ws = tmp_path / "ws"
    run(images, ws, "--workers", "2")
    assert model_files(ws) == model_files(reference)
    report = json.loads((ws / "report.json").read_text())
    assert len({c["worker"] for c in report["clusters"]}) == 2  # the clusters did run in two processes


def test_a_changed_option_recomputes_its_stage_and_the_later_ones_only(images, reference, tmp_path):
    ws = tmp_path / "ws"
    subprocess.run(["cp", "-r", str(reference), str(ws)], check=True)
    log = run(images, ws, "--workers", "1")  # nothing changed: nothing runs again
    assert f"{NUM_IMAGES} of {NUM_IMAGES} images already have features" in log and f"{PAIRS} already verified" in log
    n = num_clusters(ws)
    assert "clusters.json is current" in log and f"{n} of {n} clusters finished" in log
    assert "sparse is current" in log or "/sparse is current" in log
    assert model_files(ws) == model_files(reference)

    log = run(images, ws, "--workers", "1", "--max-cluster-size", "10")
    assert f"{NUM_IMAGES} of {NUM_IMAGES} images already have features" in log and f"{PAIRS} already verified" in log
    assert "cluster: runs again: options changed (max_cluster_size: 6 -> 10)" in log
    assert "cluster: the earlier results of map, merge are stale" in log
    assert "clusters finished by an earlier run" not in log and "sparse is current" not in log
    stages = ledger(ws)
    assert stages["cluster"]["options"]["max_cluster_size"] == 10 and stages["merge"]["done"]
    assert json.loads((ws / "clusters.json").read_text())["max_cluster_size"] == 10
    assert json.loads((ws / "report.json").read_text())["registered"] == NUM_IMAGES

    log = run(images, ws, "--workers", "1", "--max-cluster-size", "10", "--max-num-features", "1000")
    assert "extract: options changed (max_num_features: 8192 -> 1000)" in log
    assert f"{NUM_IMAGES} images extracted, 0 skipped" in log and f"0 already verified (resumed), {PAIRS} to match" in log
    stages = ledger(ws)
    assert stages["extract"]["options"]["max_num_features"] == 1000
    with sqlite3.connect(ws / "database.db") as conn:
        # 1,000 keypoint locations, each with at most two orientations (sfm.features.sift)
        assert 1000 <= conn.execute("SELECT MAX(rows) FROM keypoints").fetchone()[0] <= 2000
