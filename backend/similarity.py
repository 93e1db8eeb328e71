"""Pairwise similarity between two local models from their common cameras (paper section 3.2.1),
and the residual error that weights the cluster-graph edge (section 3.2.2, Eq. 10-11).

Conventions: poses are ``cam_from_world`` (x_cam = R X + t), camera centre
C = -R^T t. A similarity ``b_from_a`` maps X_b = s R X_a + t; a camera k registered in both models
then satisfies R_b,k = R_a,k R^T and C_b,k = s R C_a,k + t. Arrays in, frozen dataclasses out;
this module imports neither ``sfm`` nor ``graph``.

Algorithm of :func:`estimate_similarity`:

1. Relative scale, Eq. 1-2: median of the ratios ||C_b,i - C_b,j|| / ||C_a,i - C_a,j|| over
   pairs of common cameras. Departure: the median is taken per RANSAC hypothesis over the pairs
   (k, j) anchored at the hypothesis camera k, not over all pairs. Over all pairs, only
   (1 - e)^2 of them join two inliers, so the global median breaks down once e > 29% of the
   common cameras are outliers; the anchored median of an inlier k holds up to e < 50%.
2. Rotation and translation, Eq. 3-6, by RANSAC with the scale known: a single camera k is a
   minimal sample (its orientation fixes R = R_b,k^T R_a,k, Eq. 5, then t = C_b,k - s R C_a,k,
   Eq. 6 written for camera centres).
   Every camera is tried when there are at most ``max_hypotheses`` (no randomness), else a
   seeded sample. A camera is an inlier when its centre error is below ``center_threshold``
   times the extent of the common cameras in frame b and its rotation error below
   ``rotation_threshold_deg``; the best hypothesis has most inliers, ties broken by the lower
   summed (threshold-normalised) error.
3. Refit on the inliers, then re-score, until the inlier set stops growing: rotation = chordal
   L2 mean of the inliers' per-camera rotations (SVD projection of their sum); scale = Horn's
   symmetric ratio sqrt(sum |C_b - mean_b|^2 / sum |C_a - mean_a|^2) (so s_ba = 1 / s_ab
   exactly); t = mean_b - s R mean_a. The rotation comes from camera orientations, not from the
   centres, by default: each orientation is fixed by many image observations, whereas the
   centres of an overlap are often nearly collinear (a street, a walk) and then leave the
   rotation about their line undetermined; it also keeps shared cameras' orientations
   consistent across the merge. ``refit_rotation_on_centres`` uses the least-squares rotation
   of the inlier centres (Horn / Umeyama, reflection-corrected) instead, when they are spread
   in at least two directions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from backend.geometry import project_to_so3, rotation_angle_deg
from backend.sim3 import Sim3

Array = np.ndarray
_NEGLIGIBLE = 1e-9  # distances below this fraction of a model's extent are not used for ratios
_MIN_SPREAD = 0.1  # second / first singular value of the centred centres: below, "collinear"


@dataclass(frozen=True)
class SimilarityOptions:
    """Options of :func:`estimate_similarity`.

    min_common_cameras: fewer common cameras and there is no edge (default 2, the fewest that fix
        a scale).
    min_inliers: fewer RANSAC inlier cameras and there is no edge (default 2).
    center_threshold: a camera is an inlier when its centre error is below this fraction of the
        common cameras' extent in frame b (median distance of their centres to their
        geometric median, robust to far outliers; default 0.05).
    rotation_threshold_deg: ... and its orientation error below this angle (default 5 degrees).
    max_msd: edges whose normalised MSD exceeds this are dropped by the caller (the paper's
        dotted edges, Figure 3). Default 0.025 = ``center_threshold`` / 2: the paper's MSE,
        Eq. 10, (1/2n) sqrt(sum e_i^2), of n points all within the inlier tolerance tau (e_i <
        tau x extent) is below tau / (2 sqrt(n)) <= tau / 2, with equality approached at n = 1.
        So it is the tightest threshold that never drops an edge whose common points all agree
        as well as its inlier cameras must, whatever n. Because of the paper's 1/(2n) sqrt(sum),
        it drops only gross residuals as n grows: an RMS above 2 sqrt(n) x max_msd extents (0.05
        extents for n = 1, 1.1 extents for n = 500 common points). Change it with
        ``center_threshold``.
    max_hypotheses: above this many common cameras, RANSAC tries a seeded sample of this many
        single-camera hypotheses instead of all of them (default 200).
    refit_rotation_on_centres: take the final rotation from the inlier centres (least squares)
        instead of the cameras' orientations, when the centres are not collinear (default False;
        see the module docstring).
    max_refits: refit / re-score rounds after RANSAC (default 5).
    seed: seeds the hypothesis sample when there are more than ``max_hypotheses`` cameras.
    """

    min_common_cameras: int = 2
    min_inliers: int = 2
    center_threshold: float = 0.05
    rotation_threshold_deg: float = 5.0
    max_msd: float = 0.025
    max_hypotheses: int = 200
    refit_rotation_on_centres: bool = False
    max_refits: int = 5
    seed: int = 0


@dataclass(frozen=True)
class SimilarityResult:
    """Result of :func:`estimate_similarity`.

    scale, rotation (3,3), translation (3,): the similarity ``b_from_a`` (X_b = s R X_a + t).
    camera_inliers: bool mask over the common cameras (input order); num_inliers its count.
    mse_ab, mse_ba: the paper's MSE, Eq. 10, in both directions (a->b with T, b->a with T^-1),
        each divided by the inlier cameras' extent in its target frame (b, resp. a).
    msd: max(mse_ab, mse_ba), the MSD of Eq. 11 (normalised, symmetric): the edge weight.
    num_points: common 3D points given; the MSD is computed over them plus the inlier camera
        centres (the common cameras are common points of the two models too).
    extent_a, extent_b: extent of the inlier cameras' centres in each frame (median distance to
        their geometric median), the MSD normalisers.
    """

    scale: float
    rotation: Array
    translation: Array
    camera_inliers: Array
    num_inliers: int
    mse_ab: float
    mse_ba: float
    msd: float
    num_points: int
    extent_a: float
    extent_b: float

    @property
    def sim_b_from_a(self) -> Sim3:
        return Sim3(self.scale, self.rotation, self.translation)


def mean_square_distance(
    scale: float, rotation: Array, translation: Array, points_a: Array, points_b: Array
) -> tuple[float, float]:
    """(mse_ab, mse_ba) of the paper's Eq. 10 (section 3.2.2), literally: mse_ab = 1/(2n)
    sqrt(sum_i |T X_a,i - X_b,i|^2) with T = ``b_from_a``, and mse_ba likewise with T^-1 from b
    to a.

    Note the paper's odd normalisation: a square root of the sum divided by 2n (not the root
    mean square), so it shrinks as 1/sqrt(n) for a fixed per-point error. Unnormalised (in the
    units of each target frame); n = 0 gives (0, 0).
    """
    pa = np.asarray(points_a, float).reshape(-1, 3)
    pb = np.asarray(points_b, float).reshape(-1, 3)
    n = len(pa)
    if n == 0:
        return 0.0, 0.0
    sim = Sim3(float(scale), np.asarray(rotation, float), np.asarray(translation, float))
    err_ab = sim.apply(pa) - pb
    err_ba = sim.inverse().apply(pb) - pa
    return float(np.sqrt((err_ab**2).sum()) / (2 * n)), float(np.sqrt((err_ba**2).sum()) / (2 * n))


def _centres(rotations: Array, translations: Array) -> Array:
    return -np.einsum("nji,nj->ni", rotations, translations)  # C = -R^T t


def _extent(centres: Array) -> float:
    """Median distance of the centres to their geometric median (Weiszfeld iterations from the
    mean). Both are robust to far outliers and, unlike a coordinate-wise median, equivariant
    under similarities, so the extents of the same cameras in a and b differ exactly by the
    scale. Falls back to the RMS distance to the mean when that median is 0."""
    centre = centres.mean(0)
    for _ in range(100):
        dist = np.maximum(np.linalg.norm(centres - centre, axis=1), 1e-300)
        step = (centres / dist[:, None]).sum(0) / (1.0 / dist).sum()
        done = np.linalg.norm(step - centre) <= 1e-12 * dist.max()
        centre = step
        if done:
            break
    med = float(np.median(np.linalg.norm(centres - centre, axis=1)))
    return med if med > 0 else float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()))


def _errors(sim: Sim3, hyp_rot: Array, ca: Array, cb: Array) -> tuple[Array, Array]:
    """Centre error (frame b units) and rotation error (degrees) of every camera under ``sim``."""
    centre_err = np.linalg.norm(sim.apply(ca) - cb, axis=1)
    return centre_err, rotation_angle_deg(hyp_rot, sim.rotation)


def _fit(
    mask: Array, hyp_rot: Array, ca: Array, cb: Array, options: SimilarityOptions
) -> Sim3:
    """Refit on the inliers (step 3 of the module docstring): rotation, Horn's scale and the
    translation of Eq. 6 over all inlier cameras."""
    a0 = ca[mask] - ca[mask].mean(0)
    b0 = cb[mask] - cb[mask].mean(0)
    rotation = project_to_so3(hyp_rot[mask].sum(0))  # chordal L2 mean
    if options.refit_rotation_on_centres and mask.sum() >= 3:
        sv = np.linalg.svd(a0, compute_uv=False)
        if sv[0] > 0 and sv[1] >= _MIN_SPREAD * sv[0]:
            rotation = project_to_so3(b0.T @ a0)  # Horn / Umeyama: max tr(R^T sum b0 a0^T)
    denom = (a0**2).sum()
    scale = float(np.sqrt((b0**2).sum() / denom)) if denom > 0 else float("nan")
    return Sim3(scale, rotation, cb[mask].mean(0) - scale * rotation @ ca[mask].mean(0))


def _ransac(
    hyp_rot: Array,
    ca: Array,
    cb: Array,
    extent_a: float,
    extent_b: float,
    options: SimilarityOptions,
) -> Array | None:
    """Inlier mask of the best single-camera hypothesis (steps 1-2 of the module docstring:
    Eq. 1-2 anchored at the hypothesis camera, then Eq. 5-6), or None."""
    n = len(ca)
    hyps = np.arange(n)
    if n > options.max_hypotheses:
        rng = np.random.default_rng(options.seed)
        hyps = np.sort(rng.choice(n, options.max_hypotheses, replace=False))
    d_a = ca[None, :, :] - ca[hyps, None, :]  # (h, n, 3): C_a,j - C_a,k
    d_b = cb[None, :, :] - cb[hyps, None, :]
    len_a, len_b = np.linalg.norm(d_a, axis=2), np.linalg.norm(d_b, axis=2)
    usable = (len_a > _NEGLIGIBLE * extent_a) & (len_b > _NEGLIGIBLE * extent_b)
    ratios = np.where(usable, len_b / np.where(usable, len_a, 1.0), np.nan)
    has_pair = usable.any(axis=1)
    scales = np.full(len(hyps), np.nan)
    scales[has_pair] = np.nanmedian(ratios[has_pair], axis=1)  # Eq. 2, anchored at k
    # Prediction of C_b,j by hypothesis k: C_b,k + s_k R_k (C_a,j - C_a,k).
    pred = cb[hyps, None, :] + scales[:, None, None] * np.einsum("kab,kjb->kja", hyp_rot[hyps], d_a)
    centre_err = np.linalg.norm(pred - cb[None], axis=2) / (options.center_threshold * extent_b)
    rot_err = (
        rotation_angle_deg(hyp_rot[hyps][:, None], hyp_rot[None])
        / options.rotation_threshold_deg
    )
    inl = (centre_err < 1.0) & (rot_err < 1.0) & (scales > 0)[:, None]
    count = inl.sum(axis=1)
    cost = np.where(inl, np.nan_to_num(centre_err) + rot_err, 0.0).sum(axis=1)
    best = np.lexsort((cost, -count))[0]
    return inl[best] if count[best] > 0 else None


def estimate_similarity(
    rotations_a: Array,
    translations_a: Array,
    rotations_b: Array,
    translations_b: Array,
    points_a: Array | None = None,
    points_b: Array | None = None,
    options: SimilarityOptions = SimilarityOptions(),
) -> SimilarityResult | None:
    """Similarity ``b_from_a`` of two local models from their common cameras (paper section
    3.2.1, Eq. 1-6; RANSAC and refit as in the module docstring) and its MSD edge weight
    (section 3.2.2, Eq. 10-11, normalised by the extents).

    rotations_* (N,3,3), translations_* (N,3): cam_from_world poses of the N common cameras in
    models a and b, row k the same image. points_* (P,3): the common 3D points, row i the same
    point (None or empty: none). The MSD is taken over these points plus the inlier camera
    centres (the centres alone when there are no points); mse_ab is divided by the inliers'
    extent in b, mse_ba by that in a, so weights compare across pairs of models of different
    scales; msd = max of the two (the paper's Eq. 11 writes max(mse_k1k2, mse_k1k2), a typo for
    the two directions).

    Returns None with fewer than ``min_common_cameras`` (or 2) common cameras, degenerate centres
    (no extent), fewer than ``min_inliers`` inliers, or a scale that is not finite and positive.
    """
    ra, rb = (
        np.asarray(rotations_a, float).reshape(-1, 3, 3),
        np.asarray(rotations_b, float).reshape(-1, 3, 3),
    )
    ca = _centres(ra, np.asarray(translations_a, float).reshape(-1, 3))
    cb = _centres(rb, np.asarray(translations_b, float).reshape(-1, 3))
    if not (len(ra) == len(rb) == len(ca) == len(cb)):
        raise ValueError("rotations and translations of a and b must describe the same cameras")
    pa = np.zeros((0, 3)) if points_a is None else np.asarray(points_a, float).reshape(-1, 3)
    pb = np.zeros((0, 3)) if points_b is None else np.asarray(points_b, float).reshape(-1, 3)
    if pa.shape != pb.shape:
        raise ValueError(f"points_a {pa.shape} and points_b {pb.shape} must correspond row by row")
    n = len(ca)
    if n < max(options.min_common_cameras, 2):
        return None
    extent_a, extent_b = _extent(ca), _extent(cb)
    if not (np.isfinite(extent_a) and np.isfinite(extent_b) and extent_a > 0 and extent_b > 0):
        return None
    hyp_rot = np.einsum("nba,nbc->nac", rb, ra)  # R_k = R_b,k^T R_a,k
    mask = _ransac(hyp_rot, ca, cb, extent_a, extent_b, options)
    if mask is None or mask.sum() < max(options.min_inliers, 2):
        return None
    sim = _fit(mask, hyp_rot, ca, cb, options)
    for _ in range(options.max_refits):
        if not (np.isfinite(sim.scale) and sim.scale > 0):
            return None
        centre_err, rot_err = _errors(sim, hyp_rot, ca, cb)
        new = (centre_err < options.center_threshold * extent_b) & (
            rot_err < options.rotation_threshold_deg
        )
        if new.sum() <= mask.sum() or np.array_equal(new, mask):
            break
        mask, sim = new, _fit(new, hyp_rot, ca, cb, options)
    if not (np.isfinite(sim.scale) and sim.scale > 0 and np.isfinite(sim.translation).all()):
        return None
    in_a, in_b = ca[mask], cb[mask]
    ext_a, ext_b = _extent(in_a), _extent(in_b)
    mse_ab, mse_ba = mean_square_distance(
        sim.scale, sim.rotation, sim.translation, np.vstack([pa, in_a]), np.vstack([pb, in_b])
    )
    mse_ab, mse_ba = mse_ab / ext_b, mse_ba / ext_a
    return SimilarityResult(
        scale=sim.scale,
        rotation=sim.rotation,
        translation=sim.translation,
        camera_inliers=mask,
        num_inliers=int(mask.sum()),
        mse_ab=mse_ab,
        mse_ba=mse_ba,
        msd=max(mse_ab, mse_ba),
        num_points=len(pa),
        extent_a=ext_a,
        extent_b=ext_b,
    )
