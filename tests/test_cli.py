"""The command line: synth -> evaluate -> export, one-line errors and exit codes."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from sfm.cli import main


def test_synth_evaluate_export(tmp_path, capsys):
    w = tmp_path / "w"
    assert main(["synth", "--scene", "street", "--num-images", "20", "--observations-per-image", "300", "--outlier-ratio", "0.2", "--workspace", str(w)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["images"] == 20 and (w / "database.db").exists() and (w / "log.txt").exists()
    assert main(["evaluate", str(w / "gt" / "model"), "--gt", str(w / "gt" / "cameras_gt_opencv.txt")]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["registered_ratio"] == 1.0 and result["auc@1"] == 1.0 and result["median_rotation_error_deg"] < 1e-9
    assert "rotation_errors_deg" not in result
    # A COLMAP model works as GT too.
    assert main(["evaluate", str(w / "gt" / "model"), "--gt", str(w / "gt" / "model"), "--per-image"]) == 0
    assert len(json.loads(capsys.readouterr().out)["rotation_errors_deg"]) == 20
    assert main(["export", str(w / "gt" / "model"), "--to", "txt", str(w / "txt")]) == 0
    assert (w / "txt" / "images.txt").exists()
    assert main(["export", str(w / "txt"), "--to", "ply", str(w / "points.ply")]) == 0
    header = (w / "points.ply").read_bytes()[:300]
    assert b"element vertex " + str(summary["points"]).encode() in header


def test_rendered_synth(tmp_path, capsys):
    assert main(["synth", "--scene", "rendered", "--num-images", "3", "--workspace", str(tmp_path)]) == 0
    assert len(list((tmp_path / "images").glob("*.png"))) == 3


@pytest.mark.parametrize(
    "argv,code,message",
    [
        (["evaluate", "nowhere", "--gt", "nothing.txt"], 2, "model not found: nowhere"),
        (["synth", "--num-images", "1", "--workspace", "{tmp}/one"], 2, "--num-images: must be >= 2; got 1"),
        (["synth", "--outlier-ratio", "1.5", "--workspace", "{tmp}/bad"], 2, "--outlier-ratio: must be >= 0 and <= 0.99; got 1.5"),
    ],
)
def test_errors_are_one_line_with_exit_code(tmp_path, argv, code, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    proc = subprocess.run([sys.executable, "-m", "sfm", *argv], capture_output=True, text=True)
    assert proc.returncode == code
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith("graphsfm ") and message in lines[-1]
    assert "Traceback" not in proc.stderr


def test_existing_workspace_is_not_overwritten(tmp_path):
    args = ["synth", "--num-images", "5", "--observations-per-image", "100", "--workspace", str(tmp_path)]
    assert main(args) == 0
    proc = subprocess.run([sys.executable, "-m", "sfm", *args], capture_output=True, text=True)
    assert proc.returncode == 2 and "exists" in proc.stderr and "Traceback" not in proc.stderr


def test_unwritable_workspace(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    proc = subprocess.run([sys.executable, "-m", "sfm", "synth", "--workspace", str(blocker / "w")], capture_output=True, text=True)
    assert proc.returncode == 2 and "cannot write to workspace" in proc.stderr and "Traceback" not in proc.stderr
