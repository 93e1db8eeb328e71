"""Bundle adjustment as a GTSAM factor graph, behind an array interface.

The local and global BAs of incremental SfM and the final bundle adjustment after merging
(paper section 3, Figure 1).  :func:`bundle_adjust` takes a :class:`backend.ba_problem.BAProblem`
and :class:`backend.ba_problem.BAOptions` and returns a :class:`backend.ba_problem.BAResult`.

Conventions: poses are ``cam_from_world`` (x_cam = R X + t, OpenCV axes: x right, y down, z
forward); GTSAM's ``Pose3`` of a camera is ``world_from_cam`` and is converted only by
:func:`pose3_from_cam_from_world` and :func:`cam_from_world_from_pose3`. Intrinsics are COLMAP
models per camera group, projected as :mod:`backend.camera_models` does.

Factors: with intrinsics held fixed, ``GenericProjectionFactorCal3DS2`` (pose and point
variables; Cal3DS2 reproduces every supported model exactly), and ``TriangulationFactorCal3DS2``
(point only) for the observations of held images when two or more are held (a local BA). When intrinsics are refined, the
calibration of each group is ONE variable shared by its images' factors
(``GeneralSFMFactor2``): ``Cal3Bundler`` (f, k1, k2; principal point constant) for the
single-focal models whose principal point is held ("focal", "focal_radial"), ``Cal3DS2``
otherwise. Components of the calibration that must not move are held by a tight prior (sigma
1e-7 relative) and returned exactly as given; fx = fy of a single-focal model in a Cal3DS2
variable is tied by a one-row factor.
The level of refinement may differ between groups (``BAOptions.refine_intrinsics`` per group; a
group at "none" among refined ones is a calibration variable held whole by its prior).
:mod:`backend.calibration_step` linearises the same graph (:func:`build_graph`) without
optimising it.
(GTSAM 4.3 gotcha: Python's ``Cal3Bundler.uncalibrate`` binds Cal3f's and skips distortion;
the C++ factors and ``PinholeCameraCal3Bundler.project`` apply k1 r2 + k2 r2² correctly.)
Factors are added in a Python loop (GTSAM's Python API has no bulk constructor for them); the
time goes to GTSAM's linearisation and elimination.
The robust noise and the Levenberg-Marquardt runs are :mod:`backend.gtsam_solver`'s.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
import gtsam
import numpy as np
from gtsam.symbol_shorthand import K, L, X

from backend.ba_problem import BAOptions, BAProblem, BAResult
from backend.camera_models import SINGLE_FOCAL_MODELS, ds2_from_params, params_from_ds2
from backend.gtsam_solver import captured_stdout, covisible_pose_keys, resolve_ordering, robust_noise, solve

logger = logging.getLogger(__name__)
Array = np.ndarray

# Free Cal3DS2 components [fx, fy, s, u0, v0, k1, k2, p1, p2] per model beyond the focal lengths.
_EXTRA_DS2 = {
    "SIMPLE_PINHOLE": [],
    "PINHOLE": [],
    "SIMPLE_RADIAL": [5],
    "RADIAL": [5, 6],
    "OPENCV": [5, 6, 7, 8],
}
HOLD_SIGMA = 1e-7  # relative sigma of the priors that hold parameters and the gauge pose
_TIE_SIGMA = 1e-6  # relative sigma of fx - fy = 0 (tighter makes LM stall)
_SCALE_SIGMA = 1e-4  # relative sigma of the scale prior: a pure gauge, so its weight is moot


def pose3_from_cam_from_world(rotation: np.ndarray, translation: np.ndarray) -> gtsam.Pose3:
    """GTSAM ``Pose3`` (world_from_cam) of a camera given as cam_from_world (R, t)."""
    world_from_cam_rot = np.asarray(rotation, dtype=float).T
    centre = -world_from_cam_rot @ np.asarray(translation, dtype=float)
    return gtsam.Pose3(gtsam.Rot3(world_from_cam_rot), centre)


def cam_from_world_from_pose3(pose: gtsam.Pose3) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera given as a GTSAM ``Pose3`` (world_from_cam)."""
    rotation = pose.rotation().matrix().T
    return rotation, -rotation @ pose.translation()


def rms(err: Array) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else 0.0


# What each level refines besides the focal lengths: (the distortion, the principal point).
_LEVEL_PARTS = {"focal": (False, False), "focal_radial": (True, False), "focal_principal": (False, True),
                "all": (True, True)}
REFINE_LEVELS = ("none", *_LEVEL_PARTS)


def free_ds2(model: str, refine: str) -> list[int]:
    """Cal3DS2 components refined for ``model`` under ``refine`` (skew never)."""
    if refine == "none":
        return []
    if refine not in _LEVEL_PARTS:
        raise ValueError(f"unknown refine_intrinsics {refine!r}")
    distortion, principal_point = _LEVEL_PARTS[refine]
    return [0, 1] + (_EXTRA_DS2[model] if distortion else []) + ([3, 4] if principal_point else [])


def refine_level(distortion: bool, principal_point: bool) -> str:
    """The level that refines the focal lengths and, as asked, the distortion and the principal
    point."""
    return next(level for level, parts in _LEVEL_PARTS.items() if parts == (distortion, principal_point))


def uses_bundler(model: str, refine: str) -> bool:
    """Cal3Bundler (f, k1, k2 variable; principal point constant) fits, else Cal3DS2."""
    return model in SINGLE_FOCAL_MODELS and not _LEVEL_PARTS.get(refine, (False, False))[1]


def _add_calibration(graph, values, key: int, model: str, params: Array, refine: str) -> None:
    """Insert one group's calibration variable, with priors holding what is not refined."""
    ds2, free = ds2_from_params(model, params), free_ds2(model, refine)
    if uses_bundler(model, refine):
        values.insert(key, gtsam.Cal3Bundler(ds2[0], ds2[5], ds2[6], ds2[3], ds2[4]))
        held, sigmas = [j not in free for j in (0, 5, 6)], np.array([ds2[0], 1.0, 1.0])
        cal, prior = values.atCal3Bundler(key), gtsam.PriorFactorCal3Bundler
    else:
        values.insert(key, gtsam.Cal3DS2(*ds2))
        held, sigmas = [j not in free for j in range(9)], np.array([ds2[0]] * 5 + [1.0] * 4)
        cal, prior = values.atCal3DS2(key), gtsam.PriorFactorCal3DS2
    if model in SINGLE_FOCAL_MODELS and not uses_bundler(model, refine):  # tie fx = fy
        tie_jacobian = np.eye(1, 9) - np.eye(1, 9, 1)

        def tie(this, vals, jacobians):
            if jacobians is not None:
                jacobians[0] = tie_jacobian
            return tie_jacobian @ vals.atCal3DS2(this.keys()[0]).vector()

        tie_noise = gtsam.noiseModel.Isotropic.Sigma(1, _TIE_SIGMA * ds2[0])
        graph.add(gtsam.CustomFactor(tie_noise, [key], tie))
    if any(held):
        precisions = np.where(held, 1.0 / (HOLD_SIGMA * sigmas) ** 2, 0.0)
        graph.add(prior(key, cal, gtsam.noiseModel.Diagonal.Precisions(precisions)))


def group_levels(refine: str | Sequence[str], num_groups: int) -> list[str]:
    """``BAOptions.refine_intrinsics`` as one level per camera group."""
    levels = [refine] * num_groups if isinstance(refine, str) else list(refine)
    if len(levels) != num_groups:
        raise ValueError(f"refine_intrinsics has {len(levels)} levels for {num_groups} camera groups")
    bad = [lv for lv in levels if lv not in REFINE_LEVELS]
    if bad:
        raise ValueError(f"unknown refine_intrinsics {bad[0]!r}; use one of {', '.join(REFINE_LEVELS)}")
    return levels


def _calibration_params(values, key: int, cameras: tuple, group: int, refine: str) -> Array:
    """The group's refined parameters; held ones exactly as given."""
    model = cameras[0][group]
    ds2 = ds2_from_params(model, cameras[1][group])
    if uses_bundler(model, refine):
        cal = values.atCal3Bundler(key)
        new = np.array([cal.fx(), cal.fx(), 0.0, cal.px(), cal.py(), cal.k1(), cal.k2(), 0.0, 0.0])
    else:
        new = values.atCal3DS2(key).vector()
    free = free_ds2(model, refine)
    ds2[free] = new[free]
    return params_from_ds2(model, ds2)


def _noise_per_observation(options: BAOptions, obs_sigma: Array | None, num_obs: int) -> list:
    """The robust noise model of every observation; one model per distinct sigma (in steps
    of 0.5%), shared by the factors that use it."""
    if obs_sigma is None:
        return [robust_noise(options.loss, options.loss_scale)] * num_obs
    sigma = np.asarray(obs_sigma, float)
    if sigma.shape != (num_obs,) or not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(f"obs_sigma must hold {num_obs} positive finite values")
    levels, index = np.unique(np.round(np.log(sigma) / np.log1p(0.005)), return_inverse=True)
    levels = np.exp(levels * np.log1p(0.005))
    models = [robust_noise(options.loss, options.loss_scale, float(s)) for s in levels]
    return [models[k] for k in index.ravel().tolist()]


def _add_projection_factors(graph, values, cameras, obs, groups, noise: list, levels: list[str],
                            constant: dict | None = None) -> None:  # fmt: skip
    """One projection factor per observation (``noise[m]`` its noise model); calibration
    variables when intrinsics move (``levels``: per group).  ``constant`` (only when every
    level is "none"): image ->
    Pose3 of the images whose poses are constants, not variables: their observations are
    factors on the point alone."""
    camera_models, camera_params, image_camera = cameras
    obs_image, obs_point, obs_xy = obs
    obs_camera = image_camera[obs_image].tolist()
    rows = zip(obs_image.tolist(), obs_point.tolist(), obs_camera, obs_xy, noise)
    if all(levels[g] == "none" for g in groups):  # no calibration variables: constant Cal3DS2
        cals = {
            g: gtsam.Cal3DS2(*ds2_from_params(camera_models[g], camera_params[g])) for g in groups
        }
        constant = constant or {}
        held = {i: gtsam.PinholeCameraCal3DS2(pose, cals[int(image_camera[i])]) for i, pose in constant.items()}
        for i, j, g, xy, nm in rows:
            if i in held:
                graph.add(gtsam.TriangulationFactorCal3DS2(held[i], xy, nm, L(j)))
            else:
                graph.add(gtsam.GenericProjectionFactorCal3DS2(xy, nm, X(i), L(j), cals[g]))
        return
    factor = {}  # one calibration variable per group, shared by its observations
    for g in groups:
        _add_calibration(graph, values, K(g), camera_models[g], camera_params[g], levels[g])
        bundler = uses_bundler(camera_models[g], levels[g])
        factor[g] = (
            gtsam.GeneralSFMFactor2Cal3Bundler if bundler else gtsam.GeneralSFMFactor2Cal3DS2
        )
    for i, j, g, xy, nm in rows:
        graph.add(factor[g](xy, nm, X(i), L(j), K(g)))


def _add_gauge(graph, values, poses: list, observed: Array, options: BAOptions, held: list[int]) -> None:
    """Priors on the ``held`` poses (the observed ones of ``BAProblem.fixed_poses``), and the
    gauge (anchor pose and scale), see :class:`BAOptions`."""
    centres = np.array([pose.translation() for pose in poses])[observed]
    spread = np.median(np.linalg.norm(centres - centres.mean(0), axis=1))
    scale = max(float(spread), 1e-9)
    pose_sigmas = HOLD_SIGMA * np.array([1, 1, 1, scale, scale, scale])
    anchors = list(held)
    if not anchors:
        anchor = options.gauge_pose if options.gauge_pose is not None else int(observed[0])
        if anchor not in set(observed.tolist()):
            raise ValueError(f"gauge_pose {anchor} has no observations")
        anchors = [anchor]
    for i in anchors:
        prior_noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)
        graph.add(gtsam.PriorFactorPose3(X(i), values.atPose3(X(i)), prior_noise))
    if len(anchors) == 1 and len(observed) > 1:
        dist = np.linalg.norm(centres - centres[observed.tolist().index(anchors[0])], axis=1)
        far, d = int(observed[np.argmax(dist)]), max(float(dist.max()), 1e-9)
        range_noise = gtsam.noiseModel.Isotropic.Sigma(1, _SCALE_SIGMA * d)
        graph.add(gtsam.RangeFactorPose3(X(anchors[0]), X(far), d, range_noise))


@dataclass
class BAGraph:
    """The factor graph of a problem and what :func:`bundle_adjust` needs of its building."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    levels: list[str]
    refined: list[int]
    observed: Array
    seen_points: Array
    cameras: tuple
    pose_variables: Array  # images whose pose is a variable


def camera_pairs(problem: BAProblem, built: BAGraph, num_factors: int, options: BAOptions) -> Array | None:
    """The co-visible pose variables' keys where the ordering needs them
    (``backend.gtsam_solver.covisible_pose_keys``); else None."""
    if resolve_ordering(options.ordering, num_factors) != "points_then_metis":
        return None
    return covisible_pose_keys(problem.obs_image, problem.obs_point, built.pose_variables, len(problem.rotations),
                               len(problem.points))


def build_graph(problem: BAProblem, options: BAOptions) -> BAGraph:
    """The graph and initial values of ``problem`` under ``options`` (module docstring)."""
    camera_models, camera_params, image_camera = problem.camera_models, problem.camera_params, problem.image_camera
    obs_image, obs_point, obs_xy, obs_sigma = problem.obs_image, problem.obs_point, problem.obs_xy, problem.obs_sigma
    if len(obs_image) == 0:
        raise ValueError("bundle adjustment needs at least one observation")
    rotations, translations = np.asarray(problem.rotations, float), np.asarray(problem.translations, float)
    points, obs_xy = np.asarray(problem.points, float), np.asarray(obs_xy, float)
    obs_image, obs_point = np.asarray(obs_image, np.int64), np.asarray(obs_point, np.int64)
    image_camera = np.asarray(image_camera, np.int64)
    levels = group_levels(options.refine_intrinsics, len(camera_models))
    cameras, obs = (camera_models, camera_params, image_camera), (obs_image, obs_point, obs_xy)
    observed, seen_points = np.unique(obs_image), np.unique(obs_point)
    groups = sorted(set(image_camera[observed].tolist()))
    refined = [g for g in groups if levels[g] != "none"]
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    poses = [pose3_from_cam_from_world(r, t) for r, t in zip(rotations, translations)]
    # Held poses are constants when two or more are observed and the intrinsics are held too
    # (a local BA): they fix the gauge, and the reduced camera system holds the free poses
    # alone.  Otherwise they are variables under tight priors (_add_gauge).
    held = sorted(set(problem.fixed_poses) & set(observed.tolist()))
    constant = {i: poses[i] for i in held} if not refined and len(held) >= 2 else {}
    for i in observed.tolist():
        if i not in constant:
            values.insert(X(i), poses[i])
    for j in seen_points.tolist():
        values.insertPoint3(L(j), points[j])
    noise = _noise_per_observation(options, obs_sigma, len(obs_image))
    _add_projection_factors(graph, values, cameras, obs, groups, noise, levels, constant)
    if not constant:
        _add_gauge(graph, values, poses, observed, options, held)
    pose_variables = np.array([i for i in observed.tolist() if i not in constant], np.int64)
    return BAGraph(graph, values, levels, refined, observed, seen_points, cameras, pose_variables)


def bundle_adjust(problem: BAProblem, options: BAOptions = BAOptions()) -> BAResult:
    """Jointly refine poses, points and (optionally) per-group intrinsics (robust LM, GTSAM): the
    bundle adjustments of local SfM (paper section 3.2) and the final one (Figure 1).

    Images, points and groups without observations are returned unchanged, and so are the
    poses in ``problem.fixed_poses``.  Errors reported are in pixels.
    """
    start = time.perf_counter()
    with captured_stdout("bundle adjustment") as printed:
        built = build_graph(problem, options)
        graph, values = built.graph, built.values
        built_s = time.perf_counter() - start
        logger.debug("BA graph: %d factors, %d variables, %.2f s", graph.size(), values.size(), built_s)
        history: list[tuple[float, float]] = []
        run = solve(graph, values, options, history, "bundle adjustment", camera_pairs(problem, built, graph.size(), options))
        initial_cost, final_cost = graph.error(values), graph.error(run.values)
    result, levels, refined = run.values, built.levels, built.refined
    observed, seen_points, cameras = built.observed, built.seen_points, built.cameras
    rotations, translations = np.asarray(problem.rotations, float), np.asarray(problem.translations, float)
    points, camera_params = np.asarray(problem.points, float), problem.camera_params
    obs_image = np.asarray(problem.obs_image, np.int64)
    initial_err = problem.reprojection_errors()
    success = run.success and final_cost <= initial_cost
    rot_out, trans_out, pts_out = rotations.copy(), translations.copy(), points.copy()
    for i in set(observed.tolist()) - set(problem.fixed_poses):
        rot_out[i], trans_out[i] = cam_from_world_from_pose3(result.atPose3(X(i)))
    for j in seen_points.tolist():
        pts_out[j] = result.atPoint3(L(j))
    params_out = [np.asarray(p, float).copy() for p in camera_params]
    for g in refined:
        params_out[g] = _calibration_params(result, K(g), cameras, g, levels[g])
    final_err = replace(problem, camera_params=params_out, rotations=rot_out, translations=trans_out,
                        points=pts_out).reprojection_errors()
    res = BAResult(
        rotations=rot_out,
        translations=trans_out,
        points=pts_out,
        camera_params=tuple(params_out),
        initial_rms=rms(initial_err),
        final_rms=rms(final_err),
        final_mean_error=float(final_err.mean()) if len(final_err) else 0.0,
        iterations=run.iterations,
        time_s=time.perf_counter() - start,
        num_observations=len(obs_image),
        success=success,
        converged=run.converged,
        last_decrease=(history[-1][0] - history[-1][1]) / max(history[-1][0], 1e-300) if history else 0.0,
        initial_cost=initial_cost,
        final_cost=final_cost,
        stopped=run.stopped if final_cost <= initial_cost else f"{run.stopped}; the cost rose",
        solver_messages=printed.lines,
    )
    summary = f"{res.initial_rms:.4f} -> {res.final_rms:.4f} px, {res.iterations} iterations, stopped: {res.stopped}"
    level = logging.INFO if options.verbose else logging.DEBUG
    logger.log(level, "BA on %d observations: RMS %s, %.2f s", len(obs_image), summary, res.time_s)
    return res
