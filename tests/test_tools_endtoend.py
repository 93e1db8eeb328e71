"""tools/bench_endtoend.py on a small rendered scene: both pipelines from the images, evaluated."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))


@pytest.mark.slow
def test_end_to_end_table_has_both_pipelines_evaluated(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    from bench_endtoend import main

    write_rendered_scene(tmp_path / "scene", RenderOptions(num_images=10, seed=4))
    gt = tmp_path / "scene" / "gt" / "cameras_gt_opencv.txt"
    assert main(["--images", str(tmp_path / "scene" / "images"), "--gt", str(gt), "--no-recording",
                 "--repeat", "2", "--out", str(tmp_path / "out"), "--page", str(tmp_path / "BENCHMARKS.md")]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = [dict(zip(header, (c.strip() for c in line.strip("|").split("|")))) for line in lines[1:]]
    # two runs (the second starts with COLMAP), each listed graphsfm first, in its own folder
    assert [(r["run"], r["method"].split()[0]) for r in rows] == [
        ("1", "graphsfm"), ("1", "pycolmap"), ("2", "graphsfm"), ("2", "pycolmap")
    ]
    assert (tmp_path / "out" / "run2" / "graphsfm" / "sparse" / "0").is_dir()
    ratio_line = next(line for line in out.splitlines() if line.startswith("total time graphsfm / COLMAP:"))
    assert "median" in ratio_line and len(ratio_line.split(":")[1].split("(")[0].split(",")) == 2
    assert "<!-- bench:endtoend-scene-images -->" in (tmp_path / "BENCHMARKS.md").read_text()
    for r in rows:
        assert r["date"] and r["machine"] and r["code"]
        assert int(r["registered"]) == 10  # a 10-image rendered arc: both register everything
        assert float(r["med_rot_deg"]) < 0.5
        parts = float(r["extract_s"]) + float(r["match_s"]) + float(r["map_s"])
        assert parts <= float(r["time_s"]) + 0.2  # the stages fit inside the measured total
