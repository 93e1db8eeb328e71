"""tools/walkthrough.py runs as a script on a small rendered scene and writes its figures."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIGURES = ["1_keypoints.png", "2_image_graph.png", "3_clusters.png", "4_cluster_graph_maxst.png",
           "5_local_models.png", "6_minst_anchor.png", "7_final_model.png", "8_error_histograms.png"]


def test_walkthrough_runs_and_draws_every_stage(tmp_path):
    pytest.importorskip("matplotlib")
    from PIL import Image

    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "walkthrough.py"), "--workspace", str(tmp_path / "ws"),
                           "--num-images", "10", "--max-cluster-size", "4", "--workers", "2"],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "K = ceil(n / S_max) = ceil(10 / 4) = 3" in out
    assert "anchor C" in out and "10/10 registered" in out
    for name in FIGURES:
        path = tmp_path / "ws_figures" / name
        with Image.open(path) as im:  # a real picture, not an empty canvas
            assert im.width > 400 and im.height > 300
            assert len(im.convert("RGB").getcolors(1 << 20) or []) > 50
