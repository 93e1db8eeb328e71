"""A bundle adjustment too large for memory, as the consensus of BAs over disjoint track parts.

GTSAM holds every factor, its linearised Jacobian and its share of the elimination in memory
while it optimises, so memory grows with the number of observations and a large block's final
BA may not fit.  Here the points are split at random into ``K`` parts of about equal size; each
part is bundle-adjusted on its own with every camera and the shared intrinsics free and the
same gauge (the same anchor pose and scale prior, so the parts' results live in one frame);
then each camera's pose is the mean of its part estimates (rotation: the chordal L2 mean, the
mean matrix projected onto SO(3); centre: the arithmetic mean) and each calibration the mean
of its part estimates.  Peak memory is that of one part.

Why a mean and not one part: in the linear regime each part's estimate is the full solution
plus an independent error whose covariance is about ``K`` times the full BA's (a random part
carries 1/K of the information about every camera); the mean of ``K`` such estimates has the
full BA's covariance again: the classic one-shot divide-and-conquer estimator.  One part alone,
or a best-spread subset of the tracks (``backend.track_subset``), carries only part of the
information, which matters where the problem is nearly flat: a nadir aerial block lets focal
length, radial distortion and camera tilt trade along a shallow valley (the "doming" of
self-calibrating aerial BA).

What the mean does not pool is that flat direction itself.  A part with a fraction of the
points pins focal, distortion and tilt far worse than in proportion, and the single BA's
estimate along the valley comes from the parts' joint information (cameras held by all points
at once pin the intrinsics), which a mean of their estimates does not carry.  So the poses
average well and the self-calibrated intrinsics less well than one BA over everything: split a
BA only when one does not fit in memory.

The points returned are each from its own part (consistent with the averaged cameras to the
parts' small spread); the caller re-estimates them with the averaged cameras held.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from backend.ba_problem import BAOptions, BAProblem, BAResult
from backend.bundle_adjustment import bundle_adjust
from backend.camera_models import reprojection_errors
from backend.geometry import project_to_so3
from backend.memory import physical_memory_bytes, return_freed_memory

logger = logging.getLogger(__name__)
_ERROR_ROWS = 1_000_000
# Peak memory of one GTSAM BA (points eliminated first) per observation: a part for the
# observation itself (its factor, linearised Jacobian and the caller's arrays) and a part per
# view of its track: eliminating a point seen by k cameras leaves a factor over those cameras,
# 2k-3 rows by 6k+2 columns of doubles (about 96 k^2 bytes, 96 k per observation), which GTSAM may
# hold until the cameras are eliminated.  So the memory grows with the observations times their
# tracks' lengths, not with the observations alone.  Fitted from above to the peak RSS of one LM
# iteration on rings of 300 cameras at 600k observations with tracks of 5, 20 and 60 views (1.2,
# 1.3 and 6.2 kB per observation) and of the merged final BA of the 1,000-image synthetic aerial
# block (1.83M observations, tracks of 10 views: 1.3 kB).
BYTES_PER_OBSERVATION = 750
BYTES_PER_OBSERVATION_AND_VIEW = 96
# Share of the machine's physical memory one BA may take when no budget is given: the rest is
# the process's model and database, the other workers and the system.
MEMORY_SHARE = 0.5


def bytes_per_observation(track_lengths: np.ndarray | None = None) -> float:
    """Peak memory of one BA per observation over tracks of these lengths (one per track):
    ``BYTES_PER_OBSERVATION + BYTES_PER_OBSERVATION_AND_VIEW`` times the mean length of the
    track an observation belongs to (``sum k^2 / sum k``); tracks of 10 views when unknown."""
    lengths = np.asarray(track_lengths if track_lengths is not None else [10], float)
    views = float(np.sum(lengths**2) / np.sum(lengths)) if np.sum(lengths) > 0 else 0.0
    return BYTES_PER_OBSERVATION + BYTES_PER_OBSERVATION_AND_VIEW * views


def observations_in_memory(memory_bytes: int | None = None, share: float = MEMORY_SHARE,
                           track_lengths: np.ndarray | None = None) -> int:
    """The most observations one BA over tracks of ``track_lengths`` (:func:`bytes_per_observation`)
    holds within ``share`` of ``memory_bytes`` (default: this machine's physical memory); 0 (no
    limit) where the memory is unknown.  The budget of :func:`bundle_adjust_partitioned`'s
    callers when the user gives none: split a BA only when one does not fit (module docstring);
    a random part of the tracks has their mix of lengths, so the budget holds for each part."""
    memory_bytes = physical_memory_bytes() if memory_bytes is None else memory_bytes
    if not memory_bytes:
        return 0
    return max(1, int(memory_bytes * share / bytes_per_observation(track_lengths)))


def bundle_adjust_partitioned(problem: BAProblem, num_parts: int, options: BAOptions = BAOptions(),
                              seed: int = 0) -> BAResult:
    """:func:`backend.bundle_adjustment.bundle_adjust` over ``num_parts`` random disjoint parts
    of the points, averaged (see the module docstring); same result layout.  Images seen by no
    part and the poses in ``problem.fixed_poses`` are returned as given."""
    start = time.perf_counter()
    if num_parts <= 1:
        return bundle_adjust(problem, options)
    obs_image, obs_point = np.asarray(problem.obs_image, np.int64), np.asarray(problem.obs_point, np.int64)
    rotations, translations = np.asarray(problem.rotations, float), np.asarray(problem.translations, float)
    points, obs_xy = np.asarray(problem.points, float), np.asarray(problem.obs_xy, float)
    image_camera, camera_models, camera_params = np.asarray(problem.image_camera), problem.camera_models, problem.camera_params
    seen = np.unique(obs_point)
    part_of_point = np.full(len(points), -1)
    part_of_point[np.random.default_rng(seed).permutation(seen)] = np.arange(len(seen)) % num_parts
    if not problem.fixed_poses and options.gauge_pose is None:  # one anchor for every part
        options = replace(options, gauge_pose=int(np.argmax(np.bincount(obs_image))))
    n = len(rotations)
    rot_sum, centre_sum, count = np.zeros((n, 3, 3)), np.zeros((n, 3)), np.zeros(n)
    param_sum = [np.zeros_like(np.asarray(p, float)) for p in camera_params]
    param_count = np.zeros(len(camera_params))
    points_out, iterations, success, converged, initial_sq = points.copy(), 0, True, True, 0.0
    last_decrease, initial_cost, final_cost, messages, stopped = 0.0, 0.0, 0.0, 0, []
    for k in range(num_parts):
        mask = part_of_point[obs_point] == k
        res = bundle_adjust(problem.observations(mask), options)
        observed = np.zeros(n, dtype=bool)
        observed[obs_image[mask]] = True
        rot_sum[observed] += res.rotations[observed]
        centre_sum[observed] += -np.einsum("nji,nj->ni", res.rotations[observed], res.translations[observed])
        count[observed] += 1
        for g in np.unique(image_camera[observed]):
            param_sum[g] += res.camera_params[g]
            param_count[g] += 1
        mine = part_of_point == k
        points_out[mine] = res.points[mine]
        iterations += res.iterations
        last_decrease = max(last_decrease, res.last_decrease)
        initial_sq += res.initial_rms**2 * res.num_observations
        initial_cost, final_cost = initial_cost + res.initial_cost, final_cost + res.final_cost
        messages += res.solver_messages
        stopped.append(res.stopped)
        success, converged = success and res.success, converged and res.converged
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug("BA part %d/%d: %d observations, RMS %.4f px, %d iterations, intrinsics %s", k + 1,
                         num_parts, int(mask.sum()), res.final_rms, res.iterations,
                         "; ".join(" ".join(f"{v:.6g}" for v in p) for p in res.camera_params))
        del res
        return_freed_memory()  # GTSAM's freed graph back to the system before the next part
    rot_out, trans_out = rotations.copy(), translations.copy()
    moved = (count > 0) & ~np.isin(np.arange(n), problem.fixed_poses)
    for i in np.flatnonzero(moved):
        rot_out[i] = project_to_so3(rot_sum[i] / count[i])  # the chordal L2 mean
        trans_out[i] = -rot_out[i] @ (centre_sum[i] / count[i])
    params_out = tuple(param_sum[g] / param_count[g] if param_count[g] else np.asarray(p, float).copy()
                       for g, p in enumerate(camera_params))
    sq_sum, err_sum = 0.0, 0.0
    for lo in range(0, len(obs_image), _ERROR_ROWS):  # in chunks: a rotation per row is 72 bytes
        part = slice(lo, lo + _ERROR_ROWS)
        err = reprojection_errors(camera_models, params_out, image_camera, rot_out, trans_out, obs_image[part],
                                  points_out[obs_point[part]], obs_xy[part])
        sq_sum, err_sum = sq_sum + float(np.sum(err**2)), err_sum + float(err.sum())
    return BAResult(rotations=rot_out, translations=trans_out, points=points_out, camera_params=params_out,
                    initial_rms=float(np.sqrt(initial_sq / len(obs_image))), final_rms=float(np.sqrt(sq_sum / len(obs_image))),
                    final_mean_error=err_sum / len(obs_image), iterations=iterations, time_s=time.perf_counter() - start,
                    num_observations=len(obs_image), success=success, converged=converged,
                    last_decrease=last_decrease, initial_cost=initial_cost, final_cost=final_cost,
                    stopped=_stop_reasons(stopped), solver_messages=messages)


def _stop_reasons(reasons: list[str]) -> str:
    """The parts' stop reasons in one line: each distinct one, with how many parts it stopped."""
    distinct = list(dict.fromkeys(reasons))
    if len(distinct) == 1:
        return f"{distinct[0]} (each of {len(reasons)} parts)"
    return "; ".join(f"{r} ({reasons.count(r)} of {len(reasons)} parts)" for r in distinct)
