"""The Dask executor gives the same local models as the local one (same payloads, same seed)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

pytest.importorskip("distributed")

from sfm.execution.dask_cluster import DaskExecutor
from sfm.execution.local import LocalExecutor
from sfm.mapper.options import MapperOptions
from sfm.stages.map import map_cluster
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def test_dask_local_cluster_matches_local_executor(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=24, observations_per_image=400, seed=3))
    names = sorted(f"aerial_{i:05d}.jpg" for i in range(24))
    payloads = load_payloads(tmp_path / "database.db", [names[:14], names[10:]], True, 15)
    tasks = [(p, MapperOptions()) for p in payloads]
    local = {r.index: r for r in LocalExecutor(workers=1).map(map_cluster, tasks, ordered=False)}
    with DaskExecutor(workers=2) as executor:
        remote = {r.index: r for r in executor.map(map_cluster, tasks, ordered=False, errors="return")}
        assert executor.address and executor.address.startswith("tcp://")
    for k in (0, 1):
        assert remote[k].error is None and remote[k].worker.startswith("tcp://")
        a, b = local[k].value[0], remote[k].value[0]
        assert sorted(a.images) == sorted(b.images)
        for i in a.images:
            np.testing.assert_array_equal(a.images[i].cam_from_world_rotation, b.images[i].cam_from_world_rotation)
        assert len(a.points3D) == len(b.points3D)


def test_dask_extract_and_match_write_the_same_database(tmp_path):
    """Features and verified pairs computed on Dask workers (image bytes and feature arrays travel,
    not paths) equal the local ones."""
    from sfm.io.database import Database
    from sfm.features.options import ExtractOptions
    from sfm.stages.extract import run_extract
    from sfm.matching.options import MatchOptions
    from sfm.stages.match import run_match
    from sfm.synthetic.options import RenderOptions
    from sfm.synthetic.rendered import write_rendered_scene

    write_rendered_scene(tmp_path / "scene", RenderOptions(num_images=6, seed=1))
    images = tmp_path / "scene" / "images"
    run_extract(images, tmp_path / "local", ExtractOptions(), LocalExecutor(1))
    run_match(tmp_path / "local", MatchOptions(), LocalExecutor(1))
    with DaskExecutor(workers=2) as executor:
        run_extract(images, tmp_path / "dask", ExtractOptions(), executor)
        result = run_match(tmp_path / "dask", MatchOptions(), executor)
    assert result.num_pairs_processed == 15 and result.num_verified >= 10
    with Database(tmp_path / "local" / "database.db") as a, Database(tmp_path / "dask" / "database.db") as b:
        assert {i.name for i in a.read_images().values()} == {i.name for i in b.read_images().values()}
        for image_id in a.read_images():
            np.testing.assert_array_equal(a.read_keypoints(image_id), b.read_keypoints(image_id))
            np.testing.assert_array_equal(a.read_descriptors(image_id), b.read_descriptors(image_id))
        ga, gb = a.read_two_view_geometries(), b.read_two_view_geometries()
        assert sorted(ga) == sorted(gb)
        for pair in ga:
            assert ga[pair].config == gb[pair].config
            np.testing.assert_array_equal(ga[pair].inlier_matches, gb[pair].inlier_matches)


def test_dask_workers_log_lines_reach_the_client_tagged_with_their_cluster(tmp_path, caplog):
    """A task's log records return with its result and are handled by the client's loggers, with
    the cluster they come from (``sfm.execution.logs``)."""
    import os

    run_synth(tmp_path, SynthOptions(scene="aerial", num_images=24, observations_per_image=400, seed=3))
    names = sorted(f"aerial_{i:05d}.jpg" for i in range(24))
    payloads = load_payloads(tmp_path / "database.db", [names[:14], names[10:]], True, 15)
    tasks = [(p, MapperOptions()) for p in payloads]
    with caplog.at_level("INFO"), DaskExecutor(workers=2) as executor:
        results = list(executor.map(map_cluster, tasks, ordered=False, errors="return"))
    assert all(r.error is None for r in results)
    starts = [r for r in caplog.records if "initial pair" in r.getMessage()]
    assert sorted(r.task for r in starts) == sorted(p.label for p in payloads)
    assert all(r.process != os.getpid() and r.name == "sfm.mapper.state" for r in starts)
    assert not [r for r in caplog.records if r.levelno < logging.INFO and r.process != os.getpid()]
