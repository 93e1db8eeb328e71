"""A real Dask cluster on loopback: a scheduler and two worker processes started as commands, as
on several machines.  The whole pipeline on it gives the local executor's model; losing a worker
while it runs a cluster loses nothing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

from sfm.cli import main
from sfm.io.colmap_model import read_model
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene


class LoopbackCluster:
    """``dask scheduler`` and two ``dask worker`` processes (no nanny: a killed worker stays dead)."""

    def __init__(self, tmp: Path, workers: int = 2) -> None:
        self.tmp = tmp
        env = dict(os.environ, DASK_DISTRIBUTED__WORKER__DAEMON="False")
        file = tmp / "scheduler.json"
        self.scheduler = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(file)], env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 60
        while not file.exists() and time.time() < deadline:
            time.sleep(0.1)
        import json

        time.sleep(0.2)
        self.address = json.loads(file.read_text())["address"]
        self.workers = [subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", self.address, "--nworkers", "1",
             "--nthreads", "1", "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"], env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for _ in range(workers)]
        from distributed import Client

        self.client = Client(self.address, timeout="60s")
        self.client.wait_for_workers(workers, timeout=120)

    def pids(self) -> dict[str, int]:
        """Worker address -> process id."""
        return self.client.run(os.getpid)

    def close(self) -> None:
        """Stop the workers, then the scheduler (a worker that stops tells its scheduler, and
        waited for one already stopping); a process that outlives 20 s is killed, and every one
        is reaped."""
        self.client.close()
        for group in (self.workers, [self.scheduler]):
            for p in group:
                if p.poll() is None:
                    p.terminate()
            for p in group:
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


@pytest.fixture
def loopback(tmp_path):
    cluster = LoopbackCluster(tmp_path)
    yield cluster
    cluster.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene")
    write_rendered_scene(out, RenderOptions(num_images=20, seed=5))
    return out


def _poses(model_dir: Path) -> dict[str, np.ndarray]:
    model = read_model(model_dir)
    return {im.name: np.concatenate([im.cam_from_world_rotation.ravel(), im.cam_from_world_translation])
            for im in model.images.values()}


def test_reconstruct_on_loopback_scheduler_equals_local(tmp_path, scene, loopback):
    common = ["--images", str(scene / "images"), "--max-cluster-size", "8", "--seed", "0", "--no-recording"]
    assert main(["reconstruct", "--workspace", str(tmp_path / "local"), "--workers", "2", *common]) == 0
    assert main(["reconstruct", "--workspace", str(tmp_path / "dask"), "--executor", "dask",
                 "--scheduler", loopback.address, *common]) == 0
    import json

    report = json.loads((tmp_path / "dask" / "report.json").read_text())
    assert report["executor"] == "dask" and report["scheduler"] == loopback.address
    assert report["num_clusters"] >= 2 and report["registered"] == 20
    workers = {c["worker"] for c in report["clusters"]}
    assert workers <= set(loopback.pids()), workers  # every cluster names the worker that ran it
    local, remote = _poses(tmp_path / "local" / "sparse" / "0"), _poses(tmp_path / "dask" / "sparse" / "0")
    assert sorted(local) == sorted(remote) and len(local) == 20
    for name in local:
        np.testing.assert_allclose(remote[name], local[name], atol=1e-9)
    a, b = read_model(tmp_path / "local" / "sparse" / "0"), read_model(tmp_path / "dask" / "sparse" / "0")
    assert len(a.points3D) == len(b.points3D)


def _kill_first_busy_worker(loopback: LoopbackCluster, killed: list, stop: threading.Event) -> None:
    """Wait until a worker is running a local-SfM task, let it work a moment, then SIGKILL it."""
    pids = loopback.pids()
    while not stop.is_set():
        busy = [w for w, keys in loopback.client.processing().items()
                if any(str(k).startswith("sfm-") for k in keys)]
        if busy:
            time.sleep(0.3)
            os.kill(pids[busy[0]], signal.SIGKILL)
            killed.append(busy[0])
            return
        time.sleep(0.02)


def test_run_survives_a_killed_worker(tmp_path, loopback):
    from sfm.stages.synth import run_synth
    from sfm.synthetic.options import SynthOptions

    work = tmp_path / "work"
    run_synth(work, SynthOptions(scene="aerial", num_images=60, observations_per_image=400, seed=2))
    killed: list[str] = []
    stop = threading.Event()
    killer = threading.Thread(target=_kill_first_busy_worker, args=(loopback, killed, stop), daemon=True)
    killer.start()
    try:
        code = main(["reconstruct", "--workspace", str(work), "--executor", "dask", "--scheduler",
                     loopback.address, "--max-cluster-size", "20", "--no-recording"])
    finally:
        stop.set()
        killer.join(5)
    assert code == 0
    assert killed, "no worker was killed: the clusters finished before the killer saw them"
    assert sum(p.poll() is not None for p in loopback.workers) == 1  # one worker really died
    import json

    report = json.loads((work / "report.json").read_text())
    assert not report.get("failed_clusters")
    assert report["registered"] == 60
    assert killed[0] not in {c["worker"] for c in report["clusters"]}  # its cluster ran elsewhere
