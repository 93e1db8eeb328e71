"""Running GTSAM's Levenberg-Marquardt for :mod:`backend.bundle_adjustment`.

The solver plumbing shared by bundle adjustment and pose refinement: the robust measurement
noise (Huber, Cauchy or none on an isotropic 1 px sigma), the optimiser with its elimination
ordering ("points_first": every point eliminated first, the Schur ordering of BA;
"points_then_metis": the same with the cameras in METIS's order of their co-visibility graph;
GTSAM's METIS / COLAMD; "auto": the first for small problems, the second for large ones),
stopping rules,
an iteration log and why the optimiser stopped; a GTSAM error (e.g. an indeterminant system)
turned into "keep the input values"; and what GTSAM's C++ code prints on stdout counted and
sent to the debug log, never to the terminal (:func:`captured_stdout`).  The options are those
of :class:`backend.ba_problem.BAOptions`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X
from scipy import sparse

from backend.ba_problem import BAOptions

# The messages are bundle adjustment's: they keep its logger name (and its log configuration).
logger = logging.getLogger("backend.bundle_adjustment")


def robust_noise(loss: str, scale: float, sigma: float = 1.0) -> gtsam.noiseModel.Base:
    """Isotropic ``sigma`` px measurement noise wrapped in the robust loss, whose ``scale``
    applies to the whitened error (``scale * sigma`` pixels)."""
    base = gtsam.noiseModel.Isotropic.Sigma(2, float(sigma))
    estimators = {
        "huber": gtsam.noiseModel.mEstimator.Huber,
        "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
    }
    if loss == "none":
        return base
    if loss not in estimators:
        raise ValueError(f"unknown loss {loss!r}; use 'huber', 'cauchy' or 'none'")
    return gtsam.noiseModel.Robust.Create(estimators[loss].Create(scale), base)


# Above this many factors "auto" orders "points_then_metis", below it "points_first": ordering
# the cameras costs more than it saves on a local BA's few cameras.
AUTO_METIS_OBSERVATIONS = 100_000
ORDERINGS = ("auto", "points_first", "points_then_metis", "metis", "colamd")


def _is_point(keys: np.ndarray) -> np.ndarray:
    return (keys >> np.uint64(56)) == ord("l")  # a Symbol's character is its top byte


def resolve_ordering(name: str, num_factors: int) -> str:
    """The ordering ``name`` stands for on a graph of ``num_factors`` factors ("auto" resolved)."""
    if name not in ORDERINGS:
        raise ValueError(f"unknown ordering {name!r}; use one of {', '.join(ORDERINGS)}")
    if name == "auto":
        return "points_then_metis" if num_factors > AUTO_METIS_OBSERVATIONS else "points_first"
    return name


def elimination_ordering(name: str, graph, values: gtsam.Values, camera_pairs: np.ndarray | None = None,
                         last: tuple[int, ...] = ()) -> gtsam.Ordering | None:
    """The elimination ordering ``name`` (:class:`backend.ba_problem.BAOptions`) of ``graph``
    as a GTSAM ``Ordering`` with ``last`` (keys) at its end; None for GTSAM's own "metis" and
    "colamd" (which do not take ``last``).  "points_then_metis" needs ``camera_pairs`` (E, 2):
    the keys of every two pose variables that see a common point, the structure of the reduced
    camera system (Schur complement); the poses are ordered by METIS's nested dissection of that
    graph, the other non-point variables (calibrations) after them."""
    name = resolve_ordering(name, graph.size())
    if name in ("metis", "colamd"):
        return None
    keys = np.array(values.keys(), dtype=np.uint64)
    point = _is_point(keys)
    at_end = set(last)
    rest = [k for k in keys[~point].tolist() if k not in at_end]
    if name == "points_then_metis" and camera_pairs is not None and len(camera_pairs):
        structure = gtsam.SymbolicFactorGraph()
        for a, b in np.asarray(camera_pairs, np.uint64).tolist():
            structure.push_factor(a, b)
        metis = gtsam.Ordering.MetisSymbolicFactorGraph(structure)
        poses = [k for k in (metis.at(i) for i in range(metis.size())) if k not in at_end]
        placed = set(poses)
        rest = poses + [k for k in rest if k not in placed]
    return gtsam.Ordering(keys[point].tolist() + rest + list(last))


def covisible_pose_keys(obs_image: np.ndarray, obs_point: np.ndarray, pose_variables: np.ndarray,
                        num_images: int, num_points: int) -> np.ndarray | None:
    """The keys ``(X(i), X(j))``, i < j, of every two images among ``pose_variables`` that see a
    common point (observation arrays as in :class:`backend.ba_problem.BAProblem`): the
    structure of the reduced camera system, which "points_then_metis" orders
    (:func:`elimination_ordering`); None when no two share a point."""
    obs_image, obs_point = np.asarray(obs_image, np.int64), np.asarray(obs_point, np.int64)
    variable = np.zeros(num_images, dtype=bool)
    variable[np.asarray(pose_variables, np.int64)] = True
    rows = variable[obs_image]
    seen = sparse.csr_matrix((np.ones(int(rows.sum()), np.float32), (obs_point[rows], obs_image[rows])),
                             shape=(num_points, num_images))
    covisible = sparse.triu(seen.T @ seen, k=1).tocoo()
    if not covisible.nnz:
        return None
    return np.uint64(X(0)) + np.stack([covisible.row, covisible.col], axis=1).astype(np.uint64)  # X(i) = X(0) + i


def _configure(params, graph, values, options: BAOptions, history: list | None, name: str,
               camera_pairs: np.ndarray | None = None):
    """The options' ordering (:func:`elimination_ordering`), tolerances and an iteration log
    (``history``, a list, receives each iteration's ``(cost before, cost after)``) on GTSAM
    optimiser ``params``."""
    ordering = elimination_ordering(options.ordering, graph, values, camera_pairs)
    if ordering is None:
        params.setOrderingType(resolve_ordering(options.ordering, graph.size()).upper())
    else:
        params.setOrdering(ordering)
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_tolerance)
    params.setAbsoluteErrorTol(options.absolute_tolerance)
    level = logging.INFO if options.verbose else logging.DEBUG

    decreases: list[float] = []

    def hook(iteration: int, before: float, after: float) -> None:
        logger.log(level, "%s iteration %d: cost %.6g -> %.6g", name, iteration, before, after)
        if history is not None:
            history.append((before, after))
        if options.on_iteration is not None:
            options.on_iteration(iteration, before, after)
        decreases.append((before - after) / before if before > 0 else 0.0)
        if options.predictive_stop and predicted_rest(decreases) < options.relative_tolerance:
            raise PredictedConvergence  # the optimiser holds this iteration's values

    params.iterationHook = hook
    return params


class PredictedConvergence(Exception):
    """Raised by the iteration hook to stop an optimiser whose next decreases are predicted
    below the relative tolerance (``BAOptions.predictive_stop``)."""


def predicted_rest(decreases: list[float]) -> float:
    """The relative cost decrease still to come, predicted from the last two iterations'
    relative decreases as a geometric series (``d_k r / (1 - r)``, ``r = d_k / d_(k-1)``);
    infinite until two iterations have lowered the cost at a shrinking rate."""
    if len(decreases) < 2 or decreases[-2] <= 0 or decreases[-1] < 0:
        return float("inf")
    rate = decreases[-1] / decreases[-2]
    return decreases[-1] * rate / (1.0 - rate) if rate < 1.0 else float("inf")


def _run(optimizer) -> tuple[gtsam.Values, bool]:
    """``optimizer.optimize()``; a predicted convergence returns the values of the iteration
    that predicted it.  ``(values, whether the prediction stopped it)``."""
    try:
        return optimizer.optimize(), False
    except PredictedConvergence:
        return optimizer.values(), True


def lm_optimizer(graph, values, options: BAOptions, history: list | None = None,
                 camera_pairs: np.ndarray | None = None) -> gtsam.LevenbergMarquardtOptimizer:
    """Levenberg-Marquardt with the options' ordering, tolerances and an iteration log;
    ``history`` (a list) receives each iteration's ``(cost before, cost after)``."""
    params = _configure(gtsam.LevenbergMarquardtParams(), graph, values, options, history, "LM", camera_pairs)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params)


@dataclass
class SolverRun:
    """What an optimiser run gave: the values (the input's where it failed), whether it ran
    without a GTSAM error, its iterations, whether it stopped before ``max_iterations``, and why
    it stopped (:func:`stop_reason`)."""

    values: gtsam.Values
    success: bool
    iterations: int
    converged: bool
    stopped: str


def stop_reason(history: list[tuple[float, float]], iterations: int, options: BAOptions, predicted: bool,
                failure: str | None = None) -> str:
    """Why an optimiser stopped, in words, from its iteration log: GTSAM's rules (maximum
    iterations; the last decrease below the absolute or relative tolerance), the predicted
    convergence of ``BAOptions.predictive_stop``, a GTSAM error (``failure``), or no iteration
    lowering the cost (Levenberg-Marquardt's damping reached its bound)."""
    if failure is not None:
        return f"GTSAM error, input kept: {failure}"
    if predicted:
        return f"predicted decrease below relative tolerance {options.relative_tolerance:g}"
    if iterations >= options.max_iterations:
        return f"maximum iterations ({options.max_iterations})"
    if not history:
        return "no step lowered the cost"
    before, after = history[-1]
    if before - after <= options.absolute_tolerance:
        return f"decrease below absolute tolerance {options.absolute_tolerance:g}"
    if before - after <= options.relative_tolerance * before:
        return f"relative decrease below tolerance {options.relative_tolerance:g}"
    return "no step lowered the cost"


def solve(graph, values: gtsam.Values, options: BAOptions, history: list, what: str,
          camera_pairs: np.ndarray | None = None) -> SolverRun:
    """The optimiser ``options.optimizer`` names ("lm" or "gauss_newton_or_lm") on ``graph``
    from ``values``; ``history`` receives each iteration's ``(cost before, cost after)``;
    ``camera_pairs``: see :func:`elimination_ordering`.  Call it inside
    :func:`captured_stdout`: GTSAM prints while it evaluates factors."""
    if options.optimizer == "gauss_newton_or_lm":
        return _gauss_newton_or_lm(graph, values, options, history, what, camera_pairs)
    if options.optimizer != "lm":
        raise ValueError(f"unknown optimizer {options.optimizer!r}; use 'lm' or 'gauss_newton_or_lm'")
    return _lm(graph, values, options, history, what, 0, camera_pairs)


def _lm(graph, values: gtsam.Values, options: BAOptions, history: list, what: str, earlier: int,
        camera_pairs: np.ndarray | None = None) -> SolverRun:
    """Levenberg-Marquardt from ``values``; ``earlier``: iterations already spent (by
    Gauss-Newton) that count in the result.  A GTSAM error (e.g. an indeterminant system)
    keeps the input values."""
    optimizer = lm_optimizer(graph, values, options, history, camera_pairs)
    try:
        result, predicted = _run(optimizer)
    except RuntimeError as exc:
        logger.warning("%s failed: %s", what, exc)
        return SolverRun(values, False, earlier + optimizer.iterations(), False,
                         stop_reason(history, optimizer.iterations(), options, False, str(exc)))
    return SolverRun(result, True, earlier + optimizer.iterations(), optimizer.iterations() < options.max_iterations,
                     stop_reason(history, optimizer.iterations(), options, predicted))


def _gauss_newton_or_lm(graph, values: gtsam.Values, options: BAOptions, history: list, what: str,
                        camera_pairs: np.ndarray | None = None) -> SolverRun:
    """Gauss-Newton while every step lowers the cost; otherwise (a step that raised it, or an
    indeterminant system) Levenberg-Marquardt from ``values`` again, its iterations counted
    with Gauss-Newton's.  From a good start (a local BA after PnP and triangulation)
    Gauss-Newton takes the same steps as LM, whose damping and step control then only cost
    time; LM remains for starts where the quadratic model misleads (a young model's
    intrinsics)."""
    trial: list[tuple[float, float]] = []
    params = _configure(gtsam.GaussNewtonParams(), graph, values, options, trial, "Gauss-Newton", camera_pairs)
    optimizer = gtsam.GaussNewtonOptimizer(graph, values, params)
    try:
        result, predicted = _run(optimizer)
        if all(after <= before for before, after in trial):
            history.extend(trial)
            return SolverRun(result, True, optimizer.iterations(), optimizer.iterations() < options.max_iterations,
                             stop_reason(trial, optimizer.iterations(), options, predicted))
        logger.debug("%s: a Gauss-Newton step raised the cost; Levenberg-Marquardt instead", what)
    except RuntimeError as exc:
        logger.debug("%s: Gauss-Newton failed (%s); Levenberg-Marquardt instead", what, exc)
    return _lm(graph, values, options, history, what, len(trial), camera_pairs)


@dataclass
class SolverOutput:
    """What GTSAM's C++ code printed on stdout inside :func:`captured_stdout`: the number of
    lines and the first of them."""

    lines: int = 0
    first: str = ""


_capturing: list[SolverOutput] = []  # the outermost capture active in this process, if any


@contextlib.contextmanager
def captured_stdout(what: str):
    """Send what GTSAM's C++ code prints on stdout (``GeneralSFMFactor`` prints a line per
    ``CheiralityException`` whenever it evaluates a point behind a camera: while LM tries a
    step, and while a cost is computed) to a :class:`SolverOutput` and the debug log instead of
    the terminal or the caller's stdout, which may carry JSON.  Nested captures add to the
    outermost one."""
    if _capturing:
        yield _capturing[0]
        return
    output = SolverOutput()
    _capturing.append(output)
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 1)
            try:
                yield output
            finally:
                os.dup2(saved, 1)
                sink.seek(0)
                lines = sink.read().decode(errors="replace").splitlines()
                output.lines, output.first = len(lines), lines[0] if lines else ""
                if lines:
                    logger.debug("%s: GTSAM printed %d lines, e.g. %s", what, len(lines), lines[0])
    finally:
        os.close(saved)
        _capturing.clear()
