"""The Dask executor gives the same local models as the local one (same payloads, same seed)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("distributed")

from sfm.dask_executor import DaskExecutor  # noqa: E402
from sfm.executors import LocalExecutor  # noqa: E402
from sfm.mapper_input import MapperOptions  # noqa: E402
from sfm.mapping import load_payloads  # noqa: E402
from sfm.synthetic import SynthOptions, run_synth  # noqa: E402


def test_dask_local_cluster_matches_local_executor(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=24, observations_per_image=400, seed=3))
    names = sorted(f"aerial_{i:05d}.jpg" for i in range(24))
    payloads = load_payloads(tmp_path / "database.db", [names[:14], names[10:]], True, 15)
    local = {r.index: r for r in LocalExecutor(workers=1).run(payloads, MapperOptions())}
    executor = DaskExecutor(workers=2)
    remote = {r.index: r for r in executor.run(payloads, MapperOptions())}
    assert executor.address and executor.address.startswith("tcp://")
    for k in (0, 1):
        assert remote[k].error is None and remote[k].worker.startswith("tcp://")
        a, b = local[k].models[0], remote[k].models[0]
        assert sorted(a.images) == sorted(b.images)
        for i in a.images:
            np.testing.assert_array_equal(a.images[i].cam_from_world_rotation, b.images[i].cam_from_world_rotation)
        assert len(a.points3D) == len(b.points3D)
