"""Evaluation of a reconstruction against ground-truth camera poses.

Poses are ``cam_from_world`` (centre ``C = -R.T @ t``) and images are matched to ground truth by
name, as in :mod:`sfm.evaluation.ground_truth` (which reads GT tables and models); an image counts as
registered when it is in the reconstruction and ``Image.registered``.

Metrics (the project's one rule for pose accuracy, used by ``graphsfm evaluate``, the tests and
the benchmarks alike):

* Registration: registered GT images / GT images.
* Absolute errors, after the robust Sim3 ``gt_from_est`` (:func:`sfm.evaluation.alignment.align_centers`
  picks inliers, scale and translation from camera centres; the rotation is the geodesic median
  of the inliers' orientation offsets, :func:`~sfm.evaluation.alignment.refine_rotation_with_orientations`):
  per image, the angle of ``R_est @ R_align.T @ R_gt.T`` in degrees, and ``|sim(C_est) - C_gt|``
  divided by the :func:`~sfm.evaluation.alignment.scene_extent` of the GT centres.
* Relative-pose AUC (alignment free): for every GT pair ``i < j`` the relative pose
  ``cam_j_from_cam_i = (R_j R_i^T, t_j - R_j R_i^T t_i)`` of the estimate is compared with the GT
  one; the pair error is ``max(rotation error, angle between the translation directions)`` in
  degrees, infinite when either image is unregistered.  ``AUC@X`` is the pose AUC of SuperGlue /
  LightGlue / hloc (:func:`auc`): area under the recall-vs-error curve up to X, divided by X.

Angles use ``atan2`` forms (never ``arccos`` of a dot product): identical rotations or parallel
directions give errors at the 1e-14 degree level, not 1e-6.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from sfm.evaluation.alignment import align_centers, default_alignment_threshold, is_collinear, scene_extent
from sfm.evaluation.alignment import refine_rotation_with_orientations
from backend.geometry import rotation_angle_deg, rotation_to_quaternion
from backend.sim3 import Sim3
from sfm.evaluation.ground_truth import GTPose
from sfm.core.model import Reconstruction

logger = logging.getLogger(__name__)

DEFAULT_AUC_THRESHOLDS = (1.0, 5.0, 10.0)
_PAIRS_PER_BLOCK = 500_000  # pairs per block: ~20 live float64 arrays of this size, ~80 MB


# ---------------------------------------------------------------------------------- pose errors
def _pair_error_blocks(
    est_rotations: np.ndarray,
    est_centers: np.ndarray,
    gt_rotations: np.ndarray,
    gt_centers: np.ndarray,
    registered: np.ndarray,
    pairs_per_block: int = _PAIRS_PER_BLOCK,
) -> Iterator[np.ndarray]:
    """Yield the errors of pairs ``i < j`` in ``np.triu_indices(N, 1)`` order, block by block.

    Rotation: with ``D_k = R_gt_k^T R_est_k`` the relative rotation error is the angle of
    ``D_j D_i^T``; with ``q_k`` the unit quaternion of ``D_k`` it is
    ``4 atan2(min(|q_i - q_j|, |q_i + q_j|), max(...))`` (accurate at every angle).
    Translation: ``t_ji = t_j - R_j R_i^T t_i = R_j (C_i - C_j)``, so the angle between the
    estimated and GT directions is the one between ``C_est_i - C_est_j`` and
    ``M_j (C_gt_i - C_gt_j)`` with ``M_j = R_est_j^T R_gt_j``, taken as ``atan2(|u x v|, u . v)``.
    A zero GT baseline has no direction (only the rotation counts); a zero estimated baseline
    against a non-zero GT one counts as 90 degrees.  Blocks are rows ``i`` against all later
    columns, computed component-wise on (rows, cols) arrays.
    """
    n = len(registered)
    if n < 2:
        return
    d = np.einsum("nki,nkj->nij", gt_rotations, est_rotations)
    q = np.stack([rotation_to_quaternion(dk) for dk in d])  # (n, 4)
    m = np.einsum("nki,nkj->nij", est_rotations, gt_rotations)
    ce = est_centers - (est_centers[registered].mean(axis=0) if registered.any() else 0.0)
    cg = gt_centers - gt_centers.mean(axis=0)
    m_cg = np.einsum("nkl,nl->nk", m, cg)  # M_j C_gt_j
    m_rows_t = [np.ascontiguousarray(m[:, k, :].T) for k in range(3)]  # row k of every M_j, (3, n)
    gt_dups = len(np.unique(cg, axis=0)) < n
    est_dups = len(np.unique(ce[registered], axis=0)) < registered.sum()
    rows_per_block = max(1, pairs_per_block // n)
    for start in range(0, n - 1, rows_per_block):
        stop = min(n - 1, start + rows_per_block)
        rows, cols = slice(start, stop), slice(start + 1, n)
        dq2 = sum((q[rows, k, None] - q[None, cols, k]) ** 2 for k in range(4))
        sq2 = np.maximum(4.0 - dq2, 0.0)
        small, large = np.sqrt(np.minimum(dq2, sq2)), np.sqrt(np.maximum(dq2, sq2))
        rot_err = np.degrees(4.0 * np.arctan2(small, large))
        del small, large
        del sq2
        u = [ce[rows, k, None] - ce[None, cols, k] for k in range(3)]
        v = [cg[rows] @ m_rows_t[k][:, cols] - m_cg[None, cols, k] for k in range(3)]
        cross2 = (u[1] * v[2] - u[2] * v[1]) ** 2
        cross2 += (u[2] * v[0] - u[0] * v[2]) ** 2
        cross2 += (u[0] * v[1] - u[1] * v[0]) ** 2
        dot = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
        trans_err = np.degrees(np.arctan2(np.sqrt(cross2), dot))
        del cross2, dot
        if gt_dups:
            gt_zero = np.logical_and.reduce(
                [cg[rows, k, None] == cg[None, cols, k] for k in range(3)]
            )
            trans_err[gt_zero] = 0.0
        if est_dups:
            est_zero = (u[0] == 0) & (u[1] == 0) & (u[2] == 0)
            if gt_dups:
                est_zero &= ~gt_zero
            trans_err[est_zero] = 90.0
        err = np.maximum(rot_err, trans_err)
        err[~(registered[rows, None] & registered[None, cols])] = np.inf
        # row start + b pairs with columns j >= start + b + 1, i.e. column index >= b
        upper = np.arange(n - start - 1)[None, :] >= np.arange(stop - start)[:, None]
        yield err[upper]


def _prepare_poses(rotations, translations, registered):
    rot = np.array(rotations, dtype=np.float64).reshape(-1, 3, 3)
    trans = np.array(translations, dtype=np.float64).reshape(-1, 3)
    reg = np.ones(len(rot), dtype=bool)
    if registered is not None:
        reg &= np.asarray(registered, dtype=bool)
    reg &= np.all(np.isfinite(rot.reshape(len(rot), 9)), axis=1)
    reg &= np.all(np.isfinite(trans), axis=1)
    rot[~reg] = np.eye(3)
    trans[~reg] = 0.0
    return rot, np.einsum("nki,nk->ni", rot, -trans), reg


def relative_pose_errors(
    est_rotations: np.ndarray,
    est_translations: np.ndarray,
    gt_rotations: np.ndarray,
    gt_translations: np.ndarray,
    registered: np.ndarray | None = None,
) -> np.ndarray:
    """Errors (degrees) of all pairs ``i < j`` in ``np.triu_indices(N, 1)`` order.

    Inputs are ``cam_from_world`` stacks (N, 3, 3) and (N, 3), row k of the estimate and the GT
    being the same image.  The pair error is ``max(relative rotation error, angle between the
    relative translation directions)`` of ``cam_j_from_cam_i``; ``inf`` when image i or j is not
    registered (``registered[k]`` False or a non-finite estimated pose).  The result holds
    N(N-1)/2 floats: for thousands of images use :func:`evaluate`, which streams the pairs.
    """
    rot_e, c_e, reg = _prepare_poses(est_rotations, est_translations, registered)
    rot_g, c_g, _ = _prepare_poses(gt_rotations, gt_translations, None)
    if rot_e.shape != rot_g.shape:
        raise ValueError(f"relative_pose_errors: {len(rot_e)} estimated vs {len(rot_g)} GT poses")
    blocks = list(_pair_error_blocks(rot_e, c_e, rot_g, c_g, reg))
    return np.concatenate(blocks) if blocks else np.zeros(0)


# ---------------------------------------------------------------------------------- AUC
class _AucAccumulator:
    """Pose AUC from errors given in any order and in chunks, without sorting or storing them.

    For the ``m`` errors ``e_1 <= ... <= e_m`` below X out of N, the trapezoid area of the
    recall curve ``(0,0), (e_k, k/N), ..., (X, m/N)`` telescopes to
    ``(m X - sum e_k) / N + e_m / (2 N)``: only the count, the sum and the largest error below
    each threshold are needed.
    """

    def __init__(self, thresholds: Sequence[float]):
        self.thresholds = [float(t) for t in thresholds]
        if any(not t > 0 for t in self.thresholds):
            raise ValueError(f"AUC thresholds must be positive, got {self.thresholds}")
        k = len(self.thresholds)
        self.count, self.sum, self.largest = np.zeros(k, dtype=np.int64), np.zeros(k), np.zeros(k)
        self.total = 0

    def add(self, errors: np.ndarray) -> None:
        e = np.asarray(errors, dtype=np.float64).ravel()
        self.total += len(e)
        if not self.thresholds:
            return
        e = e[e < max(self.thresholds)]  # drops inf and NaN too
        for k, t in enumerate(self.thresholds):
            below = e[e < t]
            if len(below):
                self.count[k] += len(below)
                self.sum[k] += below.sum()
                self.largest[k] = max(self.largest[k], below.max())

    def result(self) -> list[float]:
        if self.total == 0:
            return [math.nan for _ in self.thresholds]
        n = self.total
        return [
            float(((self.count[k] * t - self.sum[k]) / n + self.largest[k] / (2 * n)) / t)
            for k, t in enumerate(self.thresholds)
        ]


def auc(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] = DEFAULT_AUC_THRESHOLDS) -> list[float]:
    """Pose AUC of SuperGlue / LightGlue / hloc: for each threshold X, the area under the recall
    curve (errors sorted, recall ``(i+1)/N``, ``(0, 0)`` prepended, clipped at X) by trapezoids,
    divided by X.  Errors equal to X do not count; ``inf`` and NaN errors count as failures.
    Returns NaN for every threshold when ``errors`` is empty.
    """
    acc = _AucAccumulator(thresholds)
    acc.add(errors)
    return acc.result()


# ---------------------------------------------------------------------------------- evaluate
def _finite_or_none(x):
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Metrics of a reconstruction against GT (see the module docstring for definitions).

    * ``num_registered``: GT images registered in the model; ``registered_ratio`` = that / GT.
    * ``alignment``: the Sim3 ``gt_from_est`` of :func:`align_centers` (None below 3 registered
      GT images: then the absolute-error fields are NaN and the per-image dicts empty);
      ``alignment_degenerate``: its inlier GT centres are (nearly) collinear (second singular
      value below 1e-3 of the first), so the roll about that line, and with it the absolute
      rotation errors, are not determined by the centres.
    * ``rotation_errors_deg`` / ``center_errors``: per registered GT image, by name; centre
      errors are relative to ``scene_extent`` (largest distance between two GT centres).
    * ``auc``: AUC in [0, 1] by threshold in degrees, over all ``num_pairs`` GT pairs.
    """

    num_gt_images: int
    num_registered: int
    registered_ratio: float
    num_registered_not_in_gt: int
    num_points: int
    mean_track_length: float
    mean_reprojection_error: float
    scene_extent: float
    alignment: Sim3 | None
    alignment_threshold: float
    num_alignment_inliers: int
    alignment_degenerate: bool
    rotation_errors_deg: dict[str, float] = field(default_factory=dict)
    center_errors: dict[str, float] = field(default_factory=dict)
    median_rotation_error_deg: float = math.nan
    mean_rotation_error_deg: float = math.nan
    median_center_error: float = math.nan
    mean_center_error: float = math.nan
    num_pairs: int = 0
    auc: dict[float, float] = field(default_factory=dict)

    def to_dict(self, per_image: bool = True) -> dict:
        """JSON-ready dict (NaN/inf become None; AUC keys ``"auc@1"``...)."""
        out: dict = {
            "num_gt_images": self.num_gt_images,
            "num_registered": self.num_registered,
            "registered_ratio": _finite_or_none(self.registered_ratio),
            "num_registered_not_in_gt": self.num_registered_not_in_gt,
            "num_points": self.num_points,
            "mean_track_length": _finite_or_none(self.mean_track_length),
            "mean_reprojection_error": _finite_or_none(self.mean_reprojection_error),
            "scene_extent": _finite_or_none(self.scene_extent),
            "alignment": None,
            "alignment_threshold": _finite_or_none(self.alignment_threshold),
            "num_alignment_inliers": self.num_alignment_inliers,
            "alignment_degenerate": self.alignment_degenerate,
            "median_rotation_error_deg": _finite_or_none(self.median_rotation_error_deg),
            "mean_rotation_error_deg": _finite_or_none(self.mean_rotation_error_deg),
            "median_center_error": _finite_or_none(self.median_center_error),
            "mean_center_error": _finite_or_none(self.mean_center_error),
            "num_pairs": self.num_pairs,
        }
        if self.alignment is not None:
            out["alignment"] = {
                "scale": float(self.alignment.scale),
                "rotation_qvec": rotation_to_quaternion(self.alignment.rotation).tolist(),
                "translation": np.asarray(self.alignment.translation, dtype=float).tolist(),
            }
        for t, value in self.auc.items():
            out[f"auc@{t:g}"] = _finite_or_none(value)
        if per_image:
            for key in ("rotation_errors_deg", "center_errors"):
                out[key] = {k: _finite_or_none(v) for k, v in getattr(self, key).items()}
        return out


def evaluate(
    recon: Reconstruction,
    gt: dict[str, GTPose],
    seed: int = 0,
    *,
    alignment_threshold: float | None = None,
    auc_thresholds: Sequence[float] = DEFAULT_AUC_THRESHOLDS,
) -> EvaluationResult:
    """Compare ``recon`` with ``gt`` (GT poses by image name); see the module docstring.

    ``alignment_threshold`` (GT units) defaults to :func:`default_alignment_threshold` of all GT
    centres; ``seed`` drives the alignment's RANSAC.  Registered images whose names are not in
    ``gt`` are only counted.  The N(N-1)/2 pairs are streamed in blocks of
    ``_PAIRS_PER_BLOCK``, so memory stays bounded whatever the number of images.
    """
    thresholds = [float(t) for t in auc_thresholds]
    _AucAccumulator(thresholds)  # validates the thresholds before any work
    names = sorted(gt)
    by_name: dict[str, object] = {}
    num_extra = 0
    for image_id in recon.registered_image_ids:
        image = recon.images[image_id]
        if image.name in by_name:
            raise ValueError(f"two registered images are named {image.name!r}")
        if image.name in gt:
            by_name[image.name] = image
        else:
            num_extra += 1
    n = len(names)
    registered = np.array([name in by_name for name in names], dtype=bool)
    gt_rot = np.stack([gt[k].rotation for k in names]) if n else np.zeros((0, 3, 3))
    gt_trans = np.stack([gt[k].translation for k in names]) if n else np.zeros((0, 3))
    est_rot = np.tile(np.eye(3), (n, 1, 1))
    est_trans = np.zeros((n, 3))
    for k, name in enumerate(names):
        if registered[k]:
            est_rot[k] = by_name[name].cam_from_world_rotation
            est_trans[k] = by_name[name].cam_from_world_translation
    est_rot, est_c, registered = _prepare_poses(est_rot, est_trans, registered)
    gt_rot, gt_c, _ = _prepare_poses(gt_rot, gt_trans, None)
    num_reg = int(registered.sum())

    extent = scene_extent(gt_c)
    if alignment_threshold is None:
        threshold = default_alignment_threshold(gt_c)
    else:
        threshold = float(alignment_threshold)
    reg_idx = np.flatnonzero(registered)
    sim, inliers = align_centers(est_c[reg_idx], gt_c[reg_idx], threshold=threshold, seed=seed)
    if sim is not None:  # rotation from the orientations: centres alone leave a roll free
        sim = refine_rotation_with_orientations(sim, est_rot[reg_idx], gt_rot[reg_idx], est_c[reg_idx], gt_c[reg_idx], inliers)
    rot_errors: dict[str, float] = {}
    center_errors: dict[str, float] = {}
    degenerate = False
    if sim is not None:
        aligned_rot = est_rot[reg_idx] @ sim.rotation.T
        rot_err = rotation_angle_deg(aligned_rot, gt_rot[reg_idx])
        c_err = np.linalg.norm(sim.apply(est_c[reg_idx]) - gt_c[reg_idx], axis=1)
        c_err = c_err / extent if extent > 0 else np.full(len(c_err), math.nan)
        rot_errors = {names[k]: float(e) for k, e in zip(reg_idx, rot_err)}
        center_errors = {names[k]: float(e) for k, e in zip(reg_idx, c_err)}
        degenerate = is_collinear(gt_c[reg_idx][inliers]) if inliers.sum() >= 3 else True
        if degenerate:
            logger.warning(
                "GT centres of the alignment inliers are (nearly) collinear: the roll about "
                "their line is not determined, absolute rotation errors include it"
            )
    else:
        logger.warning("fewer than 3 registered GT images: no alignment, no absolute errors")

    acc = _AucAccumulator(thresholds)
    num_pairs = 0
    for block in _pair_error_blocks(est_rot, est_c, gt_rot, gt_c, registered):
        num_pairs += len(block)
        acc.add(block)
    aucs = acc.result()

    rot_values = np.array(list(rot_errors.values()))
    c_values = np.array(list(center_errors.values()))
    result = EvaluationResult(
        num_gt_images=n,
        num_registered=num_reg,
        registered_ratio=num_reg / n if n else math.nan,
        num_registered_not_in_gt=num_extra,
        num_points=len(recon.points3D),
        mean_track_length=float(recon.mean_track_length),
        mean_reprojection_error=float(recon.mean_reprojection_error()),
        scene_extent=extent,
        alignment=sim,
        alignment_threshold=threshold,
        num_alignment_inliers=int(inliers.sum()),
        alignment_degenerate=degenerate,
        rotation_errors_deg=rot_errors,
        center_errors=center_errors,
        median_rotation_error_deg=float(np.median(rot_values)) if len(rot_values) else math.nan,
        mean_rotation_error_deg=float(np.mean(rot_values)) if len(rot_values) else math.nan,
        median_center_error=float(np.median(c_values)) if len(c_values) else math.nan,
        mean_center_error=float(np.mean(c_values)) if len(c_values) else math.nan,
        num_pairs=num_pairs,
        auc=dict(zip(thresholds, aucs)),
    )
    logger.info(
        "evaluation: %d/%d registered, median rotation error %.3g deg, "
        "median centre error %.3g, AUC %s",
        num_reg, n, result.median_rotation_error_deg, result.median_center_error,
        ", ".join(f"@{t:g}={a:.4f}" for t, a in result.auc.items()),
    )
    return result
