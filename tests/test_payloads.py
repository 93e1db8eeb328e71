"""Cluster payloads are read from the database one at a time, and the local executor keeps only
a few in flight: memory grows with the clusters being mapped, not with the scene."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pytest

from sfm.execution.local import LocalExecutor
from sfm.mapper.payload import MapperInput
from sfm.mapper.options import MapperOptions
from sfm.stages.map import map_cluster
from sfm.stages.payloads import ClusterPayloads, load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("payloads")
    run_synth(folder, SynthOptions(scene="aerial", num_images=24, observations_per_image=400, seed=5))
    names = sorted(f"aerial_{i:05d}.jpg" for i in range(24))
    return folder / "database.db", names


def test_a_cluster_payload_is_the_whole_payload_restricted_to_its_images(scene):
    db, names = scene
    [whole] = load_payloads(db, None, True, 15)
    clusters = [names[:9], names[6:17], names[15:]]
    lazy = ClusterPayloads(db, clusters, True, 15, labels=["A", "B", "C"])
    assert len(lazy) == 3 and lazy.labels == ["A", "B", "C"] and lazy.sizes == [9, 11, 9]
    assert lazy.names == [sorted(c) for c in clusters]  # known without reading a payload
    index = {n: k for k, n in enumerate(whole.names)}
    for k, cluster in enumerate(clusters):
        p = lazy[k]
        assert isinstance(p, MapperInput) and p.label == "ABC"[k] and p.names == sorted(cluster)
        g = [index[n] for n in p.names]  # local -> whole index
        for a, n in enumerate(p.names):
            np.testing.assert_array_equal(p.keypoints[a], whole.keypoints[index[n]])
        expected = {(g.index(i), g.index(j)): m for i, j, m, _ in whole.pairs if i in g and j in g}
        got = {(i, j): m for i, j, m, _ in p.pairs}
        assert sorted(got) == sorted(expected) and len(got) > 0
        for key, m in got.items():
            np.testing.assert_array_equal(m, expected[key])
    assert [p.label for p in lazy] == ["A", "B", "C"]  # iterable like a list


class CountingPayloads(Sequence):
    """A lazy payload sequence that records how many payloads were read."""

    def __init__(self, inner: ClusterPayloads) -> None:
        self.inner, self.read = inner, 0
        self.sizes, self.labels = inner.sizes, inner.labels

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, k):
        self.read += 1
        return self.inner[k]


def test_the_local_pool_reads_payloads_as_workers_free_up(scene):
    db, names = scene
    clusters = [names[k : k + 8] for k in range(0, 24, 3) if k + 8 <= 24]  # 6 overlapping clusters
    payloads = CountingPayloads(ClusterPayloads(db, clusters, True, 15))
    workers, seen = 2, []
    items = ((payloads[k], MapperOptions()) for k in range(len(payloads)))
    for result in LocalExecutor(workers=workers).map(map_cluster, items, num_items=len(payloads), ordered=False):
        seen.append(result.index)
        assert result.error is None and result.value
        assert payloads.read - len(seen) <= 2 * workers  # never more than two per worker in flight
    assert sorted(seen) == list(range(len(clusters))) and payloads.read == len(clusters)


def test_keypoint_scales_reach_the_mapper_as_observation_sigmas(scene, tmp_path):
    """A database keypoint table with scales gives (K, 3) payload keypoints, and the mapper
    weighs each observation by ``localization_sigma`` of its scale unless told not to."""
    import shutil

    from sfm.io.database import Database
    from sfm.mapper.state import MapperState

    db = tmp_path / "database.db"
    shutil.copy(scene[0], db)
    with Database(db) as d:
        image_id = d.image_id_by_name()[scene[1][3]]
        xy = d.read_keypoints(image_id)[:, :2]
        scales = np.linspace(0.5, 6.0, len(xy))
        d.write_keypoints(image_id, np.column_stack([xy, scales, np.zeros(len(xy))]).astype(np.float32))
    [payload] = load_payloads(db, None, True, 15)
    k = payload.names.index(scene[1][3])
    assert payload.keypoints[k].shape == (len(xy), 3)
    np.testing.assert_allclose(payload.keypoints[k][:, 2], scales.astype(np.float32))
    assert all(p.shape[1] == 2 for j, p in enumerate(payload.keypoints) if j != k)
    state = MapperState(payload, MapperOptions())
    rows = state.image_rows[k]
    assert len(rows) > 100
    expected = np.maximum(1.0, scales.astype(np.float32)[state.obs_kp[rows]] / 0.8)
    np.testing.assert_allclose(state.obs_sigma[rows], expected, rtol=1e-6)
    others = np.setdiff1d(np.arange(len(state.obs_sigma)), rows)
    assert np.all(state.obs_sigma[others] == 1.0)
    plain = MapperState(payload, MapperOptions(scale_weights=False))
    assert np.all(plain.obs_sigma == 1.0)
