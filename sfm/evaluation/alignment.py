"""Robust Sim3 alignment of estimated camera centres onto ground-truth ones.

A reconstruction is only defined up to a similarity, so absolute pose errors are measured after
a ``gt_from_est`` :class:`~backend.sim3.Sim3` with ``gt_centers ≈ sim.apply(est_centers)``,
estimated on camera centres by RANSAC over 3-point Umeyama fits with MSAC scoring and local
refinement (:func:`align_centers`), so a minority of badly placed cameras does not bias it.

Also here: the inlier threshold's default (:func:`default_alignment_threshold`, a fraction of the
GT centres' robust spread), the scene extent that centre errors are divided by
(:func:`scene_extent`, the largest distance between two centres) and the collinearity test that
flags an alignment whose roll about the centres' line is undetermined (:func:`is_collinear`).

The library does no printing; it logs through ``logging.getLogger(__name__)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from itertools import combinations

import numpy as np

from backend.geometry import project_to_so3
from backend.sim3 import Sim3, umeyama

logger = logging.getLogger(__name__)

#: Default RANSAC inlier threshold, as a fraction of the GT centres' robust spread (see
#: :func:`default_alignment_threshold`).
DEFAULT_ALIGNMENT_FRACTION = 0.05


def scene_extent(centers: np.ndarray) -> float:
    """Largest distance between two of the given centres (0 for fewer than two); O(N^2) work
    in row blocks, so memory stays small for thousands of cameras.

    Centre errors are divided by it: rotation invariant, unlike a bounding-box diagonal, and
    ``2 r`` for a ring of radius r.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    if len(c) < 2:
        return 0.0
    c = c - c.mean(axis=0)
    sq = np.sum(c * c, axis=1)
    best = 0.0
    step = max(1, 2_000_000 // len(c))
    for start in range(0, len(c), step):
        block = c[start : start + step]
        d2 = sq[start : start + step, None] + sq[None, :] - 2.0 * block @ c.T
        best = max(best, float(d2.max()))
    return math.sqrt(max(best, 0.0))


def default_alignment_threshold(gt_centers: np.ndarray) -> float:
    """``DEFAULT_ALIGNMENT_FRACTION`` (5%) of the median distance of the GT centres to their
    coordinate-wise median.

    That spread is robust (a minority of odd GT cameras does not change it) and is the scene
    radius for cameras around an object; a centre off by 5% of the radius is seen from the scene
    centre about 3 degrees away, the scale of the AUC@5 metric.  When more than half of the
    centres coincide, the mean distance is used instead.
    """
    c = np.asarray(gt_centers, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        return 0.0
    dist = np.linalg.norm(c - np.median(c, axis=0), axis=1)
    spread = float(np.median(dist))
    if spread <= 0.0:
        spread = float(dist.mean())
    return DEFAULT_ALIGNMENT_FRACTION * spread


def _msac(sim: Sim3, est: np.ndarray, gt: np.ndarray, threshold: float) -> tuple[float, np.ndarray]:
    residuals = np.linalg.norm(sim.apply(est) - gt, axis=1)
    cost = float(np.minimum(residuals, threshold) @ np.minimum(residuals, threshold))
    return cost, residuals <= threshold


def _refine(sim: Sim3, est: np.ndarray, gt: np.ndarray, threshold: float, max_rounds: int = 20):
    """Refit on the inliers while the truncated cost does not grow (local optimisation)."""
    cost, mask = _msac(sim, est, gt, threshold)
    for _ in range(max_rounds):
        if mask.sum() < 3:
            break
        new_sim = umeyama(est[mask], gt[mask])
        new_cost, new_mask = _msac(new_sim, est, gt, threshold)
        if new_cost > cost:
            break
        sim, cost = new_sim, new_cost
        if np.array_equal(new_mask, mask):
            break
        mask = new_mask
    return sim, cost, mask


def align_centers(
    est_centers: np.ndarray,
    gt_centers: np.ndarray,
    threshold: float | None = None,
    seed: int = 0,
    max_iterations: int = 2000,
    confidence: float = 0.9999,
) -> tuple[Sim3 | None, np.ndarray]:
    """Robust similarity ``gt_from_est`` with ``gt_centers ≈ sim.apply(est_centers)``.

    RANSAC over minimal 3-point samples fitted by Umeyama, scored by the truncated quadratic
    (MSAC) cost; every new best hypothesis is refined by Umeyama refits on its inliers.  When
    ``C(N, 3) <= max_iterations`` all triples are tried (in order), otherwise samples are drawn
    from ``numpy.random.default_rng(seed)`` with the usual adaptive stopping at ``confidence``;
    either way the result is deterministic, and exact (to rounding) for noise-free input.

    ``threshold`` is the inlier distance in GT units (default: :func:`default_alignment_threshold`,
    5% of the robust spread of ``gt_centers``).  Returns ``(sim, inlier_mask)``.

    * ``N < 3``: ``(None, all-False mask)``; two centres fix a similarity only up to a rotation
      about their baseline, so none is returned.
    * ``N == 3``: the single sample is all points, i.e. plain Umeyama on the three.
    * Collinear centres (or inliers): a best fit is still returned; its rotation about the line is
      not determined by the centres (Umeyama's SVD picks one), so rotation errors measured after
      such an alignment include that arbitrary roll.  :func:`sfm.evaluation.metrics.evaluate` flags the
      case.
    """
    est = np.asarray(est_centers, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_centers, dtype=np.float64).reshape(-1, 3)
    if est.shape != gt.shape:
        raise ValueError(f"align_centers: {est.shape} estimated vs {gt.shape} GT centres")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(gt))):
        raise ValueError("align_centers: non-finite centres")
    n = len(est)
    if n < 3:
        return None, np.zeros(n, dtype=bool)
    if threshold is None:
        threshold = default_alignment_threshold(gt)
    threshold = float(threshold)

    best_sim, best_cost, best_mask = None, math.inf, np.zeros(n, dtype=bool)
    exhaustive = math.comb(n, 3) <= max_iterations
    if exhaustive:
        samples: Iterator = (np.array(s) for s in combinations(range(n), 3))
    else:
        rng = np.random.default_rng(seed)
        samples = (rng.choice(n, 3, replace=False) for _ in range(max_iterations))
    needed = max_iterations
    for iteration, sample in enumerate(samples):
        if iteration >= needed:
            break
        sim = umeyama(est[sample], gt[sample])
        cost, _ = _msac(sim, est, gt, threshold)
        if cost >= best_cost:
            continue
        best_sim, best_cost, best_mask = _refine(sim, est, gt, threshold)
        inlier_ratio = best_mask.mean()
        if inlier_ratio >= 1.0:
            break
        if not exhaustive and inlier_ratio > 0:
            trials = math.log(1 - confidence) / math.log(1 - inlier_ratio**3)
            needed = min(max_iterations, int(math.ceil(trials)))
    logger.debug("align_centers: %d/%d inliers at threshold %.4g", best_mask.sum(), n, threshold)
    return best_sim, best_mask


def is_collinear(points: np.ndarray, tol: float = 1e-3) -> bool:
    """True when the points' second principal spread is below ``tol`` of the first."""
    if len(points) < 3:
        return True
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(sv[0] == 0 or sv[1] <= tol * sv[0])


def _log_so3(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotations (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


def _exp_so3(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def rotation_median(rotations: np.ndarray, iterations: int = 100) -> np.ndarray:
    """Geodesic L1 median of rotations (N, 3, 3): Weiszfeld on SO(3) from the chordal mean,
    compared with the best data point (the median of a majority of identical rotations is that
    rotation exactly, which Weiszfeld only approaches)."""
    def cost(r):
        return np.linalg.norm(_log_so3(np.einsum("ij,njk->nik", r.T, rotations)), axis=1).sum()

    est = project_to_so3(rotations.sum(axis=0))
    for _ in range(iterations):
        w = _log_so3(np.einsum("ij,njk->nik", est.T, rotations))
        d = np.linalg.norm(w, axis=1)
        keep = d > 1e-12
        if not keep.any():
            break
        step = (w[keep] / d[keep, None]).sum(0) / (1.0 / d[keep]).sum()
        est = est @ _exp_so3(step[None])[0]
        if np.linalg.norm(step) < 1e-13:
            break
    best = min(range(len(rotations)), key=lambda k: cost(rotations[k]))
    return rotations[best] if cost(rotations[best]) <= cost(est) else est


def refine_rotation_with_orientations(sim: Sim3, est_rot: np.ndarray, gt_rot: np.ndarray,
                                      est_c: np.ndarray, gt_c: np.ndarray, inliers: np.ndarray) -> Sim3:
    """Re-estimate the rotation of ``gt_from_est`` from the inlier cameras' orientations, then
    scale and translation from their centres with that rotation fixed.

    Camera centres alone leave the rotation about their line undetermined when they are close to
    collinear (cameras along a short arc or a street): the roll about that line is then fixed
    only by the centres' small spread across it, so a tiny centre error becomes a rotation error
    of every image, larger the thinner the spread.  Each orientation
    gives the alignment rotation directly (``R_gt^T R_est``); their geodesic median is robust to
    a few wrong cameras.  Centres still select the inliers.
    """
    idx = np.flatnonzero(inliers)
    if len(idx) == 0:
        return sim
    rotation = rotation_median(np.einsum("nji,njk->nik", gt_rot[idx], est_rot[idx]))
    a = est_c[idx] - est_c[idx].mean(0)
    b = gt_c[idx] - gt_c[idx].mean(0)
    ra = a @ rotation.T
    denom = float((ra * ra).sum())
    scale = float((ra * b).sum() / denom) if denom > 0 else sim.scale
    translation = gt_c[idx].mean(0) - scale * rotation @ est_c[idx].mean(0)
    return Sim3(scale, rotation, translation)
