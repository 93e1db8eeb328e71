"""Incremental SfM over one set of images (paper section 3.2: "we choose incremental SfM").

The loop, as COLMAP's incremental mapper: choose an initial pair with many inliers and a wide
triangulation angle (not a homography-dominated pair), reconstruct it from its essential matrix;
then repeatedly register the next best image (most visible triangulated tracks, well spread) by
PnP RANSAC (OpenCV USAC) refined on its inliers; triangulate the tracks it newly sees (batched
multi-view DLT with angle, depth and reprojection checks); run a local BA around it; run a global
BA (and re-triangulation, and filtering of observations above ``max_reproj_error``) whenever the
model has grown by ``global_ba_ratio``.  When no image can be registered any more, a new model is
started from the remaining images: several models are a result, not an error.

State lives in flat numpy arrays over the observations of the tracks (``sfm.mapper.tracks``), so each
step is vectorised; the geometry bookkeeping is in :class:`sfm.mapper.state.MapperState`.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from backend.memory import return_freed_memory
from sfm.mapper.bundle_adjuster import FINAL_TOLERANCE, GROWING_TOLERANCE
from sfm.mapper.payload import MapperInput, MapperOptions
from sfm.mapper.output import log_progress, to_reconstruction
from sfm.mapper.state import MapperState
from sfm.core.model import Reconstruction
from sfm.viz.recorder import Recorder
from sfm.mapper.structureless import register_structureless
from sfm.mapper.triangulation import triangulate_dlt

log = logging.getLogger(__name__)

PLANAR_CONFIGS = (4, 5, 6)  # PLANAR, PANORAMIC, PLANAR_OR_PANORAMIC


def _relative_pose(state: MapperState, i: int, j: int, matches: np.ndarray, seed: int):
    """cam_j_from_cam_i (R, t with |t| = 1) from the matches' essential matrix, and its inliers."""
    x1 = state.norm_of(i, matches[:, 0])
    x2 = state.norm_of(j, matches[:, 1])
    # rows a degenerate camera cannot unproject count as outliers
    kept = np.flatnonzero(np.isfinite(x1).all(axis=1) & np.isfinite(x2).all(axis=1))
    if len(kept) < 8:
        return None
    x1, x2 = x1[kept], x2[kept]
    thr = state.opts.max_reproj_error / np.mean([state.focal(i), state.focal(j)])
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=thr, maxIters=10000)
    if E is None or E.shape != (3, 3):
        return None
    n, R, t, mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    if n < 8:
        return None
    inl = np.zeros(len(matches), dtype=bool)
    inl[kept[mask.ravel() > 0]] = True
    return R, t.ravel() / np.linalg.norm(t), inl


def two_view_score(state: MapperState, i: int, j: int, R: np.ndarray, t: np.ndarray, matches: np.ndarray) -> tuple[int, float]:
    """Points of a candidate initial pair that pass depth and reprojection checks, and their
    median triangulation angle (degrees)."""
    if len(matches) == 0:
        return 0, 0.0
    x = np.concatenate([state.norm_of(i, matches[:, 0]), state.norm_of(j, matches[:, 1])])
    m = len(matches)
    rot = np.concatenate([np.tile(np.eye(3), (m, 1, 1)), np.tile(R, (m, 1, 1))])
    tra = np.concatenate([np.zeros((m, 3)), np.tile(t, (m, 1))])
    order = np.r_[np.arange(m), np.arange(m) + m].reshape(2, m).T.ravel()  # interleave views
    starts = np.arange(0, 2 * m + 1, 2)
    X = triangulate_dlt(rot[order], tra[order], x[order], starts)
    z1 = X[:, 2]
    z2 = (X @ R.T + t)[:, 2]
    proj1 = X[:, :2] / z1[:, None]
    x2c = X @ R.T + t
    proj2 = x2c[:, :2] / z2[:, None]
    err = np.maximum(np.linalg.norm(proj1 - x[:m], axis=1) * state.focal(i), np.linalg.norm(proj2 - x[m:], axis=1) * state.focal(j))
    ok = (z1 > 0) & (z2 > 0) & (err < state.opts.max_reproj_error)
    if ok.sum() == 0:
        return 0, 0.0
    c2 = -R.T @ t
    r1 = X[ok] / np.linalg.norm(X[ok], axis=1, keepdims=True)
    r2 = (X[ok] - c2) / np.linalg.norm(X[ok] - c2, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(np.sum(r1 * r2, axis=1), -1, 1)))
    good = angles >= state.opts.min_tri_angle
    return int(good.sum()), float(np.median(angles))


def ray_angles(state: MapperState, i: int, j: int, R: np.ndarray, matches: np.ndarray) -> np.ndarray:
    """Triangulation angle (degrees) of each match between images ``i`` and ``j`` of relative
    rotation ``R`` (cam_j_from_cam_i), without triangulating: the angle at a point between its
    rays from the two centres is the angle between its viewing directions expressed in one
    frame, whatever the baseline (exact for noise-free matches)."""
    d1 = state.norm_of(i, matches[:, 0])
    d2 = state.norm_of(j, matches[:, 1])
    d1 = np.column_stack([d1, np.ones(len(d1))])
    d2 = np.column_stack([d2, np.ones(len(d2))]) @ R  # rows R^T d2: the rays of j in i's frame
    cos = np.sum(d1 * d2, axis=1) / (np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


# A candidate initial pair whose inliers' median ray angle is below this share of the angle
# threshold is not triangulated unless every threshold relaxation needs it: the median over the
# points that pass the checks is the same angle over slightly fewer rows, far from a 20% gap.
_DEFER_ANGLE_SHARE = 0.8


def _try_initial_pair(state: MapperState, tried: set) -> bool:
    """Find and reconstruct an initial pair among unregistered images.

    Candidates are the pairs with the most inliers (at least ``init_min_num_inliers`` when any
    has that many), up to ``init_max_pairs``; each gets its relative pose once (E).  The pair
    with the most well-triangulated points among those whose median triangulation angle
    reaches ``init_min_tri_angle`` wins; if none does, the angle is halved, up to three times
    (COLMAP relaxes twice; a camera moving forward along a street sees median angles of 2-3
    degrees even between frames a few steps apart, and BA widens the baseline as the model
    grows).  Candidates come in order of inliers and a score never exceeds a pair's inliers, so
    the search stops once a pair passing the first angle threshold scores more than the next
    candidate has inliers: the same winner, fewer two-view reconstructions.  The two-view
    triangulation that scores a pair (:func:`two_view_score`) waits until a threshold needs it
    for pairs whose rays are clearly too parallel for the first one (:func:`ray_angles`): on
    a ring of views, most pairs with many matches are neighbours a few degrees apart."""
    opts = state.opts
    cands = [
        (len(m), i, j, m)
        for (i, j), (m, config) in state.pair_matches.items()
        if not state.registered[i] and not state.registered[j] and not state.used[i] and not state.used[j]
        and (i, j) not in tried and config not in PLANAR_CONFIGS
        and len(m) >= max(opts.abs_pose_min_num_inliers, opts.min_num_matches)
    ]
    cands.sort(key=lambda c: (-c[0], c[1], c[2]))
    if sum(c[0] >= opts.init_min_num_inliers for c in cands) >= 1:
        cands = [c for c in cands if c[0] >= opts.init_min_num_inliers]
    evaluated, deferred = [], []
    best_wide = -1  # best score so far among pairs that pass the first angle threshold

    def score(i, j, R, t, m):
        points, angle = two_view_score(state, i, j, R, t, m)
        log.debug("init candidate %s-%s: %d inliers, median angle %.1f deg, %d points",
                  state.names[i], state.names[j], len(m), angle, points)
        if points >= opts.abs_pose_min_num_inliers:
            evaluated.append((points, angle, i, j, R, t))
        return points, angle

    for n_inl, i, j, m in cands[: opts.init_max_pairs]:
        if best_wide > n_inl:
            break  # a score counts inliers of these matches: no later pair can beat it
        rel = _relative_pose(state, i, j, m, opts.seed)
        if rel is None:
            continue
        R, t, inl = rel
        if np.median(ray_angles(state, i, j, R, m[inl])) < _DEFER_ANGLE_SHARE * opts.init_min_tri_angle:
            deferred.append((i, j, R, t, m[inl]))
            continue
        points, angle = score(i, j, R, t, m[inl])
        if points >= opts.abs_pose_min_num_inliers and angle >= opts.init_min_tri_angle:
            best_wide = max(best_wide, points)
    for min_angle in (opts.init_min_tri_angle, opts.init_min_tri_angle / 2, opts.init_min_tri_angle / 4,
                      opts.init_min_tri_angle / 8):
        if min_angle < opts.init_min_tri_angle:
            for args in deferred:
                score(*args)
            deferred = []
        ok = [e for e in evaluated if e[1] >= min_angle]
        if ok:
            points, angle, i, j, R, t = max(ok, key=lambda e: (e[0], -e[2], -e[3]))
            tried.add((i, j))
            state.start_model(i, j, R, t)
            return True
    return False


def _register_next(state: MapperState) -> bool:
    """Register the best unregistered image that PnP accepts; False when none can be.  After
    the ready candidates come the failed images worth a retry when nothing else registers
    (``MapperState.next_image_candidates(stalled=True)``)."""
    opts = state.opts
    for i in state.next_image_candidates(stalled=True):
        rows, X = state.visible_points(i)
        if len(rows) < opts.abs_pose_min_num_inliers:
            continue
        x = state.obs_norm[rows]
        usac = cv2.UsacParams()
        usac.threshold = opts.abs_pose_max_error / state.focal(i)
        usac.confidence = 0.9999
        usac.maxIterations = 10000
        usac.randomGeneratorState = opts.seed + i
        usac.isParallel = False
        ok, _, rvec, tvec, inliers = cv2.solvePnPRansac(X, x, np.eye(3), None, params=usac)
        if not ok or inliers is None:
            state.note_failure(i, len(rows))
            continue
        inliers = inliers.ravel()
        if len(inliers) < opts.abs_pose_min_num_inliers or len(inliers) < opts.abs_pose_min_inlier_ratio * len(rows):
            state.note_failure(i, len(rows))
            continue
        # Least squares on the RANSAC inliers, in normalised coordinates like the RANSAC (the
        # local BA that follows refines the pose again, robustly and in pixels).
        rvec, tvec = cv2.solvePnPRefineLM(X[inliers], x[inliers], np.eye(3), None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        state.register(i, R, tvec.ravel())
        return True
    return False


def reconstruct_incremental(payload: MapperInput, opts: MapperOptions, recorder: Recorder | None = None) -> list[Reconstruction]:
    """All models incremental SfM makes of ``payload``'s images, largest first."""
    recorder = recorder or Recorder.disabled()
    state = MapperState(payload, opts)
    models: list[Reconstruction] = []
    tried: set = set()
    min_size = opts.smallest_model(len(payload.names))
    while len(models) < opts.max_num_models:
        if not _try_initial_pair(state, tried):
            break
        last_global = state.num_registered
        log_progress(state, recorder)
        # A failed image is retried once it sees 20% more points (cheap on large clusters);
        # when nothing else registers, with any growth (at most MAX_REG_TRIALS failures), then
        # without PnP.
        while _register_next(state) or register_structureless(state, _relative_pose):
            state.triangulate_new(state.last_registered)
            if state.num_registered >= opts.global_ba_ratio * last_global or state.num_registered <= 10:
                state.global_ba()  # covers what the local BA would adjust
                state.retriangulate()
                last_global = state.num_registered
            else:
                state.local_ba(state.last_registered)
            log_progress(state, recorder)
        _final_refinement(state)
        model = to_reconstruction(state)
        n = state.num_registered
        state.close_model()
        if n >= min_size:
            models.append(model)
            log.info("%s: model %d with %d images, %d points", payload.label, len(models) - 1, n, len(model.points3D))
        if int(np.sum(~state.used)) < 2:
            break
    models.sort(key=lambda m: -len(m.images))
    return models


# A second final BA runs when re-triangulation after the first changed more than this share of
# the observations (COLMAP's ba_global_max_refinement_change, 0.0005): below it the second BA
# moves nothing that matters and costs as much as the first.
MAX_REFINEMENT_CHANGE = 0.0005


def _final_refinement(state: MapperState) -> None:
    """Final global BA, re-triangulation, and a second final BA if that changed enough.

    The first BA stops at the growing model's looser tolerance (a relative cost decrease of
    1e-3): re-triangulation usually changes the problem, and the second BA, run to
    ``FINAL_TOLERANCE``, starts from there.  When nothing changed enough, the second BA runs
    only if the first stopped short of ``FINAL_TOLERANCE`` (its last decrease was larger), so
    the last BA of every model reaches it.  On temple_ring the two take 3 + 3 LM iterations
    instead of 6 + 4, for the same model."""
    state.global_ba(final=True, tolerance=GROWING_TOLERANCE)
    first_decrease = state.last_ba_decrease
    before = int(state.obs_inlier.sum())
    state.retriangulate()
    changed = int(state.obs_inlier.sum()) - before
    if changed > MAX_REFINEMENT_CHANGE * max(before, 1) or first_decrease >= FINAL_TOLERANCE:
        state.global_ba(final=True)
    else:
        log.debug("%s: re-triangulation changed %d of %d observations and the first final BA "
                  "converged: no second final BA", state.payload.label, changed, before)


def refine_with_poses(payload: MapperInput, opts: MapperOptions, poses: dict[str, tuple[np.ndarray, np.ndarray]],
                      camera_params: dict[int, np.ndarray]) -> Reconstruction:
    """Global refinement of merged poses (paper Figure 1, after merging): every track of the
    payload is triangulated with the given poses, then global BA and filtering, then
    re-triangulation, and a second global BA only if re-triangulation added more than 2% of
    observations ("in practice, it is enough to perform them once", section 3).  Images
    without a pose stay unregistered.  These BAs keep the local BAs' robust loss scale
    (``opts.loss_scale``, 1 px), as the merged clusters' own global BAs do
    (``MapperOptions.global_loss_scale``): the merged tracks were filtered against poses moved
    by similarity transforms, not by a BA over them; on the synthetic aerial block at 500
    images the inlier threshold here and in the clusters gave 0.0282 deg, 1 px here only
    0.0212, 1 px throughout 0.0211."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # nothing would register the dropped images again
    state.release_pairs()
    del payload  # the caller passes its only reference: the matches go with it
    return_freed_memory()
    for c, key in enumerate(state.cam_keys):
        if key in camera_params:
            state.params[c] = np.asarray(camera_params[key], dtype=np.float64)
    state.apply_params()
    for i, name in enumerate(state.names):
        if name in poses:
            state.R[i], state.t[i] = poses[name]
            state.registered[i] = True
    state.num_registered = int(state.registered.sum())
    state.retriangulate()
    state.global_ba(final=True, loss_scale=opts.loss_scale)
    before = int(state.obs_inlier.sum())
    state.retriangulate()
    if state.obs_inlier.sum() > 1.02 * before:
        state.global_ba(final=True, loss_scale=opts.loss_scale)
    return to_reconstruction(state)
