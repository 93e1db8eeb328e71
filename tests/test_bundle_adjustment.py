"""Bundle adjustment (backend/bundle_adjustment.py): projection, gauge, noise, robust losses,
fixed parameters, intrinsics refinement and option checks.

Synthetic scenes (_helpers_bundle_adjustment.py): a ring of cameras looking at a cube of points,
every point seen by every camera, observations exact or with Gaussian pixel noise; known answers,
tight tolerances. The BAL reader is in test_bal.py.
"""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from _helpers_bundle_adjustment import observe, perturb, ring_scene
from scipy.spatial.transform import Rotation

from backend.ba_problem import BAOptions, BAProblem
from backend.bundle_adjustment import bundle_adjust, cam_from_world_from_pose3, pose3_from_cam_from_world
from backend.calibration_step import calibration_step
from backend.camera_models import ds2_from_params, project

# a longer focal length: with 500 points and 0.5 px noise, pose and focal noise floors are
# ~0.02 deg and ~0.03 %, well below the tolerances the noisy tests check
LONG_FOCAL = ("SIMPLE_RADIAL", np.array([1000.0, 640.0, 480.0, -0.05]))
EXACT = BAOptions(loss="none", relative_tolerance=1e-12, absolute_tolerance=0.0)


def centres(rotations, translations):
    return -np.einsum("nji,nj->ni", rotations, translations)


def align(src: np.ndarray, dst: np.ndarray):
    """Umeyama similarity (s, Q, c) with dst ≈ s Q src + c."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    q = u @ flip @ vt
    s = np.trace(np.diag(d) @ flip) / (a**2).sum()
    return s, q, mu_d - s * q @ mu_s


def pose_errors(result, truth: dict):
    """Max rotation error (deg) and centre / point errors (m) after a similarity alignment."""
    est_c = centres(result.rotations, result.translations)
    s, q, c = align(est_c, centres(truth["rotations"], truth["translations"]))
    rel = np.einsum("nij,kj,nlk->nil", result.rotations, q, truth["rotations"])
    angles = np.rad2deg(Rotation.from_matrix(rel).magnitude())
    centre_err = np.linalg.norm(
        s * est_c @ q.T + c - centres(truth["rotations"], truth["translations"]), axis=1
    )
    point_err = np.linalg.norm(s * result.points @ q.T + c - truth["points"], axis=1)
    return angles.max(), centre_err.max(), point_err.max()


def test_pose_conversions_round_trip_and_agree_with_gtsam_projection():
    rng = np.random.default_rng(3)
    rotation = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    translation = rng.normal(size=3)
    pose = pose3_from_cam_from_world(rotation, translation)
    back_r, back_t = cam_from_world_from_pose3(pose)
    np.testing.assert_allclose(back_r, rotation, atol=1e-14)
    np.testing.assert_allclose(back_t, translation, atol=1e-14)
    np.testing.assert_allclose(pose.translation(), -rotation.T @ translation, atol=1e-14)
    point = rotation.T @ (np.array([0.3, -0.2, 4.0]) - translation)  # in front of the camera
    cases = {
        "SIMPLE_RADIAL": (
            [800.0, 320.5, 240.0, -0.08],
            gtsam.PinholeCameraCal3Bundler,
            gtsam.Cal3Bundler(800.0, -0.08, 0.0, 320.5, 240.0),
        ),
        "RADIAL": (
            [800.0, 320.5, 240.0, -0.08, 0.02],
            gtsam.PinholeCameraCal3Bundler,
            gtsam.Cal3Bundler(800.0, -0.08, 0.02, 320.5, 240.0),
        ),
        "PINHOLE": ([800.0, 790.0, 320.5, 240.0], gtsam.PinholeCameraCal3DS2, None),
        "OPENCV": (
            [800.0, 790.0, 320.5, 240.0, -0.08, 0.02, 1e-3, -2e-3],
            gtsam.PinholeCameraCal3DS2,
            None,
        ),
    }
    for model, (params, camera_type, cal) in cases.items():
        cal = cal or gtsam.Cal3DS2(*ds2_from_params(model, np.array(params)))
        expected = camera_type(pose, cal).project(point)
        xy = project(model, np.array(params), (rotation @ point + translation)[None])
        np.testing.assert_allclose(xy[0], expected, atol=1e-9, err_msg=model)
    # COLMAP's formula by hand: pixel = f u (1 + k r2) + cx for SIMPLE_RADIAL
    u, v = 0.3 / 4.0, -0.2 / 4.0
    radial = 1 - 0.08 * (u * u + v * v)
    xy = project("SIMPLE_RADIAL", np.array(cases["SIMPLE_RADIAL"][0]), (rotation @ point + translation)[None])
    np.testing.assert_allclose(
        xy[0], [800 * u * radial + 320.5, 800 * v * radial + 240.0], atol=1e-9
    )


@pytest.mark.parametrize("ordering", ["auto", "points_first", "points_then_metis", "metis", "colamd"])
def test_exact_observations_recover_the_truth(ordering):
    truth = ring_scene()
    start = perturb(truth, rot_deg=2.0, trans_frac=0.05)
    result = bundle_adjust(BAProblem(**start), options=replace(EXACT, ordering=ordering))
    assert result.success and result.converged
    assert result.initial_rms > 10.0
    assert result.final_rms < 1e-8
    rot_deg, centre_m, point_m = pose_errors(result, truth)
    assert rot_deg < 1e-8 and centre_m < 1e-8 and point_m < 1e-8
    # the gauge: the first pose does not move, nor does the distance to the farthest camera
    np.testing.assert_allclose(result.rotations[0], start["rotations"][0], atol=1e-12)
    np.testing.assert_allclose(result.translations[0], start["translations"][0], atol=1e-12)
    c_start = centres(start["rotations"], start["translations"])
    c_end = centres(result.rotations, result.translations)
    far = np.argmax(np.linalg.norm(c_start - c_start[0], axis=1))
    assert np.linalg.norm(c_end[far] - c_end[0]) == pytest.approx(
        np.linalg.norm(c_start[far] - c_start[0]), rel=1e-9
    )
    assert result.num_observations == 3000 and result.iterations > 0 and result.time_s > 0


def test_noisy_rms_matches_the_residual_degrees_of_freedom():
    sigma = 0.5
    truth = ring_scene(noise=sigma, seed=5)
    result = bundle_adjust(BAProblem(**perturb(truth)), options=replace(EXACT, refine_intrinsics="focal"))
    n_res = 2 * result.num_observations
    dof = 6 * 10 + 3 * 300 + 1 - 7  # poses, points, focal, minus the similarity gauge
    expected = sigma * np.sqrt(2.0) * np.sqrt((n_res - dof) / n_res)
    assert result.final_rms == pytest.approx(expected, rel=0.05)
    assert result.final_rms < result.initial_rms
    rms = np.sqrt(
        np.mean(
            BAProblem(
                **{
                    **truth,
                    "camera_params": result.camera_params,
                    "rotations": result.rotations,
                    "translations": result.translations,
                    "points": result.points,
                }
            ).reprojection_errors()
            ** 2
        )
    )
    assert rms == pytest.approx(result.final_rms, rel=1e-12)


def test_last_decrease_says_where_the_tolerance_stopped_lm():
    truth = ring_scene(noise=0.5, seed=5)
    start = perturb(truth)
    loose = bundle_adjust(BAProblem(**start), options=replace(EXACT, refine_intrinsics="focal", relative_tolerance=1e-3))
    assert loose.converged and 0.0 <= loose.last_decrease < 1e-3
    one = bundle_adjust(BAProblem(**start), options=replace(EXACT, refine_intrinsics="focal", max_iterations=1))
    assert one.iterations == 1 and not one.converged
    # the first iteration from a perturbed start removes most of the cost
    assert one.last_decrease == pytest.approx(1.0 - (one.final_rms / one.initial_rms) ** 2, abs=0.05)
    assert one.last_decrease > 0.5


def test_gauss_newton_first_matches_lm_from_a_good_start():
    truth = ring_scene(noise=0.5, seed=5)
    start = perturb(truth, keep=(0, 4))
    options = BAOptions(refine_intrinsics="none")
    lm = bundle_adjust(BAProblem(**start, fixed_poses=(0, 4)), options=options)
    gn = bundle_adjust(BAProblem(**start, fixed_poses=(0, 4)), options=replace(options, optimizer="gauss_newton_or_lm"))
    assert gn.success and gn.converged and gn.iterations == lm.iterations
    np.testing.assert_allclose(gn.points, lm.points, atol=1e-7)
    np.testing.assert_allclose(gn.translations, lm.translations, atol=1e-7)
    assert gn.final_rms == pytest.approx(lm.final_rms, rel=1e-9)


@pytest.mark.parametrize("failure", ["cost_rose", "indeterminant"])
def test_gauss_newton_first_falls_back_to_lm(monkeypatch, failure):
    """A Gauss-Newton step that raises the cost, or a GTSAM error, sends the BA to LM from the
    start: the result is LM's."""
    import backend.gtsam_solver as solver

    class Failing:
        def __init__(self, graph, values, params):
            self.params, self.values = params, values

        def optimize(self):
            if failure == "indeterminant":
                raise RuntimeError("Indeterminant linear system")
            self.params.iterationHook(1, 10.0, 20.0)  # the step raised the cost
            return self.values

        def iterations(self):
            return 1

    truth = ring_scene(noise=0.5, seed=5)
    start = perturb(truth)
    lm = bundle_adjust(BAProblem(**start), options=BAOptions(refine_intrinsics="focal"))
    monkeypatch.setattr(solver.gtsam, "GaussNewtonOptimizer", Failing)
    gn = bundle_adjust(BAProblem(**start), options=BAOptions(refine_intrinsics="focal", optimizer="gauss_newton_or_lm"))
    assert gn.success and gn.final_rms == lm.final_rms
    np.testing.assert_array_equal(gn.points, lm.points)
    assert gn.iterations == lm.iterations + (failure == "cost_rose")


def test_robust_loss_resists_gross_outliers():
    """5% of the observations moved by 50 px; sigma 0.5 px elsewhere (noise floor ~0.02 deg)."""
    truth = ring_scene(model=LONG_FOCAL, n_points=500, noise=0.5, seed=7)
    rng = np.random.default_rng(8)
    corrupted = truth["obs_xy"].copy()
    bad = rng.choice(len(corrupted), size=len(corrupted) // 20, replace=False)
    direction = rng.normal(size=(len(bad), 2))
    corrupted[bad] += 50.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    start = perturb({**truth, "obs_xy": corrupted})
    errors = {}
    for loss in ("huber", "cauchy", "none"):
        result = bundle_adjust(BAProblem(**start), options=BAOptions(loss=loss, loss_scale=1.0, refine_intrinsics="none"))
        errors[loss] = pose_errors(result, truth)[0]
    assert errors["huber"] < 0.05 and errors["cauchy"] < 0.05
    assert errors["none"] > 0.2 and errors["none"] > 5 * max(errors["huber"], errors["cauchy"])


def test_fixed_poses_and_fixed_intrinsics_are_exactly_unchanged():
    truth = ring_scene()
    fixed = (0, 3, 7)
    start = perturb(truth, keep=fixed)
    start["camera_params"] = [truth["camera_params"][0] * np.array([1.05, 1, 1, 1])]
    result = bundle_adjust(BAProblem(**start, fixed_poses=fixed), options=BAOptions(refine_intrinsics="none"))
    for i in fixed:
        assert np.array_equal(result.rotations[i], start["rotations"][i])
        assert np.array_equal(result.translations[i], start["translations"][i])
    assert not np.allclose(result.rotations[1], start["rotations"][1])
    assert np.array_equal(result.camera_params[0], start["camera_params"][0])
    assert result.final_rms < result.initial_rms


def test_fixed_poses_with_exact_data_give_the_truth_without_alignment():
    truth = ring_scene()
    result = bundle_adjust(BAProblem(**perturb(truth, keep=(0, 5)), fixed_poses=(0, 5)), options=EXACT)
    np.testing.assert_allclose(result.rotations, truth["rotations"], atol=1e-9)
    np.testing.assert_allclose(result.translations, truth["translations"], atol=1e-9)
    np.testing.assert_allclose(result.points, truth["points"], atol=1e-9)


def test_one_fixed_pose_plus_the_scale_prior_fix_the_gauge():
    truth = ring_scene()
    start = perturb(truth, keep=(2,))
    result = bundle_adjust(BAProblem(**start, fixed_poses=(2,)), options=EXACT)
    assert np.array_equal(result.rotations[2], truth["rotations"][2])
    c_start = centres(start["rotations"], start["translations"])
    c_end = centres(result.rotations, result.translations)
    far = np.argmax(np.linalg.norm(c_start - c_start[2], axis=1))
    assert np.linalg.norm(c_end[far] - c_end[2]) == pytest.approx(
        np.linalg.norm(c_start[far] - c_start[2]), rel=1e-9
    )
    assert max(pose_errors(result, truth)) < 1e-8


def test_reprojection_errors_flag_points_behind_the_camera():
    scene = ring_scene(n_images=2, n_points=5)
    scene["points"][3] = 2.0 * centres(scene["rotations"], scene["translations"])[0]  # behind 0
    errors = BAProblem(**scene).reprojection_errors()
    behind = (scene["obs_image"] == 0) & (scene["obs_point"] == 3)
    assert np.isinf(errors[behind]).all() and np.isfinite(errors[~behind]).all()


def test_focal_refinement_recovers_a_five_percent_error():
    truth = ring_scene(model=LONG_FOCAL, n_points=500, noise=0.5, seed=11)
    start = perturb(truth)
    start["camera_params"] = [truth["camera_params"][0] * np.array([1.05, 1, 1, 1])]
    result = bundle_adjust(BAProblem(**start), options=BAOptions(refine_intrinsics="focal"))
    f_est, f_true = result.camera_params[0][0], truth["camera_params"][0][0]
    assert abs(f_est / f_true - 1) < 1e-3
    # everything but the focal length is held exactly
    np.testing.assert_array_equal(result.camera_params[0][1:], start["camera_params"][0][1:])


def test_radial_distortion_is_recovered():
    truth = ring_scene(model=("SIMPLE_RADIAL", np.array([500.0, 320.0, 240.0, -0.12])))
    start = perturb(truth)
    start["camera_params"] = [np.array([480.0, 320.0, 240.0, 0.0])]
    result = bundle_adjust(BAProblem(**start), options=replace(EXACT, refine_intrinsics="focal_radial"))
    np.testing.assert_allclose(
        result.camera_params[0], truth["camera_params"][0], rtol=1e-9, atol=1e-9
    )
    assert result.final_rms < 1e-8


@pytest.mark.parametrize(
    "model",
    [
        ("SIMPLE_PINHOLE", np.array([500.0, 320.0, 240.0])),
        ("PINHOLE", np.array([500.0, 510.0, 320.0, 240.0])),
        ("RADIAL", np.array([500.0, 320.0, 240.0, -0.1, 0.02])),
        ("OPENCV", np.array([500.0, 505.0, 320.0, 240.0, -0.1, 0.02, 1e-3, -1e-3])),
    ],
)
def test_all_intrinsics_including_principal_point(model):
    truth = ring_scene(model=model)
    start = perturb(truth)
    shifted = truth["camera_params"][0].copy()
    n_focal = 2 if model[0] in ("PINHOLE", "OPENCV") else 1
    shifted[:n_focal] *= 0.97
    shifted[n_focal : n_focal + 2] += [4.0, -3.0]
    start["camera_params"] = [shifted]
    result = bundle_adjust(BAProblem(**start), options=replace(EXACT, refine_intrinsics="all"))
    np.testing.assert_allclose(
        result.camera_params[0], truth["camera_params"][0], rtol=1e-8, atol=1e-8
    )


def test_camera_groups_share_intrinsics():
    truth = ring_scene()
    truth["camera_models"] = ["SIMPLE_RADIAL", "PINHOLE"]
    truth["camera_params"] = [
        np.array([500.0, 320.0, 240.0, -0.05]),
        np.array([620.0, 600.0, 330.0, 250.0]),
    ]
    truth["image_camera"] = np.arange(10) % 2
    truth["obs_xy"] = observe(truth)
    start = perturb(truth)
    start["camera_params"] = [
        truth["camera_params"][0] * [0.96, 1, 1, 0],
        truth["camera_params"][1] * [1.03, 0.98, 1, 1],
    ]
    result = bundle_adjust(BAProblem(**start), options=replace(EXACT, refine_intrinsics="focal_radial"))
    for got, want in zip(result.camera_params, truth["camera_params"]):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)



def test_bad_options_raise():
    scene = ring_scene(n_images=3, n_points=20)
    with pytest.raises(ValueError, match="loss"):
        bundle_adjust(BAProblem(**scene), options=BAOptions(loss="l1"))
    with pytest.raises(ValueError, match="refine_intrinsics"):
        bundle_adjust(BAProblem(**scene), options=BAOptions(refine_intrinsics="everything"))
    with pytest.raises(ValueError, match="observation"):
        bundle_adjust(BAProblem(**{**scene, "obs_image": scene["obs_image"][:0]}))
    with pytest.raises(ValueError, match="not supported"):
        bundle_adjust(BAProblem(**{**scene, "camera_models": ["FISHEYE"]}))
    with pytest.raises(ValueError, match="optimizer"):
        bundle_adjust(BAProblem(**scene), options=BAOptions(optimizer="dogleg"))


def test_observation_sigmas_weigh_the_observations():
    """Half the observations with 0.2 px noise, half with 3 px: weighing each by its sigma (the
    maximum-likelihood BA) lands far nearer the truth than equal weights; sigmas of 1 px are
    the unweighted BA exactly; errors are reported in pixels either way."""
    truth = ring_scene(model=LONG_FOCAL, n_points=300, noise=0.0, seed=11)
    rng = np.random.default_rng(12)
    sigma = np.where(rng.random(len(truth["obs_xy"])) < 0.5, 0.2, 3.0)
    noisy = {**truth, "obs_xy": truth["obs_xy"] + rng.normal(size=truth["obs_xy"].shape) * sigma[:, None]}
    start = perturb(noisy)
    options = replace(EXACT, refine_intrinsics="none")
    plain = bundle_adjust(BAProblem(**start), options=options)
    weighted = bundle_adjust(BAProblem(**start, obs_sigma=sigma), options=options)
    ones = bundle_adjust(BAProblem(**start, obs_sigma=np.ones(len(sigma))), options=options)
    plain_err, weighted_err = pose_errors(plain, truth)[0], pose_errors(weighted, truth)[0]
    assert weighted_err < 0.4 * plain_err, (weighted_err, plain_err)
    assert weighted_err < 0.04, (weighted_err, plain_err)
    np.testing.assert_allclose(ones.rotations, plain.rotations, atol=1e-12)
    np.testing.assert_allclose(ones.points, plain.points, atol=1e-10)
    err = BAProblem(**{**noisy, "rotations": weighted.rotations,
                       "translations": weighted.translations, "points": weighted.points}).reprojection_errors()
    assert weighted.final_rms == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
    assert weighted.final_rms > plain.final_rms  # the weighted fit trades pixels for likelihood
    with pytest.raises(ValueError, match="obs_sigma"):
        bundle_adjust(BAProblem(**start, obs_sigma=np.zeros(len(sigma))), options=options)


def test_the_calibration_steps_covariance_is_the_optimums_also_from_a_state_short_of_it():
    """``calibration_step`` scales its covariance by the residuals at the optimum its step
    predicts.  From the BA's optimum (principal point held) and from that state with every point
    moved by ~1.7 px (twelve times the optimum's cost) the principal point's standard deviations
    agree to 2% (the cost at the given values would make them larger by the square root of the
    cost ratio), and the estimate plus the step lands on the same principal point within its
    uncertainty."""
    sigma = 0.5
    truth = ring_scene(noise=sigma, seed=5)
    held = bundle_adjust(BAProblem(**perturb(truth)), options=replace(EXACT, refine_intrinsics="focal_radial"))
    optimum = replace(BAProblem(**truth), camera_params=held.camera_params, rotations=held.rotations,
                      translations=held.translations, points=held.points)
    rng = np.random.default_rng(2)
    short = replace(optimum, points=optimum.points + rng.normal(0.0, 0.02, optimum.points.shape))
    cost = [np.mean(p.reprojection_errors() ** 2) for p in (optimum, short)]
    assert cost[1] > 10 * cost[0]
    options = replace(EXACT, refine_intrinsics="all")
    [(step_opt, cov_opt)], [(step_short, cov_short)] = calibration_step(optimum, options), calibration_step(short, options)
    std_opt, std_short = np.sqrt(np.diag(cov_opt)[[3, 4]]), np.sqrt(np.diag(cov_short)[[3, 4]])
    np.testing.assert_allclose(std_short, std_opt, rtol=0.02)
    start = ds2_from_params("SIMPLE_RADIAL", held.camera_params[0])
    np.testing.assert_allclose((start + step_short)[[3, 4]], (start + step_opt)[[3, 4]], atol=std_opt.max())


def test_the_result_says_why_the_optimiser_stopped_and_what_the_cost_did():
    truth = ring_scene(noise=0.5, seed=5)
    start = BAProblem(**perturb(truth))
    options = replace(EXACT, refine_intrinsics="focal")
    done = bundle_adjust(start, options=replace(options, relative_tolerance=1e-3))
    assert done.stopped == "relative decrease below tolerance 0.001"
    # GTSAM's cost is half the sum of squared whitened errors (EXACT: no robust loss, 1 px sigma)
    assert done.initial_cost == pytest.approx(0.5 * done.num_observations * done.initial_rms**2, rel=1e-6)
    assert done.final_cost == pytest.approx(0.5 * done.num_observations * done.final_rms**2, rel=1e-6)
    one = bundle_adjust(start, options=replace(options, max_iterations=1))
    assert one.stopped == "maximum iterations (1)"
    predicted = bundle_adjust(start, options=replace(options, predictive_stop=True, optimizer="gauss_newton_or_lm"))
    assert predicted.stopped.startswith("predicted decrease below relative tolerance")
    assert predicted.solver_messages == 0 == done.solver_messages


def test_gtsam_messages_stay_off_the_terminal_and_are_counted(capfd):
    """A point behind a camera makes GTSAM's GeneralSFMFactor print a CheiralityException line
    each time the cost is evaluated; the BA counts them and the terminal sees none."""
    scene = ring_scene(n_images=4, n_points=40)
    scene["points"][3] = 2.0 * centres(scene["rotations"], scene["translations"])[0]  # behind camera 0
    capfd.readouterr()
    result = bundle_adjust(BAProblem(**scene), options=replace(EXACT, refine_intrinsics="focal", max_iterations=3))
    out, err = capfd.readouterr()
    assert out == "" and "Cheirality" not in err
    assert result.solver_messages >= 2  # at least the costs before and after


def test_stop_reasons_of_a_partitioned_ba_are_pooled():
    from backend.partitioned_ba import _stop_reasons

    assert _stop_reasons(["maximum iterations (5)"] * 3) == "maximum iterations (5) (each of 3 parts)"
    assert _stop_reasons(["a", "b", "a"]) == "a (2 of 3 parts); b (1 of 3 parts)"


def test_points_then_metis_orders_points_then_poses_then_calibrations():
    from backend.bundle_adjustment import build_graph, camera_pairs
    from backend.gtsam_solver import elimination_ordering
    from gtsam.symbol_shorthand import K, L, X

    scene = ring_scene(n_images=6, n_points=30)
    problem, options = BAProblem(**scene), BAOptions(refine_intrinsics="focal", ordering="points_then_metis")
    built = build_graph(problem, options)
    pairs = camera_pairs(problem, built, built.graph.size(), options)
    assert len(pairs) == 15 and set(pairs.ravel().tolist()) == {X(i) for i in range(6)}  # every point seen by all
    order = elimination_ordering("points_then_metis", built.graph, built.values, pairs)
    keys = [order.at(i) for i in range(order.size())]
    assert set(keys[:30]) == {L(j) for j in range(30)} and set(keys[30:36]) == {X(i) for i in range(6)}
    assert keys[36:] == [K(0)]
    last = elimination_ordering("points_then_metis", built.graph, built.values, pairs, last=(X(2),))
    assert last.at(last.size() - 1) == X(2) and last.size() == 37
