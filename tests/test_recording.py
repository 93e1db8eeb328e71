"""The Rerun recorder (``sfm.viz.recorder``): its stream opens in a background thread."""

from __future__ import annotations

import numpy as np
import pytest

from sfm.viz.recorder import Recorder, entity_paths


def test_what_is_logged_right_after_construction_reaches_the_file(tmp_path):
    rr = pytest.importorskip("rerun")
    path = tmp_path / "out" / "recording.rrd"
    with Recorder(path, tmp_path) as recorder:
        assert recorder.enabled
        recorder.stage("map")
        recorder.log("world/points", rr.Points3D(np.zeros((3, 3))))
    assert not recorder.enabled  # closed
    assert any(p.endswith("world/points") for p in entity_paths(path))


def test_a_stream_that_cannot_open_fails_at_its_first_use(tmp_path):
    pytest.importorskip("rerun")
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    recorder = Recorder(blocker / "sub" / "recording.rrd", tmp_path)  # returns at once
    with pytest.raises(OSError):
        recorder.stage("extract")
    assert not recorder.enabled  # reported once; the run may go on without a recording


def test_a_disabled_recorder_accepts_every_call():
    recorder = Recorder.disabled()
    recorder.stage("map")
    recorder.log("world/points")
    recorder.close()
    assert not recorder.enabled
