"""Registering the next image of a growing model by PnP (COLMAP's incremental mapper).

Candidates come from :meth:`sfm.mapper.state.MapperState.next_image_candidates` (most visible
triangulated points, best spread first).  A candidate is registered when OpenCV's USAC PnP
RANSAC finds at least ``abs_pose_min_num_inliers`` inliers, and ``abs_pose_min_inlier_ratio``
of the points it sees, within ``abs_pose_max_error`` pixels; its pose is then refined by least
squares on those inliers.  When PnP registers nothing, ``sfm.mapper.structureless`` tries the
images from 2D-2D matches.

An image whose camera no registered image uses yet (one camera per image, a second camera in the
set) brings intrinsics the model has not estimated: COLMAP's mapper then estimates them with the
pose (``RegisterNextImage``).  A focal length that is a guess (no EXIF, no ``--intrinsics``:
1.2 x the longer side) is searched first (:func:`search_focal`); then the pose, the focal length
and the first radial term are refined together on the PnP inliers
(:func:`refine_pose_and_camera`), as far as ``intrinsics_refinement`` allows.  Registered with
the guess instead, such an image keeps a pose distorted by the wrong focal length through the
local BAs until the next global BA, and its first points are triangulated with it.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from backend.camera_models import focal_lengths, has_bogus_params, model_spec, project
from sfm.mapper.distortion import chi_square, significance_chi2
from sfm.mapper.state import MapperState

# Focal lengths the search tries: the range of COLMAP's bogus-camera test (0.1 to 10 x the longer
# image side), spaced by a constant ratio (30 candidates: 17% apart).  A candidate is judged by
# the inliers a PnP RANSAC of FOCAL_SEARCH_ITERATIONS finds among FOCAL_SEARCH_POINTS of the
# points (a random sample): enough for P3P's 3-point samples to hit an all-inlier one with
# 99.9% confidence down to a 35% inlier ratio, and a count that ranks candidates as all points
# would; the pose at the chosen focal length is then found from all points.
FOCAL_SEARCH_RANGE = (0.1, 10.0)
FOCAL_SEARCH_CANDIDATES = 30
# The ratio between neighbouring candidates: the resolution at which the search tells focal
# lengths apart.
FOCAL_SEARCH_STEP = (FOCAL_SEARCH_RANGE[1] / FOCAL_SEARCH_RANGE[0]) ** (1.0 / (FOCAL_SEARCH_CANDIDATES - 1))
FOCAL_SEARCH_ITERATIONS = 160
FOCAL_SEARCH_POINTS = 300
# Inliers the refinement of pose and camera uses at most (a random sample): a thousand points fix
# one view's focal length to a fraction of a percent; the local BA that follows uses them all.
REFINE_POINTS = 1000


def register_next(state: MapperState) -> bool:
    """Register the best unregistered image that PnP accepts; False when none can be.  After
    the ready candidates come the failed images worth a retry when nothing else registers
    (``MapperState.next_image_candidates(stalled=True)``)."""
    opts = state.opts
    for i in state.next_image_candidates(stalled=True):
        visible = len(state.visible_points(i)[0])
        if visible < opts.abs_pose_min_num_inliers:
            continue
        c = state.cam_index[i]
        level = state.new_camera_level(c)  # what is estimated with the pose: None, "focal", "focal_radial"
        estimated = None
        if level is not None:
            state.reset_camera(c)  # from its prior, as COLMAP does for a camera no image has refined
            estimated = _pose_and_camera(state, i, level)
        if estimated is not None:
            R, t, params = estimated
            state.set_intrinsics(c, params)
        else:
            if level is not None:
                state.reset_camera(c)  # the view does not determine its camera: the prior's values
            found = _pose(state, i)
            if found is None:
                state.note_failure(i, visible)
                continue
            R, t, _ = found
        state.register(i, R, t)
        return True
    return False


def _pose(state: MapperState, i: int):
    """PnP RANSAC of image ``i`` with its camera's current intrinsics, refined by least squares
    on the inliers: ``(R, t, inlier rows)``, or None when PnP finds too few inliers."""
    opts = state.opts
    rows, X = state.visible_points(i)
    x = state.obs_norm[rows]
    ok, rvec, tvec, inliers = _pnp_ransac(X, x, opts.abs_pose_max_error / state.focal(i), 10000, opts.seed + i)
    if not ok or inliers is None:
        return None
    inliers = inliers.ravel()
    if len(inliers) < opts.abs_pose_min_num_inliers or len(inliers) < opts.abs_pose_min_inlier_ratio * len(rows):
        return None
    # Least squares on the RANSAC inliers, in normalised coordinates like the RANSAC (the
    # local BA that follows refines the pose again, robustly and in pixels).
    rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], np.eye(3), None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.ravel(), rows[inliers]


def _pose_and_camera(state: MapperState, i: int, level: str):
    """Image ``i``'s pose with its camera (new to the model, at its prior) estimated: the focal
    length searched when the prior's is a guess, PnP at it, then pose, focal length and (with
    ``level`` "focal_radial") the first radial term refined together.  A radial term the view
    does not determine (its change from the prior within the 3-sigma test of
    ``sfm.mapper.distortion``) is held and the focal length refined alone.  Returns
    ``(R, t, params)``.  Where the view does not determine the focal length either (a far,
    narrow view: focal length and distance trade against each other) or leaves a camera no lens
    has (``has_bogus_params``), the prior stands: the pose PnP found with it, or None when the
    search had moved away from a guessed focal length (the caller poses the image at the
    prior); None also when the search or PnP fail."""
    opts = state.opts
    c = state.cam_index[i]
    prior = state.priors[c]
    if not prior.prior_focal_length:
        rows, X = state.visible_points(i)
        focal = search_focal(X, state.obs_norm[rows], state.focal(i), prior, opts.abs_pose_max_error, opts.seed + i)
        if focal is None:
            return None
        state.set_focal(c, focal)
    found = _pose(state, i)
    if found is None:
        return None
    R, t, rows = found
    if len(rows) > REFINE_POINTS:
        rows = np.sort(np.random.default_rng(opts.seed + i).choice(rows, REFINE_POINTS, replace=False))
    X, pixels, sigmas = state.track_xyz[state.obs_track[rows]], state.obs_px[rows], state.obs_sigma[rows]
    radial = model_spec(prior.model).extra_idx[:1]
    for refined_level in (("focal_radial", "focal") if level == "focal_radial" and radial else ("focal",)):
        refined = refine_pose_and_camera(X, pixels, sigmas, R, t, prior.model, state.params[c], refined_level,
                                         opts.loss, opts.loss_scale)
        if refined is None:
            return None
        R_new, t_new, params, covariance = refined
        if refined_level == "focal" or _significant(params[list(radial)] - prior.params[list(radial)],
                                                    covariance[1:, 1:]):
            break
    focal_change = focal_lengths(prior.model, params)[0] - focal_lengths(prior.model, prior.params)[0]
    if has_bogus_params(prior.model, params, prior.width, prior.height) or not _significant(
            np.array([focal_change]), covariance[:1, :1]):
        # the prior stands; PnP already posed the image with it unless the search moved it
        return (R, t, np.array(prior.params, dtype=np.float64)) if prior.prior_focal_length else None
    return R_new, t_new, params


def _covariance(jacobian: np.ndarray) -> np.ndarray:
    """The inverse of the Gauss-Newton Hessian ``J^T J``, inverted at unit diagonal (parameters
    in pixels and radians differ by orders of magnitude), infinite when it is singular: a
    direction the data do not determine has no finite variance (a pseudo-inverse would report
    it as exactly known)."""
    hessian = jacobian.T @ jacobian
    scale = np.sqrt(np.maximum(np.diag(hessian), 1e-300))
    try:
        inverse = np.linalg.inv(hessian / np.outer(scale, scale))
    except np.linalg.LinAlgError:
        return np.full_like(hessian, np.inf)
    return inverse / np.outer(scale, scale)


def _significant(change: np.ndarray, covariance: np.ndarray) -> bool:
    """Whether ``change`` (of parameters with ``covariance``) passes the 3-sigma chi-square test
    the final BAs' self-calibration applies (``sfm.mapper.distortion.significance_chi2``)."""
    with np.errstate(invalid="ignore"):  # an infinite covariance gives NaN: not significant
        chi2 = chi_square(change, covariance)
    return bool(np.isfinite(chi2) and chi2 > significance_chi2(len(change)))


def _pnp_ransac(X: np.ndarray, x_norm: np.ndarray, threshold: float, iterations: int, seed: int,
                local_optimisation: bool = True):
    """OpenCV's USAC PnP RANSAC on normalised coordinates: (ok, rvec, tvec, inliers).  Without
    ``local_optimisation`` (its inner re-estimation from the inliers, most of its time) for
    counting inliers only."""
    usac = cv2.UsacParams()
    if not local_optimisation:
        usac.loMethod = cv2.LOCAL_OPTIM_NULL
    usac.threshold = threshold
    usac.confidence = 0.9999
    usac.maxIterations = iterations
    usac.randomGeneratorState = seed
    usac.isParallel = False
    ok, _, rvec, tvec, inliers = cv2.solvePnPRansac(X, x_norm, np.eye(3), None, params=usac)
    return ok, rvec, tvec, inliers


def search_focal(X: np.ndarray, x_norm: np.ndarray, focal: float, prior, max_error: float, seed: int) -> float | None:
    """The focal length, of ``FOCAL_SEARCH_CANDIDATES`` spread over ``FOCAL_SEARCH_RANGE`` x the
    longer image side, at which PnP RANSAC finds the most inliers within ``max_error`` pixels
    among ``FOCAL_SEARCH_POINTS`` of the points (COLMAP's ``estimate_focal_length`` by sampled
    focal lengths); None when none finds any.

    ``x_norm`` are the points' normalised coordinates at ``focal`` with the prior's (zero)
    distortion, so at focal ``f`` they are ``x_norm * focal / f``."""
    size = float(max(prior.width, prior.height))
    if len(X) > FOCAL_SEARCH_POINTS:
        sample = np.sort(np.random.default_rng(seed).choice(len(X), FOCAL_SEARCH_POINTS, replace=False))
        X, x_norm = X[sample], x_norm[sample]
    best, best_count = None, 0
    for f in np.geomspace(FOCAL_SEARCH_RANGE[0] * size, FOCAL_SEARCH_RANGE[1] * size, FOCAL_SEARCH_CANDIDATES):
        ok, _, _, inliers = _pnp_ransac(X, x_norm * (focal / f), max_error / f, FOCAL_SEARCH_ITERATIONS, seed,
                                        local_optimisation=False)
        count = 0 if not ok or inliers is None else len(inliers)
        if count > best_count:
            best, best_count = float(f), count
    return best


def refine_pose_and_camera(X: np.ndarray, pixels: np.ndarray, sigmas: np.ndarray, R: np.ndarray, t: np.ndarray,
                           model: str, params: np.ndarray, level: str, loss: str, loss_scale: float):
    """``cam_from_world`` and the camera's focal length (with ``level`` "focal_radial" also its
    first radial term, if the model has one) minimising the robust reprojection error of the
    points ``X`` at ``pixels``, in units of each observation's ``sigmas`` as in bundle
    adjustment (COLMAP's ``RefineAbsolutePose`` with ``refine_focal_length`` and
    ``refine_extra_params``); principal point, aspect ratio and any further distortion terms
    held.  Returns ``(R, t, params, covariance)``, the covariance of the refined intrinsics
    (focal length, then the radial term) from the Gauss-Newton Hessian of the whitened errors;
    None when the refinement fails or ends with a focal length that is not positive."""
    spec = model_spec(model)
    free = list(spec.focal_idx)
    radial = spec.extra_idx[:1] if level == "focal_radial" else ()
    fx, fy = focal_lengths(model, params)
    aspect = fy / fx

    def camera(v: np.ndarray) -> np.ndarray:
        p = np.array(params, dtype=np.float64)
        p[free[0]] = v[6]
        if len(free) > 1:
            p[free[1]] = v[6] * aspect
        if radial:
            p[radial[0]] = v[7]
        return p

    def residuals(v: np.ndarray) -> np.ndarray:
        points_cam = Rotation.from_rotvec(v[:3]).apply(X) + v[3:6]
        r = (project(model, camera(v), points_cam) - pixels) / sigmas[:, None]
        return np.where(np.isfinite(r), r, 1e6).ravel()

    start = np.concatenate([Rotation.from_matrix(R).as_rotvec(), t, [fx], [params[radial[0]]] if radial else []])
    try:
        result = least_squares(residuals, start, method="trf", x_scale="jac",
                               loss={"none": "linear"}.get(loss, loss), f_scale=loss_scale)
    except (ValueError, np.linalg.LinAlgError):
        return None
    covariance = _covariance(result.jac)[6:, 6:]
    if not result.success or result.x[6] <= 0:
        return None
    return Rotation.from_rotvec(result.x[:3]).as_matrix(), result.x[3:6], camera(result.x), covariance
