"""The merged model starts from the local models' own points (Alg. 2's C_final holds cameras and
points): sfm.merge.alignment.merged_points and MapperState.seed_points."""

from __future__ import annotations

import numpy as np

from backend.sim3 import Sim3
from graph.merge_plan import MergePlan
from sfm.core.model import Camera, Image, Reconstruction
from sfm.evaluation.ground_truth import read_gt_table
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.state import MapperState
from sfm.merge.alignment import merged_points
from sfm.merge.cluster_graph import LocalModel
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def _model(names: list[str], points: list[tuple[list[float], list[tuple[int, int]]]]) -> Reconstruction:
    recon = Reconstruction()
    recon.cameras[1] = Camera(1, "SIMPLE_RADIAL", 640, 480, np.array([500.0, 320.0, 240.0, 0.0]))
    for k, name in enumerate(names):
        recon.images[10 + k] = Image(10 + k, name, 1, keypoints=np.zeros((5, 2)))
    for xyz, track in points:
        recon.add_point3D(np.array(xyz), [(10 + k, kp) for k, kp in track])
    return recon


def test_merged_points_moves_each_model_by_its_similarity_nearest_the_anchor_first():
    anchor = _model(["a", "b"], [([0.0, 0.0, 1.0], [(0, 3), (1, 4)])])
    other = _model(["b", "c"], [([1.0, 0.0, 0.0], [(0, 2), (1, 0)]), ([0.0, 1.0, 0.0], [(1, 1), (0, 1)])])
    plan = MergePlan(anchor=1, clusters=(0, 1), total_size=4, parent={1: None, 0: 1}, layer={0: 1, 1: 1},
                     num_layers=1, path={1: (1,), 0: (0, 1)}, edges=((0, 1, 1.0),), merge_order=((0, 1),))
    sims = {1: Sim3(), 0: Sim3(scale=2.0, translation=np.array([0.0, 0.0, 5.0]))}
    names, keypoints, owner, xyz = merged_points([LocalModel("C0/0", anchor), LocalModel("C1/0", other)], plan, sims)
    # node 1 is the anchor: its two points come first, as given; node 0's point is moved
    assert names == ["b", "c", "c", "b", "a", "b"]
    np.testing.assert_array_equal(keypoints, [2, 0, 1, 1, 3, 4])
    np.testing.assert_array_equal(owner, [0, 0, 1, 1, 2, 2])
    np.testing.assert_allclose(xyz, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 7.0]])


def _street(tmp_path):
    """A state of a synthetic street with every image registered at its true pose."""
    if not (tmp_path / "database.db").exists():
        run_synth(tmp_path, SynthOptions(scene="street", num_images=8, observations_per_image=500,
                                         outlier_ratio=0.2, seed=5))  # fmt: skip
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    state.set_poses({n: (gt[n].rotation, gt[n].translation) for n in state.names})
    return state


def _rows_of(model: Reconstruction):
    points = list(model.points3D.values())
    names = [model.images[i].name for p in points for i, _ in p.track]
    keypoints = np.array([kp for p in points for _, kp in p.track])
    owner = np.array([k for k, p in enumerate(points) for _ in p.track])
    return names, keypoints, owner, np.array([p.xyz for p in points])


def test_seeded_tracks_take_the_given_points_and_rows_and_the_first_given_point_wins_among_equals(tmp_path):
    reference = _street(tmp_path)
    reference.retriangulate()
    model = to_reconstruction(reference)
    names, keypoints, owner, xyz = _rows_of(model)
    moved = xyz + 1.0  # a second copy of every point, given after the first: ignored
    state = _street(tmp_path)
    seeded = state.seed_points(names + names, np.r_[keypoints, keypoints], np.r_[owner, owner + len(xyz)],
                               np.r_[xyz, moved])
    assert seeded == len(model.points3D)
    np.testing.assert_array_equal(state.track_valid, reference.track_valid)
    np.testing.assert_array_equal(state.obs_inlier, reference.obs_inlier & reference.track_valid[reference.obs_track])
    np.testing.assert_allclose(state.track_xyz[state.track_valid], reference.track_xyz[reference.track_valid])


def test_a_point_with_one_row_in_the_registered_images_seeds_nothing(tmp_path):
    reference = _street(tmp_path)
    reference.retriangulate()
    names, keypoints, owner, xyz = _rows_of(to_reconstruction(reference))
    rows = np.flatnonzero(owner == 0)[:2]  # two rows of the first point
    state = _street(tmp_path)
    assert state.seed_points([names[rows[0]]], keypoints[rows[:1]], np.array([0]), xyz) == 0
    state.registered[state.names.index(names[rows[1]])] = False  # the second row's image leaves
    assert state.seed_points([names[k] for k in rows], keypoints[rows], np.array([0, 0]), xyz) == 0
    state.registered[:] = True
    assert state.seed_points([names[k] for k in rows], keypoints[rows], np.array([0, 0]), xyz) == 1
    assert state.obs_inlier.sum() == 2


def test_a_track_takes_the_given_point_seen_by_the_most_rows(tmp_path):
    reference = _street(tmp_path)
    reference.retriangulate()
    names, keypoints, owner, xyz = _rows_of(to_reconstruction(reference))
    rows = np.flatnonzero(owner == np.argmax(np.bincount(owner)))  # the longest track
    assert len(rows) >= 3
    few, all_rows = rows[:2], rows  # point 0: two of its rows; point 1 (given later): all of them
    state = _street(tmp_path)
    given = np.r_[few, all_rows]
    seeded = state.seed_points([names[k] for k in given], keypoints[given], np.r_[[0] * len(few), [1] * len(all_rows)],
                               np.stack([xyz[owner[rows[0]]] + 1.0, xyz[owner[rows[0]]]]))
    assert seeded == 1
    assert state.obs_inlier.sum() == len(all_rows)
    np.testing.assert_allclose(state.track_xyz[state.track_valid][0], xyz[owner[rows[0]]])
