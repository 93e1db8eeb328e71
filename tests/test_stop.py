"""Ctrl-C (SIGINT) or SIGTERM mid-stage ends a real ``python -m sfm reconstruct`` with one
line saying where it stopped and that rerunning resumes, leaves no process behind (pool
workers, their fork server), and the rerun finishes the model; a run that ends normally has
what it left in its process group ended, without waiting on zombies
(``sfm.execution.processes``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sfm.execution import processes
from sfm.execution.processes import descendants, group_members
from sfm.stages.synth import run_synth
from sfm.synthetic.options import RenderOptions, SynthOptions
from sfm.synthetic.rendered import write_rendered_scene

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


def _group(pgid: int) -> list[int]:
    """Live processes of process group ``pgid``."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[2]) == pgid and fields[0] != "Z":
                out.append(int(entry))
    return out


def _alive(pids: list[int]) -> list[int]:
    alive = []
    for pid in pids:
        try:
            if "State:\tZ" not in Path(f"/proc/{pid}/status").read_text():
                alive.append(pid)
        except OSError:
            pass
    return alive


def _stop_mid_stage(argv: list[str], log: Path, marker: str, signum: int) -> tuple[subprocess.CompletedProcess, list]:
    """Start ``graphsfm argv``, wait until ``log`` shows ``marker`` (the stage is running), send
    ``signum``; the finished process and the processes the run had started."""
    proc = subprocess.Popen([sys.executable, "-m", "sfm", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=_env())
    deadline = time.monotonic() + 600
    while not (log.exists() and marker in log.read_text()):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the stage never started"
        time.sleep(0.05)
    started = descendants(proc.pid)
    [child] = [p for p in started if Path(f"/proc/{p}/stat").exists() and int(
        Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[1]) == proc.pid] or [None]
    assert child is not None
    started = sorted(set(started) | set(_group(child)))
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)  # a guard: the stop itself takes well under a second
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), started


def _check_stopped(done: subprocess.CompletedProcess, started: list[int], code: int, name: str, stage: str):
    assert done.returncode == code, done.stderr[-2000:]
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in done.stderr and "Warning" not in done.stderr, done.stderr[-2000:]
    assert lines[-1].startswith(f"graphsfm reconstruct: stopped by {name} during {stage}")
    assert lines[-1].endswith("; rerun the same command to resume")
    assert len(started) >= 3  # the run, its fork server and pool workers at least
    for _ in range(50):  # reaped by init a moment after being killed
        if not _alive(started):
            break
        time.sleep(0.1)
    assert _alive(started) == []


def test_ctrl_c_during_matching_stops_everything_and_the_rerun_resumes(tmp_path):
    scene = write_rendered_scene(tmp_path / "scene", RenderOptions(num_images=16, seed=5))
    ws = tmp_path / "ws"
    argv = ["reconstruct", "--images", scene["image_dir"], "--workspace", str(ws), "--no-recording", "--workers", "2"]
    done, started = _stop_mid_stage(argv, ws / "log.txt", "pairs selected", signal.SIGINT)
    _check_stopped(done, started, 130, "Ctrl-C (SIGINT)", "match")
    report = json.loads((ws / "report.json").read_text())
    assert report["status"] == "stopped" and report["finished"]
    assert "stopped by Ctrl-C (SIGINT) during match" in (ws / "log.txt").read_text()
    assert (ws / "run.lock").read_text() == ""
    rerun = subprocess.run([sys.executable, "-m", "sfm", *argv], capture_output=True, text=True, env=_env(),
                           timeout=900)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert "16 images already have features" in rerun.stderr and "already verified (resumed)" in rerun.stderr
    report = json.loads((ws / "report.json").read_text())
    assert report["status"] == "finished" and report["registered"] == 16


def test_sigterm_during_the_clusters_local_sfm_stops_every_worker(tmp_path):
    ws = tmp_path / "ws"
    run_synth(ws, SynthOptions(scene="aerial", num_images=90, observations_per_image=600, seed=0))
    argv = ["reconstruct", "--workspace", str(ws), "--no-recording", "--workers", "2", "--max-cluster-size", "35"]
    done, started = _stop_mid_stage(argv, ws / "log.txt", "initial pair", signal.SIGTERM)
    _check_stopped(done, started, 143, "SIGTERM", "map (")
    assert json.loads((ws / "report.json").read_text())["status"] == "stopped"


def _zombie_in_own_group() -> subprocess.Popen:
    """A process in a process group of its own that has exited and is not reaped yet."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"], preexec_fn=os.setpgrp)
    deadline = time.monotonic() + 60
    while "State:\tZ" not in Path(f"/proc/{proc.pid}/status").read_text():
        assert time.monotonic() < deadline
        time.sleep(0.01)
    return proc


def _record_killpg(monkeypatch) -> list[int]:
    sent: list[int] = []
    real = os.killpg

    def killpg(pgid: int, signum: int) -> None:
        sent.append(signum)
        real(pgid, signum)

    monkeypatch.setattr(processes.os, "killpg", killpg)
    return sent


def test_the_end_of_a_run_does_not_wait_for_zombies_to_be_reaped(monkeypatch):
    zombie = _zombie_in_own_group()
    try:
        assert group_members(zombie.pid) == []
        sent = _record_killpg(monkeypatch)
        processes._end_group(zombie.pid)
        # a zombie holds nothing: no wait for its reaping, so no SIGKILL after the grace time
        assert sent == [signal.SIGTERM]
    finally:
        zombie.wait()


def test_the_end_of_a_run_ends_what_is_left_in_its_group(monkeypatch):
    leftover = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"], preexec_fn=os.setpgrp)
    try:
        deadline = time.monotonic() + 60
        while group_members(leftover.pid) != [leftover.pid]:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        sent = _record_killpg(monkeypatch)
        processes._end_group(leftover.pid)
        assert sent == [signal.SIGTERM]
        assert leftover.wait(timeout=60) == -signal.SIGTERM
    finally:
        leftover.kill()
        leftover.wait()
