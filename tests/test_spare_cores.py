"""A task that runs in this process borrows the idle workers' cores for an independent piece of
its work (``sfm.execution.spare_cores``): the piece runs in a process of its own only when a core
is spare, gives the same value either way, and is computed here when that process dies."""

from __future__ import annotations

import multiprocessing
import operator
import os
from dataclasses import replace

import numpy as np
import pytest

import sfm.mapper.self_calibration as self_calibration
from sfm.execution import spare_cores as spare
from sfm.execution.local import LocalExecutor
from sfm.io.colmap_model import read_model
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import make_scene

pytestmark = pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(),
                                reason="the side process forks from the pipeline's fork server")


def _dies_outside(parent: int) -> int:
    """Kills the process it runs in unless that is ``parent``."""
    if os.getpid() != parent:
        os._exit(3)
    return parent


def _spare_now(_) -> int:
    return spare._SPARE.get()


def test_without_a_spare_core_the_piece_runs_here():
    assert spare.run_beside(operator.call, os.getpid)() == os.getpid()
    with spare.spare_cores(0):
        assert spare.run_beside(operator.call, os.getpid)() == os.getpid()


def test_a_spare_core_runs_the_piece_in_a_process_of_its_own():
    with spare.spare_cores(1):
        elsewhere = spare.run_beside(operator.call, os.getpid)
        assert elsewhere() != os.getpid()
        assert spare.run_beside(sum, [1, 2, 3])() == 6


def test_a_side_process_that_dies_is_replaced_by_computing_here():
    with spare.spare_cores(1):
        assert spare.run_beside(_dies_outside, os.getpid())() == os.getpid()


def test_a_map_run_in_this_process_lends_the_other_workers_cores():
    assert [r.value for r in LocalExecutor(2).map(_spare_now, [0])] == [1]
    assert [r.value for r in LocalExecutor(1).map(_spare_now, [0, 1])] == [0, 0]
    assert [r.value for r in LocalExecutor(2).map(_spare_now, [0, 1, 2])] == [0, 0, 0]  # pool workers: none spare
    assert spare._SPARE.get() == 0


def test_the_principal_points_halves_on_a_spare_core_give_the_same_model(tmp_path, monkeypatch):
    """The split-sample test's first half runs beside the second when the map stage has one
    cluster and two workers; the model is the same, bit for bit, as with one worker."""
    opts = SynthOptions(scene="orbit", num_images=12, observations_per_image=500, seed=3)
    scene = make_scene(opts)
    moved = replace(scene, keypoints=[k + np.array([20.0, -12.0]) for k in scene.keypoints])  # an off-centre point
    pairs = simulate_matching(scene, opts)
    seen = []
    real = self_calibration.run_beside

    def spy(func, item, **kwargs):
        seen.append(spare._SPARE.get())
        return real(func, item, **kwargs)

    monkeypatch.setattr(self_calibration, "run_beside", spy)
    models = {}
    for workers in (1, 2):
        ws = tmp_path / f"w{workers}"
        ws.mkdir()
        write_database(moved, pairs, ws / "database.db", camera_model="SIMPLE_RADIAL")
        run_map(ws, MapperOptions(), executor=LocalExecutor(workers))
        models[workers] = read_model(ws / "sparse" / "0")
    assert seen == [0, 1]  # the halves ran once per model: here, then beside
    [one], [two] = models[1].cameras.values(), models[2].cameras.values()
    np.testing.assert_array_equal(one.params, two.params)
    assert abs(one.params[1] - (scene.width - 1) / 2 - 20.0) < 2.0  # the test refined the principal point
    for image_id, image in models[1].images.items():
        np.testing.assert_array_equal(image.cam_from_world_rotation, models[2].images[image_id].cam_from_world_rotation)
        np.testing.assert_array_equal(image.cam_from_world_translation,
                                      models[2].images[image_id].cam_from_world_translation)


def test_a_piece_that_does_not_fit_beside_runs_here():
    with spare.spare_cores(1):
        assert spare.run_beside(operator.call, os.getpid, fits=False)() == os.getpid()
