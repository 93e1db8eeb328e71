"""Running GTSAM's Levenberg-Marquardt for :mod:`backend.bundle_adjustment`.

The solver plumbing shared by bundle adjustment and pose refinement: the robust measurement
noise (Huber, Cauchy or none on an isotropic 1 px sigma), the optimiser with its elimination
ordering ("points_first": every point eliminated first, the Schur ordering of BA; GTSAM's
METIS / COLAMD; "auto": points first for small problems, METIS for large ones), stopping rules and an iteration log, and running it with GTSAM's stdout
chatter sent to the debug log and a GTSAM error (e.g. an indeterminant system) turned into
"keep the input values". The options are those of :class:`backend.ba_problem.BAOptions`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import gtsam
import numpy as np

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


# Above this many factors "auto" orders by METIS: points first would hold a dense Hessian
# block per point over all its cameras, whose memory grows faster than METIS's fill.
AUTO_METIS_OBSERVATIONS = 100_000


def _configure(params, graph, values, options: BAOptions, history: list | None, name: str):
    """The options' ordering, tolerances and an iteration log (``history``, a list, receives
    each iteration's ``(cost before, cost after)``) on GTSAM optimiser ``params``."""
    if options.ordering not in ("auto", "points_first", "metis", "colamd"):
        raise ValueError(
            f"unknown ordering {options.ordering!r}; use 'auto', 'points_first', 'metis' or 'colamd'"
        )
    ordering_name = options.ordering
    if ordering_name == "auto":
        ordering_name = "metis" if graph.size() > AUTO_METIS_OBSERVATIONS else "points_first"
    if ordering_name == "points_first":
        # The classic BA ordering: eliminating every point first leaves the reduced camera
        # system (a Schur complement); no graph partitioning to compute.
        keys = np.array(values.keys(), dtype=np.uint64)
        is_point = (keys >> np.uint64(56)) == ord("l")  # a Symbol's character is its top byte
        params.setOrdering(gtsam.Ordering(np.concatenate([keys[is_point], keys[~is_point]]).tolist()))
    else:
        params.setOrderingType(ordering_name.upper())
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


def _run(optimizer, what: str):
    """``optimizer.optimize()`` with GTSAM's stdout sent to the log; a predicted convergence
    returns the values of the iteration that predicted it."""
    with _quiet_stdout(what):
        try:
            return optimizer.optimize()
        except PredictedConvergence:
            return optimizer.values()


def lm_optimizer(graph, values, options: BAOptions, history: list | None = None) -> gtsam.LevenbergMarquardtOptimizer:
    """Levenberg-Marquardt with the options' ordering, tolerances and an iteration log;
    ``history`` (a list) receives each iteration's ``(cost before, cost after)``."""
    params = _configure(gtsam.LevenbergMarquardtParams(), graph, values, options, history, "LM")
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params)


def gauss_newton_or_lm(graph, values: gtsam.Values, options: BAOptions, history: list,
                       what: str) -> tuple[gtsam.Values, bool, int, bool]:  # fmt: skip
    """Gauss-Newton while every step lowers the cost; otherwise (a step that raised it, or an
    indeterminant system) Levenberg-Marquardt from ``values`` again.  ``(result, success,
    iterations, converged)``: iterations of both, converged when the one that gave the result
    stopped before ``options.max_iterations``.  From a good start (a local BA after PnP and
    triangulation) Gauss-Newton takes the same steps as LM, whose damping and step control
    then only cost time; LM remains for starts where the quadratic model misleads (a young
    model's intrinsics)."""
    trial: list[tuple[float, float]] = []
    params = _configure(gtsam.GaussNewtonParams(), graph, values, options, trial, "Gauss-Newton")
    optimizer = gtsam.GaussNewtonOptimizer(graph, values, params)
    try:
        result = _run(optimizer, what)
        if all(after <= before for before, after in trial):
            history.extend(trial)
            return result, True, optimizer.iterations(), optimizer.iterations() < options.max_iterations
        logger.debug("%s: a Gauss-Newton step raised the cost; Levenberg-Marquardt instead", what)
    except RuntimeError as exc:
        logger.debug("%s: Gauss-Newton failed (%s); Levenberg-Marquardt instead", what, exc)
    lm = lm_optimizer(graph, values, options, history)
    result, success = optimize_or_keep(lm, values, what)
    return result, success, len(trial) + lm.iterations(), lm.iterations() < options.max_iterations


@contextlib.contextmanager
def _quiet_stdout(what: str):
    """Send what GTSAM's C++ code prints on stdout (GeneralSFMFactor prints a line per
    ``CheiralityException`` while LM tries a step that puts a point behind a camera) to the
    debug log instead of the caller's stdout, which may carry JSON."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            sink.seek(0)
            lines = sink.read().decode(errors="replace").splitlines()
            if lines:
                logger.debug("%s: GTSAM printed %d lines, e.g. %s", what, len(lines), lines[0])


def optimize_or_keep(optimizer, values: gtsam.Values, what: str) -> tuple[gtsam.Values, bool]:
    """Run the optimiser; on a GTSAM error (e.g. an indeterminant system) keep the input."""
    try:
        return _run(optimizer, what), True
    except RuntimeError as exc:
        logger.warning("%s failed: %s", what, exc)
        return values, False
