"""Two-view tracks (COLMAP's ``tri_ignore_two_view_tracks``): a match no third image confirms
is triangulated only in the initial pair; a track the cluster's edge cuts to two rows, whose
keypoints match images outside the cluster, is confirmed and triangulated."""

from __future__ import annotations

import numpy as np

from backend.geometry import look_at
from sfm.io.database import Database
from sfm.mapper.options import MapperOptions
from sfm.mapper.payload import CameraPrior, MapperInput
from sfm.mapper.state import MapperState
from sfm.stages.payloads import ClusterPayloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions

FOCAL, WIDTH, HEIGHT = 800.0, 640, 480


def _three_views():
    """Three cameras 1 m apart looking at points ~5 m away, and three points seen as:
    point 0 by images 0 and 1 only (a two-view track), point 1 by all three, point 2 by images
    0 and 1 inside the cluster, its keypoint in image 1 matched outside the cluster as well."""
    centres = np.array([[-1.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0]])
    poses = [look_at(c, np.array([0.0, 0, 5]), np.array([0.0, -1, 0])) for c in centres]
    points = np.array([[-0.5, 0.2, 5.0], [0.3, -0.4, 5.5], [0.1, 0.5, 4.5]])
    keypoints = []
    for R, t in poses:
        cam = points @ R.T + t
        keypoints.append(FOCAL * cam[:, :2] / cam[:, 2:] + [(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    pairs = [(0, 1, np.array([[0, 0], [1, 1], [2, 2]]), 2), (1, 2, np.array([[1, 1]]), 2), (0, 2, np.array([[1, 1]]), 2)]
    camera = CameraPrior("PINHOLE", WIDTH, HEIGHT, np.array([FOCAL, FOCAL, (WIDTH - 1) / 2, (HEIGHT - 1) / 2]))
    names = ["a", "b", "c"]
    payload = MapperInput(image_ids=[1, 2, 3], names=names, camera_ids=[1, 1, 1], cameras={1: camera},
                          keypoints=keypoints, pairs=pairs,
                          match_counts=[np.array([1, 2, 1]), np.array([1, 2, 2]), np.array([0, 2, 0])])
    return payload, dict(zip(names, poses))


def test_only_a_track_no_third_image_confirms_is_two_view():
    payload, _ = _three_views()
    state = MapperState(payload, MapperOptions(min_num_matches=1))
    two_view = {tuple(state.obs_kp[state.starts[t]:state.starts[t + 1]]): bool(state.two_view_track[t])
                for t in range(state.num_tracks)}
    assert two_view == {(0, 0): True, (1, 1, 1): False, (2, 2): False}
    # without the database's counts, the cluster's own pairs decide: the cut track looks two-view
    alone = MapperState(MapperInput(**{**payload.__dict__, "match_counts": None}), MapperOptions(min_num_matches=1))
    assert alone.two_view_track.tolist() == [True, False, True]


def test_a_model_past_its_initial_pair_leaves_two_view_tracks_untriangulated():
    payload, poses = _three_views()
    for ignore, expected in ((True, [False, True, True]), (False, [True, True, True])):
        state = MapperState(payload, MapperOptions(min_num_matches=1, ignore_two_view_tracks=ignore))
        state.set_poses(poses)
        state.retriangulate()
        assert state.track_valid.tolist() == expected
    # the initial pair triangulates every match
    state = MapperState(payload, MapperOptions(min_num_matches=1))
    state.start_model(0, 1, *_relative(poses["a"], poses["b"]))
    assert state.track_valid.tolist() == [True, True, True]


def _relative(first, second):
    (R1, t1), (R2, t2) = first, second
    R = R2 @ R1.T
    return R, t2 - R @ t1


def test_a_clusters_payload_counts_each_keypoints_matches_over_the_whole_database(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=10, observations_per_image=300, seed=4))
    with Database(tmp_path / "database.db", readonly=True) as db:
        images = db.read_images()
        geoms = db.read_two_view_geometries(min_config=2, min_inliers=15)
        sizes = {i: len(k) for i, k in db.read_all_keypoints().items()}
    members = sorted(images)[:4]
    [payload] = ClusterPayloads(tmp_path / "database.db", [[images[i].name for i in members]],
                                fixed_intrinsics=False, min_inliers=15)
    expected = {i: np.zeros(sizes[i], np.int64) for i in members}
    for (a, b), g in geoms.items():
        for image, column in ((a, 0), (b, 1)):
            if image in expected:
                np.add.at(expected[image], g.inlier_matches[:, column], 1)
    outside = sum(1 for a, b in geoms if (a in expected) != (b in expected))
    assert outside > 0  # the cluster's images match images outside it
    for i, counts in zip(payload.image_ids, payload.match_counts):
        np.testing.assert_array_equal(counts, expected[i])
    assert all(a < len(members) and b < len(members) for a, b, _, _ in payload.pairs)
