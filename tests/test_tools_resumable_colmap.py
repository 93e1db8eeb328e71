"""tools/resumable_colmap.py: the time ledger across segments, snapshot choice, and a COLMAP run
stopped at its budget and resumed to the end."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import resumable_colmap as rc


def _snapshot(root: Path, name: str, mtime: float, files=rc.MODEL_FILES) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    for f in files:
        (folder / f).write_bytes(b"x")
        os.utime(folder / f, (mtime, mtime))
    return folder


def test_credited_seconds_follow_the_segment_running_then():
    segments = [{"wall_start": 1000.0, "offset": 0.0}, {"wall_start": 5000.0, "offset": 250.0}]
    assert rc.credited_seconds(segments, 1200.0) == pytest.approx(200.0)  # first segment, 200 s in
    # between the segments (the machine did other things) nothing is credited beyond the first
    # segment's own clock; the second starts from what its snapshot was credited
    assert rc.credited_seconds(segments, 5100.0) == pytest.approx(350.0)
    with pytest.raises(ValueError):
        rc.credited_seconds(segments, 999.0)


def test_snapshots_are_complete_ones_oldest_first_and_pruning_keeps_the_newest(tmp_path):
    newest = _snapshot(tmp_path, "0003", 300.0)
    oldest = _snapshot(tmp_path, "0009", 100.0)  # names do not decide the order, times do
    middle = _snapshot(tmp_path, "0001", 200.0)
    _snapshot(tmp_path, "0005", 400.0, files=rc.MODEL_FILES[:2])  # half written: ignored
    assert rc.snapshots(tmp_path) == [oldest, middle, newest]
    assert rc.snapshot_time(newest) == pytest.approx(300.0)
    rc._prune(tmp_path)
    assert rc.snapshots(tmp_path) == [middle, newest][-rc.KEEP_SNAPSHOTS:]
    assert rc.snapshots(tmp_path / "absent") == []


@pytest.mark.slow
def test_a_stopped_run_resumes_from_its_snapshot_to_the_end(tmp_path, monkeypatch):
    """COLMAP stopped after 2 s and resumed gives the complete model, with the time of both
    segments; progress lines stay in order across the resume."""
    pytest.importorskip("pycolmap")
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    run_synth(tmp_path / "data", SynthOptions(scene="orbit", num_images=60, outlier_ratio=0.2, seed=0))
    db, work = tmp_path / "data" / "database.db", tmp_path / "work"
    monkeypatch.setattr(rc, "SNAPSHOT_EVERY", 5)
    model, first_s, finished, segments = rc.run_incremental(db, work, budget_s=2)
    assert not finished and segments == 1 and model is not None and first_s >= 2.0
    model, total_s, finished, segments = rc.run_incremental(db, work)
    assert finished and segments == 2 and total_s > first_s
    import pycolmap

    assert pycolmap.Reconstruction(str(model)).num_reg_images() == 60
    ledger = json.loads((work / "segments.json").read_text())
    assert ledger[1]["offset"] == pytest.approx(first_s, abs=0.5) and ledger[1]["from"]
    times = [float(line.split()[0]) for line in (work / "progress.txt").read_text().splitlines()]
    assert times == sorted(times) and times[-1] <= total_s


@pytest.mark.slow
def test_a_run_killed_in_its_final_refinement_resumes_to_a_refined_model(tmp_path, monkeypatch):
    """Snapshots are taken while the model grows, so the newest one of a run killed in its final
    refinement holds every image unrefined; resuming it registers nothing, and COLMAP would
    then skip its final refinement.  The resumed run does it: the model is the one the
    uninterrupted run ends with, not the snapshot."""
    pytest.importorskip("pycolmap")
    import numpy as np
    import pycolmap

    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    run_synth(tmp_path / "data", SynthOptions(scene="orbit", num_images=40, outlier_ratio=0.2, seed=0))
    db, work = tmp_path / "data" / "database.db", tmp_path / "work"
    monkeypatch.setattr(rc, "SNAPSHOT_EVERY", 1)  # the newest snapshot: the last registration
    full_dir, _, finished, _ = rc.run_incremental(db, work)
    assert finished
    full = pycolmap.Reconstruction(str(full_dir))
    snap = pycolmap.Reconstruction(str(rc.snapshots(work / "snapshots")[-1]))
    assert snap.num_reg_images() == full.num_reg_images() == 40
    # As if killed in the final refinement: the next call resumes from that snapshot.
    model_dir, _, finished, segments = rc.run_incremental(db, work)
    assert finished and segments == 2
    resumed = pycolmap.Reconstruction(str(model_dir))
    assert resumed.num_reg_images() == 40
    # The refinement moves the intrinsics (focal length by ~0.07 px here); the resumed run
    # lands where the uninterrupted one did.
    params = lambda rec: np.asarray(rec.cameras[1].params)
    assert np.abs(params(snap) - params(full)).max() > 1e-2
    assert np.abs(params(resumed) - params(full)).max() < 1e-3
    assert resumed.compute_mean_reprojection_error() == pytest.approx(full.compute_mean_reprojection_error(), rel=1e-4)
