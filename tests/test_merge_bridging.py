"""Bridges between merge parts that share no aligned cluster pair (``sfm.merge.bridging``): two
local models of an orbit's halves, in frames a similarity apart and without a common image,
are joined from the rays between their photos and points, and merge into one model."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _helpers_recording import recording_texts
from scipy.spatial.transform import Rotation

from backend.sim3 import Sim3
from sfm.core.model import Image, Reconstruction
from sfm.evaluation.ground_truth import read_gt_table
from sfm.evaluation.metrics import evaluate
from sfm.io.colmap_model import read_model, write_model
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.state import MapperState
from sfm.merge import bridging
from sfm.merge.bridging import bridge_edges, bridge_weight, find_bridges
from sfm.merge.cluster_graph import LocalModel, plan_components
from sfm.merge.options import MergeOptions
from sfm.merge.refinement import left_out_by_component
from sfm.stages.merge import run_merge
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions
from sfm.viz.recorder import Recorder

# The second half's frame: x_first = SCALE * ROTATION @ x_second + SHIFT.
SCALE = 0.4
ROTATION = Rotation.from_rotvec([-0.7, 0.2, 1.3]).as_matrix()
SHIFT = np.array([3.0, 1.0, -2.0])


def _orbit(tmp_path):
    """A 16-image orbit: its payload, the true poses by name, and the state's image names."""
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    return payload, {n: (gt[n].rotation, gt[n].translation) for n in payload.names}


def _half(payload, poses: dict, names: list[str], moved: bool):
    """A local model of ``names`` at their poses (in the second half's frame when ``moved``),
    its points triangulated from them alone."""
    if moved:  # cam_from_second = cam_from_world . world_from_second
        poses = {n: (R @ ROTATION, (R @ SHIFT + t) / SCALE) for n, (R, t) in poses.items()}
    state = MapperState(payload, MapperOptions())
    state.set_poses({n: poses[n] for n in names})
    state.retriangulate()
    return to_reconstruction(state)


def test_two_halves_of_an_orbit_without_a_common_image_are_bridged(tmp_path):
    payload, poses = _orbit(tmp_path)
    names = sorted(poses)
    first, second = names[:9], names[9:]
    parts = []
    for half, moved in ((first, False), (second, True)):
        model = _half(payload, poses, half, moved)
        pose_of = {im.name: (im.cam_from_world_rotation, im.cam_from_world_translation) for im in model.images.values()}
        params = {c: cam.params for c, cam in model.cameras.items()}
        points = ([], np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))  # re-triangulated from the poses
        parts.append((pose_of, params, points))
    [bridge] = find_bridges(payload, MapperOptions(), parts)
    assert (bridge.into, bridge.moved, bridge.common_images) == (0, 1, 0)  # the larger part receives
    assert bridge.inliers >= MapperOptions().abs_pose_min_num_inliers
    sim = bridge.into_from_moved
    assert abs(sim.scale / SCALE - 1) < 0.01
    assert np.degrees(Rotation.from_matrix(sim.rotation @ ROTATION.T).magnitude()) < 0.3
    np.testing.assert_allclose(sim.translation, SHIFT, atol=0.02 * np.linalg.norm(SHIFT))
    # two models of an earlier run (graphsfm extend's other models) are not tried together
    assert find_bridges(payload, MapperOptions(), parts, finished=[True, True]) == []
    assert len(find_bridges(payload, MapperOptions(), parts, finished=[True, False])) == 1


def _part(payload, poses: dict, names: list[str], moved: bool):
    """``(poses, camera parameters, points)`` of a local model of ``names`` (``_half``), its
    points left to the re-triangulation from its poses."""
    model = _half(payload, poses, names, moved)
    pose_of = {im.name: (im.cam_from_world_rotation, im.cam_from_world_translation) for im in model.images.values()}
    no_points = ([], np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    return pose_of, {c: cam.params for c, cam in model.cameras.items()}, no_points


def test_a_part_that_joins_no_single_part_is_tried_again_against_their_union(tmp_path, monkeypatch):
    payload, poses = _orbit(tmp_path)
    names = sorted(poses)  # along the orbit
    # two arcs that meet where the orbit closes, and the short arc between their other ends
    arcs = [names[:7], names[9:], names[7:9]]
    parts = [_part(payload, poses, arc, moved) for arc, moved in zip(arcs, (False, True, False))]
    index = {n: i for i, n in enumerate(payload.names)}
    first_two = [index[n] for n in arcs[0] + arcs[1]]
    short = {index[n] for n in arcs[2]}
    [alone] = find_bridges(payload, MapperOptions(), [parts[0], parts[2]])  # the short arc and the first arc
    real = bridging.estimate_similarity

    def short_arc_only_to_both(state, finished, seed=0):
        """The short arc seeing too few points of either arc alone to join it."""
        if set(finished.images.tolist()) == short and not state.registered[first_two].all():
            return None, "too few rays"
        return real(state, finished, seed)

    monkeypatch.setattr(bridging, "estimate_similarity", short_arc_only_to_both)
    first, second = find_bridges(payload, MapperOptions(), parts)
    assert (first.into, first.moved) == (0, 1) and abs(first.into_from_moved.scale / SCALE - 1) < 0.01
    # the short arc joins the union in the first arc's frame, from the rays of both arcs' points
    assert (second.into, second.moved) == (0, 2)
    assert abs(second.into_from_moved.scale - 1) < 0.01
    assert np.degrees(Rotation.from_matrix(second.into_from_moved.rotation).magnitude()) < 0.3
    np.testing.assert_allclose(second.into_from_moved.translation, 0.0, atol=0.01)
    assert second.rays > alone.rays


def _model(label: str, num_images: int) -> LocalModel:
    recon = Reconstruction()
    for k in range(num_images):
        recon.images[k + 1] = Image(image_id=k + 1, name=f"{label}-{k}", camera_id=1)
    return LocalModel(label, recon)


def test_a_bridge_is_an_edge_between_the_parts_anchors_weighted_after_every_kept_edge():
    options = MergeOptions()
    sized = [_model(f"C{k}/0", 5 + k) for k in range(4)]
    edges = {(0, 1): {"msd": 0.01, "used": True}, (2, 3): {"msd": 0.02, "used": True}}
    plans = plan_components(sized, edges)
    assert len(plans) == 2
    into_from_moved = Sim3(2.0, Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix(), np.array([1.0, 2.0, 3.0]))
    into, moved = (0, 1) if plans[0].total_size >= plans[1].total_size else (1, 0)
    found = bridge_edges(plans, [bridging.Bridge(into, moved, into_from_moved, 40, 50, 0)], options.max_msd)
    [(u, v)] = found
    assert u < v and found[(u, v)]["used"] and found[(u, v)]["bridge"]
    # the edge's similarity maps u's frame into v's: from the moved part's anchor to the other's
    expected = into_from_moved if plans[moved].anchor == u else into_from_moved.inverse()
    np.testing.assert_allclose(found[(u, v)]["sim"].matrix(), expected.matrix(), atol=1e-12)
    assert found[(u, v)]["weight"] > options.max_msd >= max(e["msd"] for e in edges.values())
    assert bridge_weight(100, options.max_msd) < bridge_weight(40, options.max_msd)
    joined = plan_components(sized, {**edges, **found})
    assert len(joined) == 1 and sorted(joined[0].clusters) == [0, 1, 2, 3]


@pytest.mark.parametrize("bridge", [True, False])
def test_the_merge_joins_local_models_that_share_no_image(tmp_path, monkeypatch, bridge):
    payload, poses = _orbit(tmp_path)
    names = sorted(poses)
    for k, (half, moved) in enumerate(((names[:9], False), (names[9:], True))):
        folder = tmp_path / "clusters" / f"C{k}" / "0"
        folder.mkdir(parents=True)
        write_model(_half(payload, poses, half, moved), folder)
    if not bridge:
        monkeypatch.setattr(bridging, "estimate_similarity", lambda state, finished, seed=0: (None, "too few rays"))
    with Recorder(tmp_path / "recording.rrd", tmp_path) as recorder:
        result = run_merge(tmp_path, MapperOptions(), MergeOptions(), recorder)
    plan = json.loads((tmp_path / "merge.json").read_text())
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    if bridge:
        assert result.num_models == 1
        [edge] = plan["edges"]
        assert edge["bridge"] and edge["msd"] is None and edge["inliers"] >= 30 and plan["unjoined"] == []
        res = evaluate(read_model(tmp_path / "sparse" / "0"), gt)
        assert res.num_registered == 16 and res.auc[1.0] > 0.9
        texts = recording_texts(tmp_path / "recording.rrd")
        merge_tour = next(text for entity, text in texts.items() if entity.startswith("/tour/") and "## 5. Merge" in text)
        assert f"C0/0-C1/0 ({edge['inliers']} of {edge['rays']} rays)" in merge_tour
        assert f"(bridge: {edge['inliers']} of {edge['rays']} rays)" in merge_tour
    else:
        assert result.num_models == 2 and plan["edges"] == []
        [part] = plan["unjoined"]
        why = ("shares no registered image with any other local model; nor did the rays between its photos and the "
               "first part's points join it as one rigid body: too few rays")
        assert part["reason"] == why
        assert f"local models {part['models'][0]} join no other: {why}" in json.loads(
            (tmp_path / "report.json").read_text())["warnings"]


def test_the_images_no_local_model_holds_are_registered_in_the_merged_model(tmp_path):
    """A cluster whose local SfM made no model leaves its images to the merge: two overlapping
    local models hold 12 of the orbit's 16 images, and the merged model registers the other 4 by
    PnP against its points (``register_left_out``), close to the truth; the report lists none
    as unregistered."""
    payload, poses = _orbit(tmp_path)
    names = sorted(poses)
    for k, (part, moved) in enumerate(((names[:7], False), (names[5:12], True))):
        folder = tmp_path / "clusters" / f"C{k}" / "0"
        folder.mkdir(parents=True)
        write_model(_half(payload, poses, part, moved), folder)
    result = run_merge(tmp_path, MapperOptions(), MergeOptions(), Recorder(None, tmp_path))
    assert result.num_models == 1
    res = evaluate(read_model(tmp_path / "sparse" / "0"), read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt"))
    assert res.num_registered == 16 and res.auc[1.0] > 0.9, res
    assert json.loads((tmp_path / "report.json").read_text())["unregistered"] == []


def test_an_image_no_component_holds_goes_to_the_one_it_shares_most_matches_with():
    # images 0, 1 in component 0, 2, 3 in component 1; 4 to 7 in none
    component = np.array([0, 0, 1, 1, -1, -1, -1, -1])
    first, second = np.array([0, 2, 4, 3, 5, 6, 0]), np.array([4, 4, 1, 5, 7, 7, 2])
    inliers = np.array([40, 30, 500, 20, 9, 9, 50])
    # 4: 40 + 500 with the first, 30 with the second; 5: 20 with the second only; 6 and 7 see no registered image
    taken = left_out_by_component(component, first, second, inliers, 2)
    assert [t.tolist() for t in taken] == [[4], [5]]
    equal = left_out_by_component(component, np.array([4, 4]), np.array([0, 2]), np.array([25, 25]), 2)
    assert [t.tolist() for t in equal] == [[4], []]  # the first of equals
    assert [t.tolist() for t in left_out_by_component(component, np.zeros(0), np.zeros(0), np.zeros(0), 2)] == [[], []]
