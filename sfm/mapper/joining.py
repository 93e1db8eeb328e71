"""Joining a finished model to the model being grown when they share no image.

Incremental SfM starts a new model when no remaining image sees enough of the current model's
points; on a ring photographed in few, wide steps, or with a weakly textured side, the models
that result are arcs of the same ring that meet in pairs of images matched to each other but
seeing too few of each other's points for PnP (``abs_pose_min_num_inliers``).  The merge
(paper section 3.2.1) aligns models through common cameras, which such arcs do not have:
each image is in one model only.  COLMAP's global mapper places them all from the pairwise
geometry; here, as COLMAP's incremental mapper registers one image from its 2D-3D matches,
a finished model is registered as one rigid body, seven degrees of freedom (a similarity), from
all the 2D-3D matches between the two models at once:

- the rotation between the two frames from the essential matrix of a pair of images, one in
  each model, matched to each other (``pose_from_essential``); each such pair with at least
  ``abs_pose_min_num_inliers`` verified matches proposes one;
- then the scale and translation, linear given the rotation, from every observation in one
  model's images of a point the other model triangulated: each ray through a point constrains
  them by two equations (its cross product with the point's direction), by RANSAC over pairs of
  rays, inliers within ``abs_pose_max_error`` pixels (PnP's registration threshold), refitted on
  the inliers.

The similarity is accepted on PnP's terms for one image (at least ``abs_pose_min_num_inliers``
inliers and ``abs_pose_min_inlier_ratio`` of the rays), with inliers in at least two images:
rays from one image alone fix that image's pose in the other frame, not the scale between the
frames.  The finished model's images are then registered with their poses carried over, its
cameras take its intrinsics where it holds more of their images, and the model grows on as one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from backend.camera_models import focal_lengths, unproject
from sfm.mapper.initialization import pose_from_essential
from sfm.mapper.state import MapperState, focal_ratio_beyond

log = logging.getLogger(__name__)

# Random pairs of rays a RANSAC over the scale and translation draws at most (all pairs when
# there are fewer: the rays between two models that PnP could not join are a few dozen).
MAX_SAMPLES = 2000
# Rotation candidates tried: the pairs across the two models with the most verified matches.
MAX_ROTATION_PAIRS = 5


@dataclass
class FinishedModel:
    """A model of this state that was closed: its images (``images``) and their
    ``cam_from_world`` poses, its points (``tracks`` of the state, at ``xyz``), its cameras'
    parameters, and ``kept``: the model as the mapper returns it, or None when it was too small
    to keep.  Only what the model holds is stored: a cluster that closes many small models
    keeps memory in proportion to their points, not to the state's tracks each."""

    images: np.ndarray  # state image indices
    R: np.ndarray  # (len(images), 3, 3)
    t: np.ndarray
    tracks: np.ndarray  # state track indices
    xyz: np.ndarray  # (len(tracks), 3)
    params: list[np.ndarray]
    kept: object | None = None
    growth_index: int | None = None
    start_focals: dict[int, float] = field(default_factory=dict)  # camera index -> focal length it grew from

    @classmethod
    def of(cls, state: MapperState, kept=None, growth_index: int | None = None) -> FinishedModel:
        images, tracks = np.flatnonzero(state.registered), np.flatnonzero(state.track_valid)
        return cls(images, state.R[images].copy(), state.t[images].copy(), tracks, state.track_xyz[tracks].copy(),
                   [p.copy() for p in state.params], kept, growth_index,
                   {c: state.start_focal(c) for c in np.unique(state.cam_index[images]).tolist()})

    @property
    def size(self) -> int:
        return len(self.images)

    def grew_far_from(self, focals: dict[int, float], ratio: float) -> bool:
        """Whether this model grew from a focal length more than ``ratio`` away (either way) from
        the value ``focals`` (camera index -> focal length) gives one of its cameras."""
        return any(c in self.start_focals and focal_ratio_beyond(f, self.start_focals[c], ratio) for c, f in focals.items())

    def arrays(self, state: MapperState) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(registered, R, t, track_valid, track_xyz)`` over all of the state's images and
        tracks, as the state holds its current model."""
        n = len(state.names)
        registered = np.zeros(n, bool)
        registered[self.images] = True
        R, t = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
        R[self.images], t[self.images] = self.R, self.t
        valid = np.zeros(state.num_tracks, bool)
        valid[self.tracks] = True
        xyz = np.full((state.num_tracks, 3), np.nan)
        xyz[self.tracks] = self.xyz
        return registered, R, t, valid, xyz


@dataclass(frozen=True)
class Similarity:
    """``x_current = scale * R @ x_finished + t``, and the rays it was accepted on."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    inliers: int
    rays: int


@dataclass(frozen=True)
class _Arrays:
    """A finished model over all of the state's images and tracks (``FinishedModel.arrays``)."""

    registered: np.ndarray
    R: np.ndarray
    t: np.ndarray
    track_valid: np.ndarray
    track_xyz: np.ndarray
    params: list[np.ndarray]

    @property
    def size(self) -> int:
        return int(self.registered.sum())


def _rays(state: MapperState, model_registered: np.ndarray, model_params: list[np.ndarray],
          points_valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the images ``model_registered`` whose tracks are triangulated in
    ``points_valid``, and their normalised coordinates under ``model_params`` (each model's
    rays with its own calibration, which its poses fit)."""
    rows = np.flatnonzero(model_registered[state.obs_image] & points_valid[state.obs_track])
    norm = np.zeros((len(rows), 2))
    cams = state.cam_index[state.obs_image[rows]]
    for c in np.unique(cams).tolist():
        sel = cams == c
        norm[sel] = unproject(state.priors[c].model, model_params[c], state.obs_px[rows[sel]])
    ok = np.isfinite(norm).all(axis=1)
    return rows[ok], norm[ok]


def _skew(v: np.ndarray) -> np.ndarray:
    """(m, 3, 3) cross-product matrices of (m, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def estimate_similarity(state: MapperState, finished: FinishedModel, seed: int = 0) -> tuple[Similarity | None, str]:
    """The similarity from ``finished``'s frame to the current model's (module docstring) and
    ``""``; or None and why not, in words, for the report and the recording: the step that fell
    short (no pair across the two models with enough matches, no relative pose from those
    pairs, too few rays between the models, too few of them fitting one similarity)."""
    opts = state.opts
    rotations, why = _rotation_candidates(state, finished, seed)
    if not rotations:
        return None, why  # before the finished model's tracks are expanded
    model = _Arrays(*finished.arrays(state), finished.params)
    cur_rows, cur_x = _rays(state, state.registered, state.params, model.track_valid)  # finished's points, current rays
    fin_rows, fin_x = _rays(state, model.registered, model.params, state.track_valid)  # current points, finished rays
    rays = len(cur_rows) + len(fin_rows)
    if rays < opts.abs_pose_min_num_inliers:
        return None, (f"their images see {rays} of each other's points, fewer than the "
                      f"{opts.abs_pose_min_num_inliers} a registration needs")
    if len(np.unique(np.concatenate([state.obs_image[cur_rows], state.obs_image[fin_rows]]))) < 2:
        return None, (f"the {rays} rays between them are all in one image, which they place in the other "
                      "frame without the scale between the frames")
    best: Similarity | None = None
    most = 0  # the most rays one similarity fitted, accepted or not
    for R in rotations:
        found, fitted = _scale_and_translation(state, model, R, (cur_rows, cur_x), (fin_rows, fin_x), seed)
        most = max(most, fitted)
        if found is not None and (best is None or found.inliers > best.inliers):
            best = found
    if best is None:
        return None, (f"at most {most} of the {rays} rays between them fit one similarity within "
                      f"{opts.abs_pose_max_error:g} px; joining needs {opts.abs_pose_min_num_inliers}, "
                      f"{opts.abs_pose_min_inlier_ratio:.0%} of the rays, in two images or more")
    return best, ""


def _rotation_candidates(state: MapperState, finished: FinishedModel, seed: int) -> tuple[list[np.ndarray], str]:
    """``R`` (finished frame to current frame) from the essential matrices of the pairs across
    the two models with the most verified matches, each with at least
    ``abs_pose_min_num_inliers`` of them and of the essential matrix's inliers; with none, why
    not in words.  The pairs are found in one vectorised pass: a cluster that closes many small
    models asks this of each at every model's end."""
    opts = state.opts
    if not state.pair_matches:
        return [], "no verified matches between their images are held"
    keys = list(state.pair_matches)
    pairs = np.array(keys, dtype=np.int64)
    sizes = np.fromiter((len(m) for m, _ in state.pair_matches.values()), np.int64, len(keys))
    position = np.full(len(state.names), -1)  # image -> its row in the finished model's arrays
    position[finished.images] = np.arange(finished.size)
    a, b = pairs[:, 0], pairs[:, 1]
    forward = (position[a] >= 0) & state.registered[b]  # (finished, current)
    linked = forward | ((position[b] >= 0) & state.registered[a])
    across = linked & (sizes >= opts.abs_pose_min_num_inliers)
    if not across.any():
        most = f" (the most: {int(sizes[linked].max())})" if linked.any() else ""
        return [], f"no image pair across them has {opts.abs_pose_min_num_inliers}+ verified matches{most}"
    candidates = []
    tried = sorted(np.flatnonzero(across).tolist(), key=lambda p: (-sizes[p], keys[p]))[:MAX_ROTATION_PAIRS]
    for p in tried:
        m = state.pair_matches[keys[p]][0]
        k, i, m = (a[p], b[p], m) if forward[p] else (b[p], a[p], m[:, ::-1])
        ck, ci = state.cam_index[k], state.cam_index[i]
        xk = unproject(state.priors[ck].model, finished.params[ck], np.asarray(state.payload.keypoints[k], float)[m[:, 0], :2])
        xi = unproject(state.priors[ci].model, state.params[ci], np.asarray(state.payload.keypoints[i], float)[m[:, 1], :2])
        focal = np.mean([state.camera_focal(ci), state.camera_focal(ck)])
        rel = pose_from_essential(xk, xi, opts.max_reproj_error / focal, seed + int(k))
        if rel is None or int(rel[2].sum()) < opts.abs_pose_min_num_inliers:
            continue
        candidates.append(state.R[i].T @ rel[0] @ finished.R[position[k]])  # rel[0]: cam_i from cam_k
    if not candidates:
        return [], (f"no pair across them gives a relative pose with {opts.abs_pose_min_num_inliers}+ inliers "
                    f"({len(tried)} tried)")
    return candidates, ""


def _scale_and_translation(state: MapperState, finished: _Arrays, R: np.ndarray, current_rays, finished_rays,
                           seed: int) -> tuple[Similarity | None, int]:
    """RANSAC over pairs of rays for ``(scale, t)`` given ``R``, refitted on the inliers: the
    similarity where the acceptance terms allow it, and how many rays it fitted (0: none)."""
    opts = state.opts
    (cur_rows, cur_x), (fin_rows, fin_x) = current_rays, finished_rays
    # current image i sees finished point X: [x]x R_i (s R X + t) = -[x]x t_i
    img_c = state.obs_image[cur_rows]
    X = finished.track_xyz[state.obs_track[cur_rows]]
    xc = np.column_stack([cur_x, np.ones(len(cur_x))])
    Sc = _skew(xc) @ state.R[img_c]
    A1 = np.concatenate([(Sc @ (R @ X.T).T[:, :, None]), Sc], axis=2)  # (m, 3, 4)
    b1 = -(_skew(xc) @ state.t[img_c][:, :, None])[:, :, 0]
    # finished image k sees current point Y: [x]x (Q (Y - t) + s t_k) = 0, Q = R_k R^T
    img_f = state.obs_image[fin_rows]
    Y = state.track_xyz[state.obs_track[fin_rows]]
    xf = np.column_stack([fin_x, np.ones(len(fin_x))])
    Q = finished.R[img_f] @ R.T
    Sf = _skew(xf)
    A2 = np.concatenate([(Sf @ finished.t[img_f][:, :, None]), -(Sf @ Q)], axis=2)
    b2 = -(Sf @ (Q @ Y[:, :, None]))[:, :, 0]
    A, b = np.concatenate([A1, A2]), np.concatenate([b1, b2])
    image_of_ray = np.concatenate([img_c, img_f])
    focal = np.array([state.camera_focal(c) for c in range(len(state.priors))])
    fin_focal = np.array([np.mean(focal_lengths(state.priors[c].model, finished.params[c])) for c in range(len(state.priors))])

    x_all = np.concatenate([cur_x, fin_x])
    f_all = np.concatenate([focal[state.cam_index[img_c]], fin_focal[state.cam_index[img_f]]])

    def errors(scale: float, t: np.ndarray) -> np.ndarray:
        """Pixel reprojection error of every ray (inf behind its camera)."""
        p = np.concatenate([np.einsum("nij,nj->ni", state.R[img_c], scale * X @ R.T + t) + state.t[img_c],
                            np.einsum("nij,nj->ni", Q, Y - t) + scale * finished.t[img_f]])
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(p[:, :2] / p[:, 2:] - x_all, axis=1) * f_all
        return np.where(p[:, 2] > 0, err, np.inf)

    def solve(idx: np.ndarray):
        sol, *_ = np.linalg.lstsq(A[idx].reshape(-1, 4), b[idx].reshape(-1), rcond=None)
        return float(sol[0]), sol[1:]

    rng = np.random.default_rng(seed)
    m = len(A)
    all_pairs = m * (m - 1) // 2
    if all_pairs <= MAX_SAMPLES:
        first, second = np.triu_indices(m, 1)
    else:
        first, second = rng.integers(0, m, MAX_SAMPLES), rng.integers(0, m, MAX_SAMPLES)
        keep = first != second
        first, second = first[keep], second[keep]
    best_inl, best_count = None, 0
    for a_, b_ in zip(first.tolist(), second.tolist()):
        if image_of_ray[a_] == image_of_ray[b_]:
            continue  # two rays of one image do not fix the scale
        scale, t = solve(np.array([a_, b_]))
        if not scale > 0:
            continue
        inl = errors(scale, t) < opts.abs_pose_max_error
        if inl.sum() > best_count:
            best_inl, best_count = inl, int(inl.sum())
    if best_inl is None:
        return None, 0
    for _ in range(2):  # refit on the inliers, count again
        scale, t = solve(np.flatnonzero(best_inl))
        if not scale > 0:
            return None, best_count
        best_inl = errors(scale, t) < opts.abs_pose_max_error
    count = int(best_inl.sum())
    if (count < opts.abs_pose_min_num_inliers or count < opts.abs_pose_min_inlier_ratio * m
            or len(np.unique(image_of_ray[best_inl])) < 2):
        return None, count
    return Similarity(scale, R, t, count, m), count


def join(state: MapperState, finished: FinishedModel, sim: Similarity) -> np.ndarray:
    """Make the union of the current model and ``finished`` the current model, in the frame and
    with the points of the larger of the two; the other's images are registered with their
    poses carried over by ``sim`` and their tracks triangulated again at the next
    re-triangulation.  Each camera takes the intrinsics of the model that holds more of its
    images.  Returns the images the current model did not hold."""
    current = state.registered.copy()
    state.used[finished.images] = False  # no longer a finished model's: the current one's, free if it drops them
    finished = _Arrays(*finished.arrays(state), finished.params)
    params = [finished.params[c] if np.sum(finished.registered & (state.cam_index == c)) > np.sum(current & (state.cam_index == c))
              else state.params[c] for c in range(len(state.priors))]
    if finished.size > int(current.sum()):  # the current model moves into the finished one's frame
        R_cur, t_cur = state.R.copy(), state.t.copy()
        state.load_model(finished.registered, finished.R, finished.t, finished.track_xyz, finished.track_valid, params)
        for i in np.flatnonzero(current & ~finished.registered).tolist():
            state.register(i, R_cur[i] @ sim.R, (R_cur[i] @ sim.t + t_cur[i]) / sim.scale)
    else:
        for c, p in enumerate(params):
            if p is not state.params[c]:
                state.set_intrinsics(c, p)
        for k in np.flatnonzero(finished.registered & ~current).tolist():
            Q = finished.R[k] @ sim.R.T
            state.register(k, Q, sim.scale * finished.t[k] - Q @ sim.t)
    return np.flatnonzero(state.registered & ~current)
