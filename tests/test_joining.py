"""Joining a finished model to the model being grown as one rigid body (``sfm.mapper.joining``):
the similarity between two models that share no image, from the rays between them, and the
union it makes; what the acceptance terms refuse."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from _helpers_recording import recording_texts
from rerun.chunk import RrdReader
from scipy.spatial.transform import Rotation

from sfm.evaluation.ground_truth import read_gt_table
from sfm.evaluation.metrics import evaluate
from sfm.mapper import incremental
from sfm.mapper.growth import Growth
from sfm.mapper.joining import FinishedModel, estimate_similarity, join
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MapperState
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions
from sfm.viz.mapping import log_growth
from sfm.viz.recorder import Recorder
from sfm.viz.tour import map_text

# The finished model's frame: x_current = SCALE * ROTATION @ x_finished + SHIFT.
SCALE = 2.5
ROTATION = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
SHIFT = np.array([1.0, -2.0, 0.5])


def _orbit(tmp_path):
    """A 16-image orbit's state and its true ``cam_from_world`` poses (state order)."""
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    gt = read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt")
    R = np.stack([gt[n].rotation for n in state.names])
    t = np.stack([gt[n].translation for n in state.names])
    return state, R, t


def _register(state: MapperState, images, R, t) -> None:
    for i in images:
        state.register(i, R[i], t[i])
    state.retriangulate()


def _two_models(tmp_path, finished_images, current_images):
    """The state with ``finished_images`` closed as a model in the SCALE/ROTATION/SHIFT frame
    (their points triangulated from them alone), and ``current_images`` registered at their
    true poses as the current model; the true poses."""
    state, R, t = _orbit(tmp_path)
    R_fin = R @ ROTATION  # cam_from_finished = cam_from_world . world_from_finished
    t_fin = (np.einsum("nij,j->ni", R, SHIFT) + t) / SCALE
    _register(state, finished_images, R_fin, t_fin)
    finished = FinishedModel.of(state)
    state.close_model()
    state.used[:] = False
    _register(state, current_images, R, t)
    return state, finished, R, t


def _rotation_error_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(A @ B.T).magnitude()))


def test_the_similarity_between_two_arcs_of_an_orbit_is_found_and_joins_them(tmp_path):
    state, finished, R, t = _two_models(tmp_path, range(8), range(8, 16))
    assert not state.registered[:8].any() and state.registered[8:].all()
    sim, why = estimate_similarity(state, finished)
    assert sim is not None and why == ""
    assert sim.inliers >= state.opts.abs_pose_min_num_inliers
    assert abs(sim.scale / SCALE - 1) < 0.01
    assert _rotation_error_deg(sim.R, ROTATION) < 0.3  # one essential matrix's rotation; the BAs refine it
    np.testing.assert_allclose(sim.t, SHIFT, atol=0.02 * np.linalg.norm(SHIFT))

    state.used[:8] = True  # as the mapper leaves a closed model's images
    joined = join(state, finished, sim)  # equal sizes: the current model's frame stays
    np.testing.assert_array_equal(joined, np.arange(8))
    assert state.registered.all() and state.num_registered == 16
    assert not state.used.any()  # the current model's now: free again if a BA's filtering drops them
    for i in range(16):
        assert _rotation_error_deg(state.R[i], R[i]) < 0.3
    centres, true_centres = state.centers(np.arange(16)), -np.einsum("nji,nj->ni", R, t)
    spread = np.linalg.norm(true_centres - true_centres.mean(axis=0), axis=1).mean()
    assert np.abs(centres - true_centres).max() < 0.01 * spread


def test_a_larger_finished_model_keeps_its_frame_and_points(tmp_path):
    state, finished, R, _ = _two_models(tmp_path, range(11), range(11, 16))
    sim, _ = estimate_similarity(state, finished)
    assert sim is not None
    join(state, finished, sim)
    assert state.registered.all()
    # the finished model's images keep their poses exactly, the others come into its frame
    np.testing.assert_array_equal(state.R[:11], finished.R[:11])
    R_fin = R @ ROTATION
    for i in range(11, 16):
        assert _rotation_error_deg(state.R[i], R_fin[i]) < 0.3
    np.testing.assert_array_equal(state.track_xyz[finished.tracks], finished.xyz)


def _cross_pairs(state: MapperState, finished: FinishedModel) -> list[tuple[int, int]]:
    inside = set(finished.images.tolist())
    return [k for k in state.pair_matches if (k[0] in inside) != (k[1] in inside)]


@pytest.mark.parametrize("what", ["no cross pair", "small cross pairs", "no relative pose", "too few rays",
                                  "rays of one image", "rays off"])
def test_no_similarity_says_which_step_fell_short(tmp_path, what):
    """Without a pair across the two models whose essential matrix gives the rotation, nothing,
    and the reason names the step: no pair across, pairs across all below PnP's inlier count,
    no essential matrix from them; rays between the models fewer than PnP's inlier count;
    every ray in one image (a current model of one image that sees the finished model's points:
    that image's pose in the other frame is fixed but not the scale); rays that no similarity
    fits (the finished model's points moved)."""
    current = [8] if what == "rays of one image" else range(8, 16)
    state, finished, _, _ = _two_models(tmp_path, range(8), current)
    opts = state.opts
    cross = _cross_pairs(state, finished)
    assert len(cross) >= 2
    if what == "no cross pair":
        for k in cross:
            del state.pair_matches[k]
    elif what == "small cross pairs":
        for k, keep in zip(cross, range(len(cross))):
            m, geometry = state.pair_matches[k]
            state.pair_matches[k] = (m[:opts.abs_pose_min_num_inliers - 1 - keep % 3], geometry)
    elif what == "no relative pose":
        rng = np.random.default_rng(0)
        for k in cross:  # each keypoint matched to a random one: no essential matrix fits them
            m, geometry = state.pair_matches[k]
            state.pair_matches[k] = (np.column_stack([m[:, 0], rng.permutation(m[:, 1])]), geometry)
    elif what == "too few rays":
        state.registered[9:] = False  # a current model of one image (8) that sees too few of them ...
        state.track_valid[:] = False
        seen = np.flatnonzero(np.isin(state.obs_track, finished.tracks) & (state.obs_image == 8))
        keep = np.isin(finished.tracks, state.obs_track[seen[:opts.abs_pose_min_num_inliers - 5]])
        finished.tracks, finished.xyz = finished.tracks[keep], finished.xyz[keep]
    elif what == "rays of one image":
        assert not state.track_valid.any()
        assert np.isin(state.obs_track[state.obs_image == 8], finished.tracks).sum() >= opts.abs_pose_min_num_inliers
    else:  # the finished model's points and camera positions scattered: its rays fit nothing
        rng = np.random.default_rng(1)
        finished.xyz = finished.xyz + rng.normal(0.0, np.ptp(finished.xyz, axis=0), finished.xyz.shape)
        finished.t = finished.t + rng.normal(0.0, np.ptp(finished.t, axis=0), finished.t.shape)
    sim, why = estimate_similarity(state, finished)
    assert sim is None
    expected = {
        "no cross pair": "no image pair across them has 30+ verified matches",
        "small cross pairs": "no image pair across them has 30+ verified matches (the most: 29)",
        "no relative pose": "no pair across them gives a relative pose with 30+ inliers (5 tried)",
        "too few rays": "their images see 25 of each other's points, fewer than the 30 a registration needs",
    }
    if what in expected:
        assert why == expected[what]
    elif what == "rays of one image":
        rays = int(np.isin(state.obs_track[state.obs_image == 8], finished.tracks).sum())
        assert why == (f"the {rays} rays between them are all in one image, which they place in the other frame "
                       "without the scale between the frames")
    else:
        assert why.startswith("at most ") and why.endswith("; joining needs 30, 25% of the rays, in two images or more")
        fitted, rays = (int(x) for x in why.removeprefix("at most ").split(" rays")[0].split(" of the "))
        assert rays > 10 * opts.abs_pose_min_num_inliers  # plenty of rays, ...
        assert fitted < max(opts.abs_pose_min_num_inliers, opts.abs_pose_min_inlier_ratio * rays)  # ... too few fit


def test_the_mapper_joins_a_model_to_the_one_it_could_not_grow_into(tmp_path, monkeypatch, caplog):
    """The orbit's first model is kept from the second half of the images (as if none of them
    saw enough of its points), so the mapper makes a second model of them: it joins the first
    as a whole, one model of 16 images, close to the truth.  Without the join: two models."""
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    second_half = np.arange(8, 16)

    def hiding_the_second_half(step):
        def wrapped(state, *args):
            if state.used[:8].any():  # the first model closed: nothing hidden
                return step(state, *args)
            saved = state.used[second_half].copy()
            state.used[second_half] = True
            try:
                return step(state, *args)
            finally:
                state.used[second_half] = saved
        return wrapped

    for name in ("try_initial_pair", "register_next", "register_structureless"):
        monkeypatch.setattr(incremental, name, hiding_the_second_half(getattr(incremental, name)))
    growth = Growth(payload.label, list(payload.names), max_points=100)
    with caplog.at_level(logging.INFO, logger="sfm.mapper.incremental"):
        models = incremental.reconstruct_incremental(payload, MapperOptions(), growth)
    assert [len(m.images) for m in models] == [16]
    assert "joined it as a whole" in caplog.text
    # the recording: the first model joined the second, which is the cluster's model 0 and says so
    first, second = growth.models
    assert first.absorbed and first.rank == -1 and not second.absorbed and second.rank == 0
    assert len(second.joins) == 1 and "the finished model of 8 images joined it as a whole" in second.joins[0]
    assert growth.left_out() == {}
    # ... and the recording shows it: the joined attempt under its own name, the join in words
    with Recorder(tmp_path / "recording.rrd", tmp_path) as recorder:
        log_growth(recorder, growth)
    texts, entities = {}, set()
    for chunk in RrdReader(str(tmp_path / "recording.rrd")).stream():
        entities.add(str(chunk.entity_path))
        batch = chunk.to_record_batch()
        if "TextDocument:text" in batch.schema.names:
            texts[str(chunk.entity_path)] = batch.column("TextDocument:text").to_pylist()[-1][0]
    label = payload.label
    assert f"/clusters/{label}/joined0/points" in entities and f"/clusters/{label}/model0/points" in entities
    assert not any("dropped" in e for e in entities)
    assert "joined it as a whole" in texts[f"/clusters/{label}/model0/joins"]
    result = evaluate(models[0], read_gt_table(tmp_path / "gt" / "cameras_gt_opencv.txt"))
    assert result.auc[1.0] > 0.9, result.auc

    monkeypatch.setattr(incremental, "estimate_similarity", lambda state, finished, seed=0: (None, "a reason"))
    growth = Growth(payload.label, list(payload.names), max_points=100)
    models = incremental.reconstruct_incremental(payload, MapperOptions(), growth)
    assert sorted(len(m.images) for m in models) == [8, 8]
    # the report and the recording say why the two models stayed apart
    assert growth.unjoined() == ["model 1 (8 images) did not join model 0 as a whole: a reason"]
    with Recorder(tmp_path / "apart.rrd", tmp_path) as recorder:
        log_growth(recorder, growth)
    [unjoined] = [text for entity, text in recording_texts(tmp_path / "apart.rrd").items()
                  if entity.endswith("/unjoined")]
    assert "- the finished model of 8 images: a reason" in unjoined
    row = {"cluster": payload.label, "images": 16, "models": [{"registered": 8, "points": 1}] * 2,
           "unregistered": 0, "unjoined": growth.unjoined()}
    assert (f"- {payload.label}: model 1 (8 images) did not join model 0 as a whole: a reason"
            in map_text([row], 16, True, MapperOptions()))  # the map stage's page of the tour
