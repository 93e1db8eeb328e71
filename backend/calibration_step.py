"""What a bundle adjustment would do to each camera's calibration, and how well the data
determine it, without running it.

:func:`calibration_step` builds the graph of :func:`backend.bundle_adjustment.bundle_adjust`,
linearises it at the problem's values and eliminates every point and pose (the Schur complement
onto the calibration variables): each refined group's Gauss-Newton step and covariance.  The
self-calibration tests of the final BAs read them (``sfm.mapper.self_calibration``: is the
distortion, is the principal point's shift significant?) before the BA they decide.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import K

from backend.ba_problem import BAOptions, BAProblem
from backend.bundle_adjustment import build_graph, camera_pairs, free_ds2, uses_bundler
from backend.gtsam_solver import captured_stdout, elimination_ordering

logger = logging.getLogger(__name__)
Array = np.ndarray


def calibration_step(problem: BAProblem, options: BAOptions) -> list[tuple[Array, Array] | None]:
    """Per camera group, ``(step, covariance)`` of its Cal3DS2 vector [fx, fy, s, u0, v0, k1, k2,
    p1, p2] at the problem's values, without optimising: the graph of :func:`bundle_adjust`
    linearised there (the robust loss weighs each observation by its current error), every point
    and pose eliminated (the Schur complement onto the calibration variables, exact), then over
    the free components (the held ones conditioned on, their rows zero) the Gauss-Newton step
    ``Lambda^-1 eta`` and the covariance ``Lambda^-1`` times the a-posteriori variance factor
    ``s0^2 = sum of squared whitened residuals / redundancy`` (the photogrammetric estimate of the
    observations' variance, of which their sigmas are only relative weights), the residuals
    taken at the optimum the step predicts (the linearised cost with every pose and point at its
    optimum and the free components moved by the step), not at the given values: a state short
    of convergence (a growing model before its final BA) would otherwise inflate the covariance
    by its excess cost.  At a BA's optimum with some components held, the step is where freeing
    them would move them to first order, and the covariance how well the data determine them.
    A Cal3Bundler group's (f, k1, k2) fill [fx and fy, k1, k2].  None for groups not refined or
    without observations, and for every group when the system is singular."""
    built = build_graph(problem, options)
    graph, values, levels, refined, cameras = built.graph, built.values, built.levels, built.refined, built.cameras
    out: list[tuple[Array, Array] | None] = [None] * len(problem.camera_models)
    if not refined:
        return out
    keys = [K(g) for g in refined]
    last = set(keys)
    others = [k for k in values.keys() if k not in last]
    try:
        with captured_stdout("calibration step"):
            linear = graph.linearize(values)
        # the BA's own ordering (backend.gtsam_solver), the calibrations last and kept
        name = options.ordering if options.ordering not in ("metis", "colamd") else "points_then_metis"
        ordering = elimination_ordering(name, graph, values, camera_pairs(problem, built, graph.size(),
                                                                          replace(options, ordering=name)), tuple(keys))
        order = [ordering.at(i) for i in range(ordering.size() - len(keys))]
        _, rest = linear.eliminatePartialMultifrontal(gtsam.Ordering(order))
        information, eta = rest.hessian(gtsam.Ordering(keys))
    except RuntimeError as exc:
        logger.debug("calibration step: %s", exc)
        return out
    sizes = [3 if uses_bundler(cameras[0][g], levels[g]) else 9 for g in refined]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    free = np.concatenate([o + np.array(_free_local(cameras[0][g], levels[g]), int)
                           for g, o in zip(refined, offsets[:-1])])
    num_poses = sum(1 for k in others if gtsam.Symbol(k).chr() == ord("x"))
    redundancy = 2 * len(problem.obs_image) - (6 * num_poses + 3 * (len(others) - num_poses) + len(free) - 7)
    try:
        inverse = np.linalg.inv(information[np.ix_(free, free)])
    except np.linalg.LinAlgError:
        return out
    if redundancy <= 0 or not np.all(np.isfinite(inverse)):
        return out
    step, cov = np.zeros(offsets[-1]), np.zeros((offsets[-1], offsets[-1]))
    step[free] = inverse @ np.asarray(eta, float).ravel()[free]
    # The residual at the optimum the step predicts: the eliminated poses and points take
    # their optimal values for any calibration, so the reduced graph's error at the step is
    # the whole linearised cost there.
    at_step = gtsam.VectorValues()
    for key, o, n in zip(keys, offsets[:-1], sizes):
        at_step.insert(key, step[o:o + n])
    variance_factor = 2.0 * max(rest.error(at_step), 0.0) / redundancy
    cov[np.ix_(free, free)] = inverse * variance_factor
    for g, o, n in zip(refined, offsets[:-1], sizes):
        g_step, g_cov = step[o:o + n], cov[o:o + n, o:o + n]
        if n == 3:  # Cal3Bundler (f, k1, k2) -> the Cal3DS2 layout, fx = fy = f
            where = np.array([0, 1, 5, 6])
            layout = np.zeros((4, 3))
            layout[[0, 1, 2, 3], [0, 0, 1, 2]] = 1.0
            g_step, g_cov = np.zeros(9), np.zeros((9, 9))
            g_step[where] = layout @ step[o:o + n]
            g_cov[np.ix_(where, where)] = layout @ cov[o:o + n, o:o + n] @ layout.T
        out[g] = (g_step, g_cov)
    return out


def _free_local(model: str, refine: str) -> list[int]:
    """The free components of a group's calibration variable in its own tangent layout."""
    free = free_ds2(model, refine)
    if uses_bundler(model, refine):
        return [k for k, j in enumerate((0, 5, 6)) if j in free]
    return free
