"""Pose-only refinement: one image's cam_from_world from 2D-3D matches, points and intrinsics
held (GTSAM's Levenberg-Marquardt, the robust losses of :mod:`backend.bundle_adjustment`)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from backend.bundle_adjustment import (
    HOLD_SIGMA,
    BAOptions,
    cam_from_world_from_pose3,
    ds2_from_params,
    pose3_from_cam_from_world,
    reprojection_errors,
    rms,
)
from backend.gtsam_solver import lm_optimizer, optimize_or_keep, robust_noise

Array = np.ndarray


@dataclass(frozen=True)
class PoseRefineResult:
    """Result of :func:`refine_pose`: cam_from_world (rotation, translation) and pixel RMS."""

    rotation: Array
    translation: Array
    initial_rms: float
    final_rms: float
    iterations: int
    success: bool


def refine_pose(
    camera_model: str,
    camera_params: Array,
    rotation: Array,
    translation: Array,
    points: Array,
    obs_xy: Array,
    loss: str = "huber",
    loss_scale: float = 1.0,
    max_iterations: int = 50,
) -> PoseRefineResult:
    """Refine one image's cam_from_world pose from 2D-3D matches (points and intrinsics fixed).

    Used after PnP: ``points`` (K,3) observed at ``obs_xy`` (K,2). Each point is a variable
    pinned by a tight prior (GTSAM's Python API has no pose-only projection factor), so the
    pose is the only thing that moves; the robust loss is as in :class:`BAOptions`.
    """
    rotation, translation = np.asarray(rotation, float), np.asarray(translation, float)
    points, obs_xy = np.asarray(points, float), np.asarray(obs_xy, float)
    index = np.arange(len(points))
    cameras, obs = ([camera_model], [camera_params], [0]), (0 * index, index, obs_xy)
    err0 = reprojection_errors(*cameras, rotation[None], translation[None], points, *obs)
    cal = gtsam.Cal3DS2(*ds2_from_params(camera_model, camera_params))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    values.insert(X(0), pose3_from_cam_from_world(rotation, translation))
    noise = robust_noise(loss, loss_scale)
    scale = max(float(np.linalg.norm(points - points.mean(0), axis=1).max(initial=0.0)), 1e-9)
    point_noise = gtsam.noiseModel.Isotropic.Sigma(3, HOLD_SIGMA * scale)
    for j, (point, xy) in enumerate(zip(points, obs_xy)):
        values.insertPoint3(L(j), point)
        graph.add(gtsam.GenericProjectionFactorCal3DS2(xy, noise, X(0), L(j), cal))
        graph.add(gtsam.PriorFactorPoint3(L(j), point, point_noise))
    options = BAOptions(
        max_iterations=max_iterations,
        relative_tolerance=1e-8,
        absolute_tolerance=1e-10,
        ordering="colamd",
    )
    optimizer = lm_optimizer(graph, values, options)
    result, success = optimize_or_keep(optimizer, values, "pose refinement")
    rot, trans = cam_from_world_from_pose3(result.atPose3(X(0)))
    err = reprojection_errors(*cameras, rot[None], trans[None], points, *obs)
    return PoseRefineResult(rot, trans, rms(err0), rms(err), optimizer.iterations(), success)
