"""Steps of the incremental mapper: the initial-pair search's early stop and the rule for a
second final BA."""

from __future__ import annotations

import types

import numpy as np

import sfm.mapper.incremental as incremental
import sfm.mapper.initialization as initialization
from sfm.mapper.bundle_adjuster import FINAL_TOLERANCE, GROWING_TOLERANCE
from sfm.mapper.incremental import MAX_REFINEMENT_CHANGE, final_refinement
from sfm.mapper.initialization import try_initial_pair, two_view_score
from sfm.merge.refinement import refine_with_poses
from sfm.mapper.options import MapperOptions
from sfm.mapper.state import MapperState
from sfm.stages.payloads import load_payloads
from sfm.stages.synth import run_synth
from sfm.synthetic.options import SynthOptions


def _full_search_winner(state: MapperState) -> tuple[int, int, int, list]:
    """The initial pair the documented rule picks when every candidate is reconstructed, its
    score, and the candidates (inliers, i, j) in search order."""
    opts = state.opts
    cands = sorted(((len(m), i, j, m) for (i, j), (m, config) in state.pair_matches.items()
                    if config not in initialization.PLANAR_CONFIGS
                    and len(m) >= max(opts.abs_pose_min_num_inliers, opts.min_num_matches)),
                   key=lambda c: (-c[0], c[1], c[2]))  # fmt: skip
    if any(c[0] >= opts.init_min_num_inliers for c in cands):
        cands = [c for c in cands if c[0] >= opts.init_min_num_inliers]
    scored = []
    for _, i, j, m in cands[: opts.init_max_pairs]:
        rel = initialization.relative_pose(state, i, j, m, opts.seed)
        if rel is not None:
            score, angle = two_view_score(state, i, j, rel[0], rel[1], m[rel[2]])
            if score >= opts.abs_pose_min_num_inliers and angle >= opts.init_min_tri_angle:
                scored.append((score, -i, -j))
    assert scored, "the scene must have a pair passing the first angle threshold"
    score, i, j = max(scored)
    return -i, -j, score, [c[:3] for c in cands[: opts.init_max_pairs]]


def test_initial_pair_search_stops_early_with_the_full_search_winner(tmp_path, monkeypatch):
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    opts = MapperOptions()
    *expected, score, cands = _full_search_winner(MapperState(payload, opts))

    calls = []
    original = initialization.relative_pose

    def counting(state, i, j, matches, seed):
        calls.append((i, j))
        return original(state, i, j, matches, seed)

    monkeypatch.setattr(initialization, "relative_pose", counting)
    state = MapperState(payload, opts)
    assert try_initial_pair(state, set())
    assert tuple(np.flatnonzero(state.registered)) == tuple(sorted(expected))
    # every pair that could still have beaten the winner was tried, and no other
    assert calls == [(i, j) for n, i, j in cands if n >= score]
    assert len(calls) < len(cands)


class _FakeState:
    """What ``final_refinement`` touches of the state: re-triangulation re-admits ``gain``
    observations."""

    def __init__(self, num_observations: int, gain: int) -> None:
        self.obs_inlier = np.zeros(num_observations + gain + 10, bool)
        self.obs_inlier[:num_observations] = True
        self.gain = gain
        self.payload = types.SimpleNamespace(label="C0")

    def retriangulate(self) -> int:
        start = int(self.obs_inlier.sum())
        self.obs_inlier[start : start + self.gain] = True
        return self.gain


class _FakeAdjuster:
    """Records the final BAs' tolerances; each BA's last LM iteration lowered the cost by
    ``decrease``."""

    def __init__(self, decrease: float) -> None:
        self.decrease, self.tolerances, self.last_decrease = decrease, [], 0.0
        # a new model: nothing recorded for the calibration to forget here
        self.calibration = types.SimpleNamespace(forget=lambda: None)

    def global_(self, final: bool = False, tolerance: float = FINAL_TOLERANCE) -> None:
        assert final
        self.tolerances.append(tolerance)
        self.last_decrease = self.decrease


def test_second_final_ba_when_retriangulation_changed_enough_or_the_first_stopped_early():
    n = 100_000
    limit = int(MAX_REFINEMENT_CHANGE * n)  # 50 observations
    converged, early = 0.5 * FINAL_TOLERANCE, 0.5 * (FINAL_TOLERANCE + GROWING_TOLERANCE)
    for gain, decrease, expected in ((0, converged, 1), (3, converged, 1), (limit, converged, 1),
                                     (limit + 1, converged, 2), (n // 100, converged, 2),
                                     (0, early, 2), (limit, early, 2)):
        adjuster = _FakeAdjuster(decrease)
        final_refinement(_FakeState(n, gain), adjuster)
        assert len(adjuster.tolerances) == expected, (gain, decrease, adjuster.tolerances)
        # the first stops at the growing model's tolerance; a second one at the final one
        assert adjuster.tolerances == [GROWING_TOLERANCE, FINAL_TOLERANCE][:expected]


def test_initial_pair_search_rule_on_a_table_of_scores(monkeypatch):
    """The search reconstructs candidates in order of inliers until the best score at the
    first angle threshold exceeds the next candidate's inliers; the best such pair wins."""
    table = {  # (i, j): (inliers, score, median angle in degrees)
        (0, 1): (500, 480, 5.0),  # most inliers, too narrow
        (0, 2): (400, 300, 20.0),
        (1, 2): (350, 340, 20.0),  # the winner: must be tried although (0, 2) passed already
        (1, 3): (250, 250, 30.0),  # cannot beat 340: never reconstructed
    }
    opts = MapperOptions()
    eye, t = np.eye(3), np.array([1.0, 0.0, 0.0])
    state = types.SimpleNamespace(
        opts=opts, registered=np.zeros(4, bool), used=np.zeros(4, bool), names=["a", "b", "c", "d"],
        pair_matches={p: (np.zeros((n, 2), np.int64), 2) for p, (n, _, _) in table.items()},
        start_model=lambda i, j, R, t: started.append((i, j)),
    )  # fmt: skip
    calls, started = [], []
    monkeypatch.setattr(initialization, "relative_pose",
                        lambda st, i, j, m, seed: calls.append((i, j)) or (eye, t, np.ones(len(m), bool)))
    monkeypatch.setattr(initialization, "two_view_score", lambda st, i, j, R, tt, m: table[(i, j)][1:])
    monkeypatch.setattr(initialization, "ray_angles", lambda st, i, j, R, m: np.full(len(m), table[(i, j)][2]))
    assert try_initial_pair(state, set())
    assert started == [(1, 2)]
    assert calls == [(0, 1), (0, 2), (1, 2)]


def test_narrow_candidates_are_scored_only_when_the_angle_is_relaxed(monkeypatch):
    """Pairs whose rays are clearly too parallel for the first threshold are triangulated only
    once no pair passes it; then the best of all wins at the relaxed threshold."""
    table = {(0, 1): (500, 480, 10.0), (0, 2): (400, 300, 9.0), (1, 2): (350, 340, 14.0)}
    opts = MapperOptions()  # first threshold 16 deg, deferred below 12.8 deg; then 8 deg
    eye, t = np.eye(3), np.array([1.0, 0.0, 0.0])
    started, scored = [], []
    state = types.SimpleNamespace(
        opts=opts, registered=np.zeros(3, bool), used=np.zeros(3, bool), names=["a", "b", "c"],
        pair_matches={p: (np.zeros((n, 2), np.int64), 2) for p, (n, _, _) in table.items()},
        start_model=lambda i, j, R, t: started.append((i, j)),
    )  # fmt: skip
    monkeypatch.setattr(initialization, "relative_pose", lambda st, i, j, m, seed: (eye, t, np.ones(len(m), bool)))
    monkeypatch.setattr(initialization, "two_view_score",
                        lambda st, i, j, R, tt, m: scored.append((i, j)) or table[(i, j)][1:])
    monkeypatch.setattr(initialization, "ray_angles", lambda st, i, j, R, m: np.full(len(m), table[(i, j)][2]))
    assert try_initial_pair(state, set())
    assert scored == [(1, 2), (0, 1), (0, 2)]  # (1, 2) at once (14 >= 12.8), the others deferred
    assert started == [(0, 1)]  # none reaches 16 deg; at 8 deg the highest score wins


def test_ray_angles_are_the_triangulation_angles(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    (i, j), (m, _) = max(state.pair_matches.items(), key=lambda kv: len(kv[1][0]))
    R, t, inl = initialization.relative_pose(state, i, j, m, 0)
    rays = initialization.ray_angles(state, i, j, R, m[inl])
    _, median = two_view_score(state, i, j, R, t, m[inl])
    assert rays.min() >= 0 and np.median(rays) > 1.0
    assert abs(np.median(rays) - median) < 0.02 * median



def test_a_stalled_model_retries_failed_images_that_see_any_more_points(tmp_path):
    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=16, observations_per_image=600, seed=4))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    state = MapperState(payload, MapperOptions())
    assert try_initial_pair(state, set())
    k = state.next_image_candidates()[0]
    seen = len(state.visible_points(k)[0])
    state.note_failure(k, seen - 1)  # failed when it saw one point fewer
    assert k not in state.next_image_candidates()  # 20% more needed
    assert k in state.next_image_candidates(stalled=True)  # any growth, once stalled
    state.note_failure(k, seen)
    assert k not in state.next_image_candidates(stalled=True)


def test_every_bundle_adjustment_weighs_by_keypoint_scale(tmp_path, monkeypatch):
    """Local, growing global and final BAs all get each observation's sigma from its keypoint
    scale (rows aligned with the observations they weigh); with scale weights off, none."""
    import sfm.mapper.bundle_adjuster as mapper_ba
    from sfm.mapper.payload import MapperInput
    from sfm.features.sift import localization_sigma

    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=12, observations_per_image=500, seed=6))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    rng = np.random.default_rng(0)
    scaled = [np.column_stack([kp, rng.uniform(0.5, 4.0, len(kp))]) for kp in payload.keypoints]
    payload = MapperInput(**{**payload.__dict__, "keypoints": scaled})
    seen = []
    original = mapper_ba.bundle_adjust_partitioned

    def spy(problem, *args, **kwargs):
        seen.append((np.asarray(problem.obs_xy).copy(), problem.obs_sigma))
        return original(problem, *args, **kwargs)

    monkeypatch.setattr(mapper_ba, "bundle_adjust_partitioned", spy)
    [model] = incremental.reconstruct_incremental(payload, MapperOptions())
    assert len(model.images) == 12 and len(seen) > 5
    scale_of = {tuple(r[:2]): r[2] for kp in scaled for r in kp}  # synthetic xy are distinct
    for xy, sigma in seen:
        assert sigma is not None and len(sigma) == len(xy)
        expected = localization_sigma(np.array([scale_of[tuple(p)] for p in xy]))
        np.testing.assert_allclose(sigma, expected)
    seen.clear()
    incremental.reconstruct_incremental(payload, MapperOptions(scale_weights=False))
    assert seen and all(np.all(sigma == 1.0) for _, sigma in seen)


def test_global_bundle_adjustments_take_the_inlier_threshold_as_loss_scale(tmp_path, monkeypatch):
    """The local BAs (Gauss-Newton first) use ``loss_scale``, the global BAs (growing and
    final, Levenberg-Marquardt) ``global_loss_scale``, by default ``max_reproj_error``: least
    squares on every observation the model keeps, as COLMAP's global BA."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=14, observations_per_image=500, seed=3))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=False, min_inliers=15)
    seen = []
    original = mapper_ba.bundle_adjust_partitioned

    def spy(problem, num_parts, options, **kwargs):
        seen.append((options.optimizer, options.loss, options.loss_scale, options.refine_intrinsics))
        return original(problem, num_parts, options, **kwargs)

    monkeypatch.setattr(mapper_ba, "bundle_adjust_partitioned", spy)
    for opts, local, glob in ((MapperOptions(), 1.0, 4.0),
                              (MapperOptions(max_reproj_error=3.0), 1.0, 3.0),
                              (MapperOptions(loss="cauchy", loss_scale=0.5, global_loss_scale=2.0), 0.5, 2.0)):
        seen.clear()
        [model] = incremental.reconstruct_incremental(payload, opts)
        assert len(model.images) == 14
        assert {optimizer for optimizer, *_ in seen} == {"lm", "gauss_newton_or_lm"}  # both kinds ran
        for optimizer, loss, scale, refine in seen:
            assert loss == opts.loss
            if optimizer == "gauss_newton_or_lm":  # a local BA: poses and points only
                levels = {refine} if isinstance(refine, str) else set(refine)  # one level, or one per camera
                assert (scale, levels) == (local, {"none"})
            else:
                assert scale == glob
        assert seen[-1][0] == "lm" and seen[-1][2] == glob  # the final BA
        seen.clear()  # the refinement of merged poses keeps the local scale
        poses = {im.name: (im.cam_from_world_rotation, im.cam_from_world_translation)
                 for im in model.images.values()}
        refined = refine_with_poses(payload, opts, poses, {})
        assert len(refined.images) == 14 and seen
        assert all(optimizer == "lm" and scale == local for optimizer, _, scale, _ in seen), seen


def test_global_loss_scale_is_the_inlier_threshold_for_final_models_and_1px_for_merged_ones():
    opts = MapperOptions(max_reproj_error=3.0, loss_scale=0.7)
    assert opts.global_loss_scale is None
    assert opts.for_model(final=True).global_loss_scale == 3.0
    assert opts.for_model(final=False).global_loss_scale == 0.7
    given = MapperOptions(global_loss_scale=2.0)
    assert given.for_model(final=True) is given and given.for_model(final=False) is given


class _Views:
    """The part of a MapperState that BundleAdjuster.posing_tracks reads: which registered
    image holds each inlier row of each track."""

    def __init__(self, num_images: int, track_images: list[list[int]]) -> None:
        self.names = [f"im{k}" for k in range(num_images)]
        self.track_images = track_images
        self.obs_image = np.array([i for images in track_images for i in images], dtype=np.int64)
        self.starts = np.cumsum([0] + [len(images) for images in track_images])

    def inlier_rows(self, tracks):
        rows = [np.arange(self.starts[t], self.starts[t + 1]) for t in tracks]
        owner = [np.full(len(r), k) for k, r in enumerate(rows)]
        return np.concatenate(rows), np.concatenate(owner)


def _posing(views: _Views) -> list[int]:
    from sfm.mapper.bundle_adjuster import BundleAdjuster

    adjuster = BundleAdjuster.__new__(BundleAdjuster)  # only the state's views are read
    adjuster.state, adjuster.opts = views, MapperOptions()
    return adjuster.posing_tracks(np.arange(len(views.track_images))).tolist()


def test_final_ba_poses_the_cameras_with_points_three_images_see_and_two_view_points_only_where_needed():
    confirmed = [[0, 1, 2]] * 40  # tracks 0-39
    views = _Views(4, confirmed + [[0, 1], [2, 3], [0, 1, 2, 3]])
    # track 40: images 0 and 1 see 40+ points of three views: left out; track 41: image 3
    # sees one such point (track 42), fewer than PnP's 30: kept
    assert _posing(views) == list(range(40)) + [41, 42]
    seen_by_30 = _Views(4, confirmed + [[1, 2, 3]] * 30 + [[0, 1], [2, 3]])  # image 3: 30 such points
    assert _posing(seen_by_30) == list(range(70))
    two_images = _Views(2, [[0, 1]] * 50)  # a two-view model keeps every point
    assert _posing(two_images) == list(range(50))


def test_the_final_ba_adjusts_poses_with_three_view_points_and_re_estimates_the_others(tmp_path, monkeypatch):
    """On a 12-image orbit, the final BA's problem holds only points seen by three images or
    more (every image sees more than 30 of them); the model keeps its two-view points,
    re-estimated with the cameras held, so they reproject as well as the others."""
    import sfm.mapper.bundle_adjuster as mapper_ba

    run_synth(tmp_path, SynthOptions(scene="orbit", num_images=12, observations_per_image=500, seed=6))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    final_problems = []
    original = mapper_ba.bundle_adjust_partitioned

    def spy(problem, num_parts, options, **kwargs):
        if options.on_iteration is not None:  # a final BA
            final_problems.append(np.bincount(np.asarray(problem.obs_point)))
        return original(problem, num_parts, options, **kwargs)

    monkeypatch.setattr(mapper_ba, "bundle_adjust_partitioned", spy)
    [model] = incremental.reconstruct_incremental(payload, MapperOptions())
    assert len(model.images) == 12 and final_problems
    assert all(views.min() >= 3 for views in final_problems)
    pids, errors = model.reprojection_errors()
    two_view = np.array([len(model.points3D[p].track) == 2 for p in pids])
    assert two_view.sum() > 100  # the orbit's short tracks stay in the model
    assert np.median(errors[two_view]) < 1.5 * np.median(errors[~two_view])


def _narrow_ring_with_a_short_guess(tmp_path, shortened_by: float):
    """A ring of 12 narrow views (focal length twice the image width, 400 points per view) whose
    database gives a focal length ``shortened_by`` times too short and not from EXIF (a guess):
    the ground truth and the payload."""
    import sqlite3

    from sfm.evaluation.ground_truth import gt_from_reconstruction
    from sfm.synthetic.matching import simulate_matching, write_database
    from sfm.synthetic.scenes import gt_reconstruction, make_scene

    opts = SynthOptions(scene="orbit", num_images=12, observations_per_image=400, pixel_noise=1.0,
                        focal=2 * 1280.0, seed=0)
    scene = make_scene(opts)
    write_database(scene, simulate_matching(scene, opts), tmp_path / "database.db", camera_model="SIMPLE_RADIAL")
    with sqlite3.connect(tmp_path / "database.db") as con:
        camera_id, blob = con.execute("SELECT camera_id, params FROM cameras").fetchone()
        params = np.frombuffer(blob, dtype=np.float64).copy()
        params[0] /= shortened_by
        con.execute("UPDATE cameras SET params = ?, prior_focal_length = 0 WHERE camera_id = ?",
                    (params.tobytes(), camera_id))
    [payload] = load_payloads(tmp_path / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    return gt_from_reconstruction(gt_reconstruction(scene)), payload


def test_a_model_whose_guessed_focal_length_moved_far_is_grown_again_from_it(tmp_path, caplog):
    """The ring's focal length guessed 4 times too short: grown at it, the model stops at 4 of
    its 12 views (poses a few degrees off) while its final BA finds a focal length 3.5 times the
    start; grown again from that value it holds all 12 views with the true focal length."""
    import logging

    from sfm.evaluation.metrics import evaluate

    gt, payload = _narrow_ring_with_a_short_guess(tmp_path, 4.0)
    with caplog.at_level(logging.INFO, logger="sfm.mapper.incremental"):
        models = incremental.reconstruct_incremental(payload, MapperOptions().for_model(True))
    assert any("refined a guessed focal length 640 -> " in r.getMessage() and "grown again" in r.getMessage()
               for r in caplog.records)
    assert len(models[0].registered_image_ids) == 12
    [camera] = models[0].cameras.values()
    assert abs(camera.params[0] / 2560.0 - 1) < 0.01
    assert evaluate(models[0], gt).auc[1.0] > 0.7


def test_only_a_guessed_focal_length_of_a_camera_with_three_images_that_moved_past_the_ratio_counts(tmp_path):
    """``MapperState.guessed_focal_moves``: the current focal length against the one the model
    started from (the prior, or the value of a restart), beyond the ratio either way; not for a
    focal length from EXIF, nor for a camera of fewer than three registered images."""
    _, payload = _narrow_ring_with_a_short_guess(tmp_path, 4.0)
    state = MapperState(payload, MapperOptions())
    assert state.start_focal(0) == 640.0
    state.registered[:3] = True
    for focal, moved in ((2000.0, True), (1500.0, False), (640.0 / 3.1, True), (640.0 * 3.0, False)):
        state.set_focal(0, focal)
        assert state.guessed_focal_moves(3.0) == ({0: focal} if moved else {}), focal
    state.set_focal(0, 2000.0)
    state.registered[2] = False
    assert state.guessed_focal_moves(3.0) == {}  # two images: a camera per image searches its own
    state.registered[2] = True
    state.restart_model({0: 2000.0})
    assert state.start_focal(0) == 2000.0 and state.camera_focal(0) == 2000.0 and not state.registered.any()
    state.registered[:3] = True
    assert state.guessed_focal_moves(3.0) == {}
    state.close_model()
    # the guess the restart rejected stays rejected: the next model starts from the restart's value
    assert state.start_focal(0) == 2000.0 and state.camera_focal(0) == 2000.0
    from dataclasses import replace

    exif = MapperState(replace(payload, cameras={k: replace(c, prior_focal_length=True)
                                                 for k, c in payload.cameras.items()}), MapperOptions())
    exif.registered[:3] = True
    exif.set_focal(0, 2000.0)
    assert exif.guessed_focal_moves(3.0) == {}


def test_a_restart_frees_the_finished_models_grown_at_the_focal_length_it_rejects(tmp_path):
    """``free_models_grown_far_from``: a finished model grown from a focal length more than
    ``FOCAL_RESTART_RATIO`` from the restart's value is taken apart (its images free again, its
    kept model and its recording no longer a model); one grown nearer to it stays."""
    from sfm.mapper.growth import Growth
    from sfm.mapper.joining import FinishedModel

    _, payload = _narrow_ring_with_a_short_guess(tmp_path, 4.0)
    state = MapperState(payload, MapperOptions())
    growth = Growth("C0", state.names, 50)
    finished, models = [], []
    for images, start in ((range(4), None), (range(4, 8), 1000.0)):
        if start is not None:
            state.restart_model({0: start})
        state.registered[list(images)] = True
        state.num_registered = len(images)
        growth.record(state, float("nan"), list(images))
        growth.close(state)
        kept = object()  # stands for the model's Reconstruction
        models.append(kept)
        finished.append(FinishedModel.of(state, kept, len(growth.models) - 1))
        state.close_model()
    assert [m.start_focals for m in finished] == [{0: 640.0}, {0: 1000.0}]
    assert state.used[:8].all()

    # 2000 px is 3.1 times 640 (beyond the ratio 3) and 2 times 1000 (within it)
    freed = incremental.free_models_grown_far_from(state, {0: 2000.0}, finished, models, growth)
    assert freed == 4
    assert [m.start_focals for m in finished] == [{0: 1000.0}] and models == [finished[0].kept]
    assert not state.used[:4].any() and state.used[4:8].all()
    assert "640 px against 2000" in growth.models[0].taken_apart and not growth.models[1].taken_apart
    growth.finish(3)
    assert [m.rank for m in growth.models] == [-1, 0]
    left_out = growth.left_out()
    assert all(left_out[state.names[i]] != "registered only in a model of 4 images, fewer than the 3 a kept model needs"
               for i in range(4))
    assert incremental.free_models_grown_far_from(state, {0: 1200.0}, finished, models, growth) == 0
    # the recording shows the model taken apart under its own name, and why
    from _helpers_recording import recording_texts

    from sfm.viz.mapping import log_growth
    from sfm.viz.recorder import Recorder

    with Recorder(tmp_path / "recording.rrd", tmp_path) as recorder:
        log_growth(recorder, growth)
    texts = recording_texts(tmp_path / "recording.rrd")
    assert "640 px against 2000" in texts["/clusters/C0/taken_apart0/taken_apart"]
    assert not any(path.startswith("/clusters/C0/model1") for path in texts)


def test_a_guessed_focal_length_is_rejected_far_off_or_nearer_with_a_camera_beyond_any_lens(tmp_path):
    """``rejected_focal_lengths``: beyond ``FOCAL_RESTART_RATIO`` for the distance alone; beyond
    the focal search's resolution only while the camera is beyond any lens (a principal point
    outside the image, or a distortion estimate the test held as no lens's); nearer, never."""
    from sfm.mapper.bundle_adjuster import BundleAdjuster
    from sfm.mapper.distortion import check_distortion
    from sfm.mapper.registration import FOCAL_SEARCH_STEP

    _, payload = _narrow_ring_with_a_short_guess(tmp_path, 4.0)
    state = MapperState(payload, MapperOptions())
    adjuster = BundleAdjuster(state)
    state.registered[:3] = True
    prior = state.priors[0]
    assert abs(FOCAL_SEARCH_STEP - 100 ** (1 / 29)) < 1e-12  # 30 candidates over 0.1-10 x the longer side

    def rejected(focal, cy=None):
        state.set_focal(0, focal)
        if cy is not None:
            state.set_camera_params({state.cam_keys[0]: np.r_[state.params[0][:2], cy, state.params[0][3:]]})
        return incremental.rejected_focal_lengths(state, adjuster)

    assert rejected(640.0 * 3.1) == ({0: 640.0 * 3.1}, "")  # far enough on its own
    assert rejected(640.0 * 1.6, cy=prior.params[2]) == ({}, "")  # a lens: the principal point in the image
    moved, why = rejected(640.0 * 1.6, cy=prior.height + 20.0)  # below the image
    assert moved == {0: 640.0 * 1.6} and "beyond any lens" in why
    assert rejected(640.0 * 1.1, cy=prior.height + 20.0) == ({}, "")  # within the search's resolution
    rejected(640.0 * 1.6, cy=prior.params[2])
    nominal = np.r_[1000.0, 1000.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert check_distortion("SIMPLE_RADIAL", nominal, np.r_[nominal[:5], -1.3, 0, 0, 0], None).beyond_lens
    assert not check_distortion("SIMPLE_RADIAL", nominal, np.r_[nominal[:5], -0.9, 0, 0, 0], None).beyond_lens
    adjuster.calibration.beyond_lens.add(0)  # as a final BA of the model whose distortion test held -1.3
    assert rejected(640.0 * 1.6)[0] == {0: 640.0 * 1.6}
    adjuster.calibration.forget()  # the next model's final BAs start without that evidence
    assert rejected(640.0 * 1.6) == ({}, "")
