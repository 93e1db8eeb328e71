"""tools/bench_scaling.py: the exponent fit, the process-tree memory sampler and the table."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_scaling import fit_exponent, main, make_aerial, report, run_child, tree_rss


def test_fit_exponent_recovers_a_power_law_from_500_images_up():
    rows = [{"images": n, "time_s": 0.02 * n**1.37} for n in (250, 500, 1000, 2000, 4000)]
    rows[0]["time_s"] *= 10  # below 500 images: not part of the fit
    assert abs(fit_exponent(rows) - 1.37) < 1e-9
    assert fit_exponent(rows[:2]) is None  # one size from 500 up: no fit


def test_tree_rss_counts_children():
    child = subprocess.Popen([sys.executable, "-c", "import time; b = b\"\\x01\" * (300 * 2**20); time.sleep(5)"])
    try:
        time.sleep(1.5)
        import os

        assert tree_rss(os.getpid()) >= tree_rss(child.pid) > 300 * 2**20
    finally:
        child.kill()
        child.wait()


def test_run_child_reports_the_peak_of_the_tree():
    code = "import time; b = b\"\\x01\" * (200 * 2**20); time.sleep(1.0)"
    rc, seconds, peak = run_child([sys.executable, "-c", code])
    assert rc == 0 and seconds >= 1.0 and 200 * 2**20 < peak < 400 * 2**20


def test_report_table_ratio_and_skipped_peers(tmp_path):
    results = {
        (500, "graphsfm-2"): {"images": 500, "method": "graphsfm-2", "time_s": 50.0, "registered": 500},
        (500, "colmap-incremental"): {"images": 500, "method": "colmap-incremental", "time_s": 200.0},
        (500, "colmap-global"): {"images": 500, "method": "colmap-global", "time_s": 80.0},
        (1000, "graphsfm-2"): {"images": 1000, "method": "graphsfm-2", "time_s": 100.0, "registered": 1000},
    }
    text = report(tmp_path, [500, 1000], results, skip_peers_above=500)
    assert "| 500 | graphsfm-2 | 50.0 |" in text and text.count("| 0.25 | 0.62 |") == 1  # to incremental, to global
    assert text.count("| 0.40 | 1.00 |") == 1  # colmap-global's own row
    assert "| 1000 | colmap-hierarchical | skipped (peers above 500 images) |" in text
    assert "| 1000 | colmap-incremental | skipped (peers above 500 images) |" in text
    assert "| 500 | graphsfm-1 | not run |" in text
    assert "- graphsfm-2: 1.00" in text and "- colmap-hierarchical: too few sizes" in text
    assert np.isfinite(fit_exponent([r for (n, m), r in results.items() if m == "graphsfm-2"]))


def test_report_says_how_far_an_unfinished_run_got(tmp_path):
    log = tmp_path / "runs" / "2000" / "colmap-incremental" / "progress.txt"
    log.parent.mkdir(parents=True)
    log.write_text("80.0 102\n3405.1 1156\n")  # "seconds registered", as resumable_colmap appends
    text = report(tmp_path, [2000], {}, skip_peers_above=2000)
    assert "| 2000 | colmap-incremental | > 3405 (stopped unfinished: 1156/2000 registered by then) |" in text
    assert "| 2000 | colmap-global | not run |" in text  # no progress log: not run


def test_report_only_runs_nothing_and_reads_the_cache(tmp_path):
    cache = tmp_path / "runs" / "500" / "graphsfm-2.json"
    cache.parent.mkdir(parents=True)
    cache.write_text('{"images": 500, "method": "graphsfm-2", "time_s": 50.0, "registered": 500}')
    page = tmp_path / "BENCHMARKS.md"
    assert main(["--out", str(tmp_path), "--sizes", "500", "1000", "--methods", "graphsfm-2", "--report-only",
                 "--page", str(page)]) == 0
    text = (tmp_path / "scaling.md").read_text()
    assert "| 500 | graphsfm-2 | 50.0 |" in text and "| 1000 | graphsfm-2 | not run |" in text
    section = page.read_text()  # the benchmarks page's section holds the same table
    assert "<!-- bench:scaling -->" in section and "| 500 | graphsfm-2 | 50.0 |" in section
    assert not (tmp_path / "data").exists()  # no scene was generated, nothing was mapped


def test_report_says_which_runs_were_resumed(tmp_path):
    results = {
        (2000, "colmap-incremental"): {"images": 2000, "method": "colmap-incremental", "time_s": 9000.0,
                                       "registered": 2000, "segments": 3},
        (2000, "graphsfm-2"): {"images": 2000, "method": "graphsfm-2", "time_s": 900.0, "registered": 2000,
                               "segments": 1},
    }
    text = report(tmp_path, [2000], results)
    assert "- colmap-incremental at 2000 images ran in 3 segments" in text
    assert "graphsfm-2 at 2000 images ran in" not in text and "| 0.10 |" in text


def test_rows_say_which_code_ran(tmp_path):
    import re

    from bench_scaling import code_version

    here = code_version("graphsfm-2")
    if here.startswith("unknown"):
        import pytest

        pytest.skip("not a git checkout")
    assert re.fullmatch(r"code [0-9a-f]{8}(\+dirty)?", here)
    assert code_version("colmap-global").startswith("pycolmap ")
    results = {
        (500, "graphsfm-2"): {"images": 500, "method": "graphsfm-2", "time_s": 50.0, "code": here},
        (500, "graphsfm-1"): {"images": 500, "method": "graphsfm-1", "time_s": 80.0},  # cached before codes
    }
    text = report(tmp_path, [500], results)
    assert f"| {here} |" in text and "| 500 | graphsfm-1 | 80.0 |" in text and "| not recorded |" in text


def test_the_table_shows_cached_rows_of_methods_not_run_this_time(tmp_path):
    runs = tmp_path / "runs" / "500"
    (runs / "colmap-incremental").mkdir(parents=True)
    (runs / "colmap-incremental" / "progress.txt").write_text("10.0 250\n")  # its log, from before it ended
    (runs / "colmap-incremental.json").write_text('{"images": 500, "method": "colmap-incremental", "time_s": 200.0}')
    (runs / "graphsfm-2.json").write_text('{"images": 500, "method": "graphsfm-2", "time_s": 50.0}')
    assert main(["--out", str(tmp_path), "--sizes", "500", "--methods", "graphsfm-2", "--report-only", "--no-page"]) == 0
    text = (tmp_path / "scaling.md").read_text()
    assert "| 500 | colmap-incremental | 200.0 |" in text and "stopped unfinished" not in text
    assert "| 500 | graphsfm-2 | 50.0 |" in text and "| 0.25 |" in text


def test_the_exponent_is_fitted_on_the_rows_of_one_code(tmp_path):
    """Rows of an earlier code stay in the table but not in the fit: t = n (b = 1) for the
    newest code's three sizes, a slower earlier row at 4000 images left out."""
    def row(n, t, code, date):
        return {"images": n, "method": "graphsfm-2", "time_s": t, "registered": n, "code": code, "date": date}

    results = {(n, "graphsfm-2"): row(n, float(n), "code new", "2026-12-08") for n in (500, 1000, 2000)}
    results[(4000, "graphsfm-2")] = row(4000, 40000.0, "code old", "2026-12-01")
    text = report(tmp_path, [500, 1000, 2000, 4000], results)
    assert "| 4000 | graphsfm-2 | 40000.0 |" in text
    assert "- graphsfm-2: 1.00 (code new, 3 sizes)" in text


def test_make_aerial_writes_the_block_in_a_child_process(tmp_path):
    make_aerial(tmp_path / "data", 12)
    from sfm.io.database import Database

    with Database(tmp_path / "data" / "database.db", readonly=True) as db:
        assert len(db.read_images()) == 12
    assert len((tmp_path / "data" / "gt" / "cameras_gt_opencv.txt").read_text().splitlines()) == 13
