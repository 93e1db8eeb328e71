"""Two-view geometric verification (paper section 3.1.1: the image edges), COLMAP's rules with OpenCV USAC.

For the raw matches of a pair:

1. Both cameras have a focal prior (and a model ``backend.camera_models`` knows): essential matrix
   with MAGSAC (``cv2.findEssentialMat`` with :class:`cv2.UsacParams`) on undistorted normalised
   coordinates, threshold ``max_error_px / mean focal``; the relative pose ``cam2_from_cam1`` from
   ``cv2.recoverPose`` (cheirality), then refined by minimising the robust (Cauchy, 1 px) Sampson
   error of the inliers: USAC's pose is fitted to a minimal sample and only scored on the rest,
   and the refinement fits it to every inlier, down to the keypoints' noise. Config CALIBRATED (2).
   Otherwise: fundamental matrix with MAGSAC in pixels; config UNCALIBRATED (3).
2. The inliers are the matches whose Sampson distance to the final E (in pixels: normalised
   distance times the mean focal) or F is at most ``max_error_px``.
3. Homography with MAGSAC in pixels; when its inliers (transfer error <= ``max_error_px``) are
   more than ``max_h_inlier_ratio`` of the E/F inliers (COLMAP's ``max_H_inlier_ratio``), the
   pair is PLANAR_OR_PANORAMIC (6): still verified, with the E/F inliers and pose.
4. Fewer than ``min_num_inliers`` matches or inliers, or no model: DEGENERATE (1), no inliers, so
   a resumed run knows the pair was tried.
5. RANSAC iterations: at most ``max_iterations``, and no more than needed to draw, with
   ``confidence``, one all-inlier sample of the weakest model worth looking for
   (:func:`ransac_trials`, :func:`search_inliers`; for H, ``max_h_inlier_ratio`` of the E/F
   inliers).  That model is one the field's global mapper trusts as an edge of its view graph
   (GLOMAP, now COLMAP's global mapper: at least 30 inliers and a quarter of the matches), and
   never less than ``min_num_inliers``.  A weaker model found on the way is still kept when it
   has ``min_num_inliers``; it is only not searched for to the end.  Most pairs that retrieval
   proposes have a few dozen chance matches and no model, and sizing their search for 15
   inliers among 60 matches costs the full ``max_iterations`` of the 5-point solver each.

Randomness: every USAC call gets ``UsacParams.randomGeneratorState`` from the caller's seed, so
the result depends only on (seed, input) - not on the process or on the order of pairs. (The
``method=cv2.USAC_MAGSAC`` overloads ignore ``cv2.setRNGSeed`` and always start from state 0.)

Pixels: keypoints, F and H here are in OpenCV's convention (pixel centres at integers). The
database stores COLMAP's (corner at 0, 0); :func:`to_colmap_pixels` converts F and H for writing
and :func:`from_colmap_pixels` back, the one place that knows. E, qvec and tvec are unaffected.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace
from typing import Protocol

import cv2
import numpy as np

from backend.camera_models import CAMERA_MODELS, calibration_matrix, focal_lengths, unproject
from sfm.io.database_schema import TwoViewConfig, TwoViewGeometry
from backend.geometry import rotation_from_rotvec, rotation_to_quaternion

# Pixel convention change: x_opencv = T @ x_colmap (COLMAP puts the image corner at (0, 0)).
_T_OPENCV_FROM_COLMAP = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
_T_COLMAP_FROM_OPENCV = np.linalg.inv(_T_OPENCV_FROM_COLMAP)


class CameraLike(Protocol):
    """What verification needs of a camera (``sfm.io.database.CameraRecord`` has it)."""

    model: str
    params: np.ndarray
    prior_focal_length: bool


@dataclass(frozen=True)
class VerifyOptions:
    """Geometric verification settings (COLMAP's defaults).

    max_error_px: inlier threshold in pixels (Sampson distance for E/F, transfer error for H)
    confidence: RANSAC confidence
    max_iterations: maximum RANSAC iterations
    min_num_inliers: fewer inliers make the pair DEGENERATE (not verified)
    max_h_inlier_ratio: H inliers / E-or-F inliers above this mark the pair PLANAR_OR_PANORAMIC
    """

    max_error_px: float = 4.0
    confidence: float = 0.999
    max_iterations: int = 10000
    min_num_inliers: int = 15
    max_h_inlier_ratio: float = 0.8


def pair_seed(seed: int, name1: str, name2: str) -> int:
    """A 31-bit RNG state from (seed, pair), the pair named by its images' names in either order:
    the same two images get the same state in every workspace, whatever ids the database gave
    them (an extension's images are numbered after the old ones)."""
    a, b = sorted((str(name1), str(name2)))
    digest = hashlib.blake2b(f"{a}\0{b}".encode(), digest_size=8).digest()
    words = np.frombuffer(digest, dtype=np.uint32).tolist()
    return int(np.random.SeedSequence([int(seed), *words]).generate_state(1)[0] & 0x7FFFFFFF)


# The weakest edge the global mapper of the field trusts (GLOMAP's InlierThresholdOptions
# min_inlier_num and min_inlier_ratio): what verification's search is sized to find.
SEARCH_MIN_INLIERS = 30
SEARCH_MIN_INLIER_RATIO = 0.25


def search_inliers(num_matches: int, min_num_inliers: int) -> float:
    """The inlier count RANSAC's iterations are sized for (module docstring, 5): the weakest
    trusted edge, ``SEARCH_MIN_INLIERS`` and ``SEARCH_MIN_INLIER_RATIO`` of the matches, and at
    least ``min_num_inliers``.  Below ``2 * SEARCH_MIN_INLIERS`` matches, where 30 inliers would
    be more than half of them, it is half the matches: the count rises from COLMAP's 15 (at 30
    matches) to 30 (at 60), so a pair with more matches never gets fewer iterations."""
    n = float(num_matches)
    return max(float(min_num_inliers), SEARCH_MIN_INLIER_RATIO * n, min(float(SEARCH_MIN_INLIERS), n / 2.0))


def ransac_trials(
    num_matches: int, needed_inliers: float, sample_size: int, confidence: float, cap: int
) -> int:
    """Iterations after which RANSAC has, with ``confidence``, drawn one all-inlier sample of
    ``sample_size`` if at least ``needed_inliers`` of the ``num_matches`` are inliers; at most
    ``cap`` (COLMAP bounds its trials the same way, through ``min_inlier_ratio``)."""
    if confidence >= 1.0:
        return int(cap)  # certainty needs every iteration
    ratio = min(float(needed_inliers) / max(int(num_matches), 1), 1.0)
    p_good = ratio**sample_size
    if p_good >= 1.0:
        return 1
    if p_good <= 0.0:
        return int(cap)
    trials = math.log(1.0 - confidence) / math.log1p(-p_good)
    return int(min(cap, max(1, math.ceil(trials))))


def _usac(
    threshold: float, options: VerifyOptions, state: int, max_iterations: int | None = None
) -> cv2.UsacParams:
    """The settings ``method=cv2.USAC_MAGSAC`` uses, with our state, iterations and confidence."""
    p = cv2.UsacParams()
    p.threshold = float(threshold)
    p.confidence = float(options.confidence)
    p.maxIterations = int(options.max_iterations if max_iterations is None else max_iterations)
    p.isParallel = False
    p.randomGeneratorState = int(state)
    p.sampler = cv2.SAMPLING_UNIFORM
    p.score = cv2.SCORE_METHOD_MAGSAC
    p.loMethod = cv2.LOCAL_OPTIM_SIGMA
    p.loIterations, p.loSampleSize = 10, 14
    p.final_polisher, p.final_polisher_iterations = cv2.MAGSAC, 10
    return p


# Inliers that choose among the four poses of an essential matrix (cheirality votes).
CHEIRALITY_POINTS = 500


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_distances(M: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of points (N, 2) to the epipolar model ``x2^T M x1 = 0``."""
    # M [x1; 1] and M^T [x2; 1] without building homogeneous copies (called once per
    # residual evaluation of the pose refinement)
    m_x1 = x1 @ M[:, :2].T + M[:, 2]
    mt_x2 = x2 @ M[:2, :] + M[2, :]
    den = m_x1[:, 0] ** 2 + m_x1[:, 1] ** 2 + mt_x2[:, 0] ** 2 + mt_x2[:, 1] ** 2
    num = x2[:, 0] * m_x1[:, 0] + x2[:, 1] * m_x1[:, 1] + m_x1[:, 2]
    return num / np.sqrt(np.maximum(den, 1e-300))


def _transfer_errors(H: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    p = np.c_[x1, np.ones(len(x1))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p[:, :2] / p[:, 2:] - x2, axis=1)
    return np.nan_to_num(err, nan=np.inf)


def sampson_gradients(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed Sampson distances of points (N, 2) to ``x2^T E x1 = 0`` (as
    :func:`sampson_distances`) and their gradients with respect to E's entries, (N, 9) in
    row-major order: ``s = n / sqrt(d)`` with ``n = x2^T E x1`` and ``d`` the squared first
    two entries of ``E x1`` and ``E^T x2``, so ``ds = dn / sqrt(d) - n dd / (2 d^1.5)``."""
    a = x1 @ E[:, :2].T + E[:, 2]  # E [x1; 1]
    b = x2 @ E[:2, :] + E[2, :]  # E^T [x2; 1]
    den = np.maximum(a[:, 0] ** 2 + a[:, 1] ** 2 + b[:, 0] ** 2 + b[:, 1] ** 2, 1e-300)
    num = x2[:, 0] * a[:, 0] + x2[:, 1] * a[:, 1] + a[:, 2]
    root = np.sqrt(den)
    n = len(x1)
    x1h, x2h = np.column_stack([x1, np.ones(n)]), np.column_stack([x2, np.ones(n)])
    a_rows = np.column_stack([a[:, 0], a[:, 1], np.zeros(n)])  # dd/dE_ij has a_i x1_j for i < 2
    b_cols = np.column_stack([b[:, 0], b[:, 1], np.zeros(n)])  # and x2_i b_j for j < 2
    d_num = x2h[:, :, None] * x1h[:, None, :]
    d_den = 2.0 * (a_rows[:, :, None] * x1h[:, None, :] + x2h[:, :, None] * b_cols[:, None, :])
    grad = d_num / root[:, None, None] - (num / (2.0 * den * root))[:, None, None] * d_den
    return num / root, grad.reshape(n, 9)


_ROTATION_GENERATORS = [_skew(axis) for axis in np.eye(3)]
REFINE_MAX_ITERATIONS = 50


def refine_relative_pose(
    c2_from_c1_rotation: np.ndarray, c2_from_c1_translation: np.ndarray, x1: np.ndarray,
    x2: np.ndarray, scale: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``cam2_from_cam1`` (R, unit t) minimising the Cauchy-robust Sampson error (in pixels:
    normalised distances times ``scale``, loss scale 1 px: the sum of ``log(1 + e^2)``) of
    normalised correspondences.

    Levenberg-Marquardt on the pose manifold: each step is a rotation vector applied to ``R``
    and a step of ``t`` in its tangent plane (five parameters), from the iteratively reweighted
    normal equations (weights ``1 / (1 + e^2)``: their solution is where the robust cost's
    gradient vanishes), with the Jacobian exact (:func:`sampson_gradients` times the derivative
    of ``E = [t]x R`` along each parameter); a step is taken only when the cost falls.  Stops
    when the cost changes by less than 1e-10 of itself."""
    rotation = np.asarray(c2_from_c1_rotation, np.float64)
    translation = np.ravel(c2_from_c1_translation).astype(np.float64)
    translation /= np.linalg.norm(translation)
    distances, gradients = sampson_gradients(_skew(translation) @ rotation, x1, x2)
    errors = scale * distances
    cost = float(np.sum(np.log1p(errors * errors)))
    damping = 1e-3
    for _ in range(REFINE_MAX_ITERATIONS):
        tangent = np.linalg.svd(translation.reshape(3, 1))[0][:, 1:]  # 3 x 2, orthogonal to t
        t_cross = _skew(translation)
        d_essential = [t_cross @ g @ rotation for g in _ROTATION_GENERATORS]
        d_essential += [_skew(tangent[:, k]) @ rotation for k in range(2)]
        jacobian = scale * (gradients @ np.stack([d.ravel() for d in d_essential], axis=1))
        weights = 1.0 / (1.0 + errors * errors)
        normal = jacobian.T @ (weights[:, None] * jacobian)
        rhs = -jacobian.T @ (weights * errors)
        while True:
            step = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), rhs)
            new_rotation = rotation_from_rotvec(step[:3]) @ rotation
            new_translation = translation + tangent @ step[3:]
            new_translation /= np.linalg.norm(new_translation)
            new_distances, new_gradients = sampson_gradients(_skew(new_translation) @ new_rotation, x1, x2)
            new_errors = scale * new_distances
            new_cost = float(np.sum(np.log1p(new_errors * new_errors)))
            if new_cost <= cost:
                damping = max(damping / 10.0, 1e-12)
                break
            damping *= 10.0
            if damping > 1e8:  # no step lowers the cost: a minimum
                return rotation, translation
        converged = cost - new_cost <= 1e-10 * cost
        rotation, translation, gradients, errors, cost = (new_rotation, new_translation, new_gradients,
                                                          new_errors, new_cost)  # fmt: skip
        if converged:
            break
    return rotation, translation


def _degenerate() -> TwoViewGeometry:
    return TwoViewGeometry(int(TwoViewConfig.DEGENERATE), np.zeros((0, 2), np.uint32))


def _calibrated(camera: CameraLike) -> bool:
    spec = CAMERA_MODELS.get(camera.model)
    return (
        bool(camera.prior_focal_length)
        and spec is not None
        and len(camera.params) == spec.num_params
    )


def _essential(x1n, x2n, threshold_n, scale, max_error_px, options, state):
    """(inlier mask, E, R, t) of the calibrated model, or None when estimation fails."""
    eye, zero = np.eye(3), np.zeros(5)
    trials = ransac_trials(len(x1n), search_inliers(len(x1n), options.min_num_inliers), 5,
                           options.confidence, options.max_iterations)
    E, mask = cv2.findEssentialMat(
        x1n, x2n, eye, eye, zero, zero, _usac(threshold_n, options, state, trials)
    )
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < 5:
        return None
    ransac = mask.ravel().astype(bool)
    # E's four (R, t) differ in which side of the cameras the points fall: evenly spaced
    # inliers decide that as well as all of them, at a fraction of the triangulations
    chosen = np.flatnonzero(ransac)
    chosen = chosen[
        np.linspace(0, len(chosen) - 1, min(len(chosen), CHEIRALITY_POINTS)).astype(int)
    ]
    _, rotation, translation, _ = cv2.recoverPose(E, x1n[chosen], x2n[chosen])
    for _ in range(2):  # refine on the RANSAC inliers, re-classify, refine again
        rotation, translation = refine_relative_pose(
            rotation, translation, x1n[ransac], x2n[ransac], scale
        )
        E = _skew(translation) @ rotation
        ransac = np.abs(sampson_distances(E, x1n, x2n)) * scale <= max_error_px
        if ransac.sum() < 5:
            return None
    return ransac, E, rotation, translation


def verify_pair(
    keypoints1: np.ndarray, keypoints2: np.ndarray, matches: np.ndarray, camera1: CameraLike,
    camera2: CameraLike, options: VerifyOptions = VerifyOptions(), seed: int = 0,
) -> TwoViewGeometry:  # fmt: skip
    """The two-view geometry of one pair from its raw matches (see the module docstring); its
    inliers are the pair's image edge and their number its weight (paper section 3.1.1).

    Keypoints (N, >=2) in OpenCV's pixel convention; ``matches`` (M, 2) indices into them.
    F and H of the result are in OpenCV's pixel convention too, E on normalised coordinates,
    ``qvec`` (w, x, y, z) and unit ``tvec`` give ``cam2_from_cam1``; ``seed`` seeds USAC.
    """
    matches = np.asarray(matches, np.int64).reshape(-1, 2)
    if len(matches) < max(options.min_num_inliers, 8):
        return _degenerate()
    p1 = np.ascontiguousarray(keypoints1[matches[:, 0], :2], np.float64)
    p2 = np.ascontiguousarray(keypoints2[matches[:, 1], :2], np.float64)
    thr = float(options.max_error_px)
    E = qvec = tvec = None
    try:
        if _calibrated(camera1) and _calibrated(camera2):
            x1n = unproject(camera1.model, camera1.params, p1)
            x2n = unproject(camera2.model, camera2.params, p2)
            scale = float(np.mean([*focal_lengths(camera1.model, camera1.params),
                                   *focal_lengths(camera2.model, camera2.params)]))  # fmt: skip
            found = _essential(x1n, x2n, thr / scale, scale, thr, options, seed)
            if found is None:
                return _degenerate()
            inliers, E, rotation, translation = found
            k1 = calibration_matrix(camera1.model, camera1.params)
            k2 = calibration_matrix(camera2.model, camera2.params)
            F = np.linalg.inv(k2).T @ E @ np.linalg.inv(k1)
            config = TwoViewConfig.CALIBRATED
            qvec, tvec = rotation_to_quaternion(rotation), translation.ravel().copy()
        else:
            trials = ransac_trials(len(p1), search_inliers(len(p1), options.min_num_inliers), 7,
                                   options.confidence, options.max_iterations)
            F, mask = cv2.findFundamentalMat(p1, p2, _usac(thr, options, seed, trials))
            if F is None or F.shape != (3, 3) or mask is None:
                return _degenerate()
            inliers = np.abs(sampson_distances(F, p1, p2)) <= thr
            config = TwoViewConfig.UNCALIBRATED
        if inliers.sum() < options.min_num_inliers:
            return _degenerate()
        # only an H with more than max_h_inlier_ratio of the E/F inliers changes the verdict
        trials = ransac_trials(
            len(p1),
            options.max_h_inlier_ratio * inliers.sum(),
            4,
            options.confidence,
            options.max_iterations,
        )
        H, h_mask = cv2.findHomography(p1, p2, _usac(thr, options, seed, trials))
    except cv2.error:  # degenerate point sets make OpenCV throw
        return _degenerate()
    if H is not None and H.shape == (3, 3) and h_mask is not None:
        h_inliers = int(np.count_nonzero(_transfer_errors(H, p1, p2) <= thr))
        if h_inliers / inliers.sum() > options.max_h_inlier_ratio:
            config = TwoViewConfig.PLANAR_OR_PANORAMIC
    else:
        H = None
    F = F / np.linalg.norm(F)
    return TwoViewGeometry(int(config), matches[inliers].astype(np.uint32), F=F, E=E, H=H,
                           qvec=qvec, tvec=tvec)  # fmt: skip


def to_colmap_pixels(geometry: TwoViewGeometry) -> TwoViewGeometry:
    """F and H from OpenCV's pixel convention to COLMAP's (what the database stores):
    ``F_colmap = T^T F T`` and ``H_colmap = T^-1 H T`` with ``x_opencv = T x_colmap``."""
    T = _T_OPENCV_FROM_COLMAP
    F = None if geometry.F is None else T.T @ geometry.F @ T
    H = None if geometry.H is None else _T_COLMAP_FROM_OPENCV @ geometry.H @ T
    return replace(geometry, F=F, H=H)


def from_colmap_pixels(geometry: TwoViewGeometry) -> TwoViewGeometry:
    """Inverse of :func:`to_colmap_pixels`: F and H as read from the database, in OpenCV's
    pixel convention (the keypoints' convention after ``Database.read_keypoints``)."""
    T = _T_COLMAP_FROM_OPENCV
    F = None if geometry.F is None else T.T @ geometry.F @ T
    H = None if geometry.H is None else _T_OPENCV_FROM_COLMAP @ geometry.H @ T
    return replace(geometry, F=F, H=H)
