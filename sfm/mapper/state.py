"""The state of incremental SfM in flat arrays over track observations, and its geometry steps.

Observation rows come from ``sfm.mapper.tracks`` (grouped by track).  Per row: image, keypoint, pixel,
normalised coordinates (distortion removed with the current intrinsics) and whether the row is
an inlier of its track's 3D point.  Per track: position and validity.  Per image: pose
``cam_from_world`` and registration.  Every step (triangulation, filtering, BA assembly) is a
vectorised operation on these arrays.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from backend.camera_models import focal_lengths, has_bogus_params, model_spec, reprojection_errors, unproject
from sfm.mapper.payload import MapperInput
from sfm.mapper.options import MapperOptions
from sfm.features.sift import localization_sigma
from sfm.mapper.tracks import build_tracks, keypoint_match_counts, two_view_tracks, work_cuts
from sfm.mapper.triangulation import depths, max_triangulation_angles, triangulate_dlt

log = logging.getLogger(__name__)

# Track rows triangulated or refined at once: the per-row temporaries stay bounded whatever
# the model's size.
ROW_CHUNK = 250_000
MAX_REG_TRIALS = 3  # failures after which a stalled model stops retrying an image (COLMAP's max_reg_trials)
# Registered images from which a camera with degenerate intrinsics takes its images out of the
# model (COLMAP's IncrementalMapper::FilterImages waits for 20).
MIN_IMAGES_FOR_CAMERA_FILTER = 20
# Points an image must keep to stay in the model: a pose has six unknowns and a point gives two
# equations, so fewer than three (P3P's minimum) leave the pose undetermined.
MIN_POSE_POINTS = 3


def focal_ratio_beyond(focal: float, other: float, ratio: float) -> bool:
    """Whether two focal lengths are more than ``ratio`` apart, either way."""
    return bool(abs(np.log(focal / other)) > np.log(ratio))


def track_rows(starts: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the given tracks (concatenated) and the position of each row's track in ``tracks``."""
    lengths = starts[tracks + 1] - starts[tracks]
    owner = np.repeat(np.arange(len(tracks)), lengths)
    first = np.repeat(starts[tracks], lengths)
    offset = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return first + offset, owner


class MapperState:
    """Arrays and steps of one incremental reconstruction (see the module docstring).  Its
    bundle adjustments are run by a :class:`sfm.mapper.bundle_adjuster.BundleAdjuster`, which
    writes back through :meth:`apply_adjustment`."""

    def __init__(self, payload: MapperInput, opts: MapperOptions) -> None:
        self.payload, self.opts = payload, opts
        self.names = payload.names
        n = len(payload.names)
        self.cam_keys = sorted(payload.cameras)
        key_index = {c: k for k, c in enumerate(self.cam_keys)}
        self.cam_index = np.array([key_index[c] for c in payload.camera_ids], dtype=np.int64)
        self.priors = [payload.cameras[c] for c in self.cam_keys]
        self.params = [np.array(c.params, dtype=np.float64) for c in self.priors]
        self.pair_matches = {
            (int(i), int(j)): (np.asarray(m), int(cfg))
            for i, j, m, cfg in payload.pairs
            if len(m) >= opts.min_num_matches
        }
        tracks = build_tracks([len(k) for k in payload.keypoints], ((i, j, m) for (i, j), (m, _) in self.pair_matches.items()))
        self.starts = tracks.starts
        self.obs_image, self.obs_kp = tracks.image, tracks.keypoint
        self.obs_track = tracks.track_of_observation()
        order = np.argsort(self.obs_image, kind="stable")
        bounds = np.searchsorted(self.obs_image[order], np.arange(n + 1))
        self.image_rows = [order[bounds[i] : bounds[i + 1]] for i in range(n)]
        self.obs_px = np.zeros((len(self.obs_image), 2))
        self.obs_sigma = np.ones(len(self.obs_image))  # pixel std of each row in BA
        for i, rows in enumerate(self.image_rows):
            if len(rows):
                kp = np.asarray(payload.keypoints[i], dtype=np.float64)[self.obs_kp[rows]]
                self.obs_px[rows] = kp[:, :2]
                if opts.scale_weights and kp.shape[1] == 3:
                    self.obs_sigma[rows] = localization_sigma(kp[:, 2])
        self.obs_norm = np.zeros_like(self.obs_px)
        cams = self.cam_index[self.obs_image]  # the rows of each camera, grouped once
        order = np.argsort(cams, kind="stable")
        bounds = np.searchsorted(cams[order], np.arange(len(self.priors) + 1))
        self._camera_rows = [order[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
        self._update_normalised()
        self.num_tracks = tracks.num_tracks
        counts = payload.match_counts
        if counts is None:  # the payload's own pairs are the whole database
            counts = keypoint_match_counts([len(k) for k in payload.keypoints],
                                           ((i if side == 0 else j, m[:, side])
                                            for (i, j), (m, _) in self.pair_matches.items() for side in (0, 1)))
        self.two_view_track = two_view_tracks(tracks, counts)
        self.used = np.zeros(n, dtype=bool)  # belongs to a finished model
        # de-register the images of cameras whose intrinsics became degenerate (off when no
        # registration follows, as in the refinement of merged poses)
        self.camera_filter = True
        self.start_focals: dict[int, float] = {}  # camera index -> focal length a new model starts from
        self._reset_model()
        log.debug("%s: %d images, %d pairs, %d tracks, %d observations", payload.label, n,
                  len(self.pair_matches), self.num_tracks, len(self.obs_image))

    def release_pairs(self, keep: np.ndarray | None = None) -> None:
        """Drop the verified matches once the tracks are built, for a caller that picks no
        initial pair again (the refinement of merged poses): on a large merged model they are a
        large share of its memory.  ``keep``: images whose pairs stay, for the structure-less
        registration of those images (``sfm.mapper.structureless``)."""
        if keep is None or not len(keep):
            self.pair_matches = {}
        else:
            kept = np.zeros(len(self.names), bool)
            kept[keep] = True
            self.pair_matches = {(a, b): m for (a, b), m in self.pair_matches.items() if kept[a] or kept[b]}
        self.payload = dataclasses.replace(self.payload, pairs=[])

    # ------------------------------------------------------------------ bookkeeping
    def _reset_model(self) -> None:
        n = len(self.names)
        self.registered = np.zeros(n, dtype=bool)
        self.R = np.tile(np.eye(3), (n, 1, 1))
        self.t = np.zeros((n, 3))
        self.track_xyz = np.full((self.num_tracks, 3), np.nan)
        self.track_valid = np.zeros(self.num_tracks, dtype=bool)
        self.obs_inlier = np.zeros(len(self.obs_image), dtype=bool)
        self.num_registered = 0
        self.last_registered = -1
        # registration failures of this model: count and points seen at the last one (PnP),
        # points seen when structure-less registration last failed
        self.failed = np.zeros(n, dtype=np.int64)
        self.fail_visible = np.zeros(n, dtype=np.int64)
        self.structureless_failed: dict[int, int] = {}
        self.unsupported = np.zeros(n, dtype=np.int64)  # drops for too few points (drop_unsupported_images)
        self.params = [np.array(c.params, dtype=np.float64) for c in self.priors]
        for c, focal in self.start_focals.items():
            self.params[c] = self._with_focal(c, focal)
        self._update_normalised()

    def set_camera_params(self, params_by_key: dict[int, np.ndarray]) -> None:
        """Intrinsics of the cameras named by key (``cam_keys``) from outside the model (the
        merged clusters' cameras); normalised coordinates follow."""
        changed = [c for c, key in enumerate(self.cam_keys) if key in params_by_key]
        for c in changed:
            self.params[c] = np.asarray(params_by_key[self.cam_keys[c]], dtype=np.float64)
        self._update_normalised(changed)

    def new_camera_level(self, c: int) -> str | None:
        """What registering an image of camera ``c`` estimates of the camera with the pose
        (``sfm.mapper.registration``): "focal", or "focal_radial", as ``intrinsics_refinement``
        allows; None when the camera is held (given intrinsics, or ``intrinsics_refinement``
        none) or a registered image of the model already uses it (its intrinsics are then the
        model's estimate)."""
        level = self.opts.intrinsics_refinement
        if self.priors[c].fixed or level == "none" or self.registered[self.cam_index == c].any():
            return None
        return "focal" if level == "focal" else "focal_radial"

    def reset_camera(self, c: int) -> None:
        """Camera ``c`` back to its prior (normalised coordinates follow)."""
        self.set_intrinsics(c, self.priors[c].params)

    def set_focal(self, c: int, focal: float) -> None:
        """Camera ``c`` with focal length ``focal`` (both focal lengths scaled alike)."""
        self.set_intrinsics(c, self._with_focal(c, focal))

    def _with_focal(self, c: int, focal: float) -> np.ndarray:
        """Camera ``c``'s parameters with its focal lengths scaled alike to mean ``focal``."""
        params = np.array(self.params[c], dtype=np.float64)
        params[list(model_spec(self.priors[c].model).focal_idx)] *= focal / self.camera_focal(c)
        return params

    def set_intrinsics(self, c: int, params: np.ndarray) -> None:
        """Camera ``c`` with ``params`` (normalised coordinates follow)."""
        self.params[c] = np.array(params, dtype=np.float64)
        self._update_normalised([c])

    def set_poses(self, poses: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Register the named images with the given ``cam_from_world`` poses (the merged
        clusters' poses); the other images stay unregistered."""
        for i, name in enumerate(self.names):
            if name in poses:
                self.R[i], self.t[i] = poses[name]
                self.registered[i] = True
        self.num_registered = int(self.registered.sum())

    def set_points(self, tracks: np.ndarray, xyz: np.ndarray) -> None:
        self.track_xyz[tracks] = xyz

    def seed_points(self, names: list[str], keypoints: np.ndarray, point_of_row: np.ndarray,
                    xyz: np.ndarray) -> int:
        """Points given from outside the model (the merged clusters' own points, moved into the
        merged frame): row ``k`` says that keypoint ``keypoints[k]`` of image ``names[k]``
        observes point ``point_of_row[k]`` at ``xyz[point_of_row[k]]``.  Each track not yet
        valid takes, of the given points with at least two rows in registered images on it, the
        one with the most such rows (the best determined; the first given among equals), and
        those rows become its inliers.  Returns the number of tracks seeded."""
        index = {name: i for i, name in enumerate(self.names)}
        image = np.array([index.get(n, -1) for n in names], dtype=np.int64)
        kp = np.asarray(keypoints, dtype=np.int64)
        point = np.asarray(point_of_row, dtype=np.int64)
        known = image >= 0
        image, kp, point = image[known], kp[known], point[known]
        width = int(max(self.obs_kp.max(initial=0), kp.max(initial=0))) + 1
        keys = self.obs_image.astype(np.int64) * width + self.obs_kp
        order = np.argsort(keys, kind="stable")
        at = np.searchsorted(keys[order], image * width + kp)
        found = (at < len(keys)) & (keys[order[np.minimum(at, len(keys) - 1)]] == image * width + kp)
        rows, point = order[at[found]], point[found]
        keep = self.registered[self.obs_image[rows]]
        rows, point = rows[keep], point[keep]
        track = self.obs_track[rows]
        tracks_points, counts = np.unique(np.stack([track, point], axis=1), axis=0, return_counts=True)
        usable = (counts >= 2) & ~self.track_valid[tracks_points[:, 0]]
        tracks_points, counts = tracks_points[usable], counts[usable]
        # each track's point with the most rows on it, the first given among equals
        order = np.lexsort((tracks_points[:, 1], -counts, tracks_points[:, 0]))
        tracks_points = tracks_points[order]
        first = np.unique(tracks_points[:, 0], return_index=True)[1]
        chosen = tracks_points[first]
        seed_of = np.full(self.num_tracks, -1, dtype=np.int64)
        seed_of[chosen[:, 0]] = chosen[:, 1]
        self.obs_inlier[rows[seed_of[track] == point]] = True
        self.track_xyz[chosen[:, 0]] = np.asarray(xyz, dtype=np.float64)[chosen[:, 1]]
        self.track_valid[chosen[:, 0]] = True
        return len(chosen)

    def apply_adjustment(self, images: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                         tracks: np.ndarray, xyz: np.ndarray, cams: np.ndarray | None,
                         camera_params) -> None:
        """A bundle adjustment's result: poses of ``images``, points of ``tracks`` and, unless
        ``cams`` is None, the intrinsics of those cameras (normalised coordinates follow)."""
        self.R[images], self.t[images] = rotations, translations
        self.track_xyz[tracks] = xyz
        if cams is not None:
            for c, p in zip(cams, camera_params):
                self.params[c] = np.asarray(p, dtype=np.float64)
            self._update_normalised(cams)

    def load_model(self, registered: np.ndarray, R: np.ndarray, t: np.ndarray, track_xyz: np.ndarray,
                   track_valid: np.ndarray, params: list[np.ndarray]) -> None:
        """Make the model closed earlier with these arrays the current one (``sfm.mapper.joining``):
        its images registered at their poses, its points, the cameras at ``params``; its
        observations are inliers where they reproject within ``max_reproj_error``."""
        self._reset_model()
        self.registered[:] = registered
        self.num_registered = int(registered.sum())
        self.R[registered], self.t[registered] = R[registered], t[registered]
        self.track_xyz[:], self.track_valid[:] = track_xyz, track_valid
        self.params = [np.array(p, dtype=np.float64) for p in params]
        self._update_normalised()
        rows = np.flatnonzero(registered[self.obs_image] & track_valid[self.obs_track])
        rows = rows[np.isfinite(self.obs_norm[rows]).all(axis=1)]
        self.obs_inlier[rows] = self.reprojection_errors(rows, self.track_xyz[self.obs_track[rows]]) < self.opts.max_reproj_error

    def close_model(self) -> None:
        """The current model is finished: its images belong to it, and the next model starts
        from the same focal lengths as this one."""
        self.used |= self.registered
        self._reset_model()

    def restart_model(self, focals: dict[int, float]) -> None:
        """Discard the current model, its images free again, and start it again, and every
        later model of this state, with the cameras of ``focals`` (camera index -> focal length)
        at those focal lengths: a guess one model of a camera rejected is rejected for all."""
        self.start_focals.update(focals)
        self._reset_model()

    def free_images(self, images: np.ndarray) -> None:
        """Images of a finished model that was taken apart: later models may register them."""
        self.used[images] = False

    def start_focal(self, c: int) -> float:
        """The focal length camera ``c`` started the current model from: its prior, or the value
        a restart gave it."""
        prior = self.priors[c]
        return self.start_focals.get(c, float(np.mean(focal_lengths(prior.model, prior.params))))

    def guessed_focal_moves(self, ratio: float) -> dict[int, float]:
        """The cameras whose focal length the model started from a guess (no EXIF, not given) and
        whose current focal length differs from that start by more than ``ratio`` (either way),
        among those with at least three registered images (a camera per image has its focal
        length searched when it registers): camera index -> current focal length."""
        moved = {}
        for c, prior in enumerate(self.priors):
            if prior.fixed or prior.prior_focal_length or np.sum(self.registered & (self.cam_index == c)) < 3:
                continue
            if focal_ratio_beyond(self.camera_focal(c), self.start_focal(c), ratio):
                moved[c] = self.camera_focal(c)
        return moved

    def _update_normalised(self, cameras=None) -> None:
        """The normalised coordinates of the rows of ``cameras`` (None: every camera) from their
        current intrinsics."""
        for c in range(len(self.priors)) if cameras is None else cameras:
            rows = self._camera_rows[c]
            if len(rows):
                self.obs_norm[rows] = unproject(self.priors[c].model, self.params[c], self.obs_px[rows])

    def camera_of(self, i: int):
        return self.priors[self.cam_index[i]]

    def focal(self, i: int) -> float:
        return self.camera_focal(self.cam_index[i])

    def camera_focal(self, c: int) -> float:
        return float(np.mean(focal_lengths(self.priors[c].model, self.params[c])))

    def norm_of(self, i: int, keypoints: np.ndarray) -> np.ndarray:
        prior = self.camera_of(i)
        kp = np.asarray(self.payload.keypoints[i], dtype=np.float64)[keypoints, :2]
        return unproject(prior.model, self.params[self.cam_index[i]], kp)

    def centers(self, images: np.ndarray) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.R[images], self.t[images])

    def reprojection_errors(self, rows: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Pixel error of each row against the point ``xyz`` (per row); inf behind the camera."""
        return reprojection_errors([p.model for p in self.priors], self.params, self.cam_index, self.R, self.t,
                                   self.obs_image[rows], xyz, self.obs_px[rows])

    # ------------------------------------------------------------------ initial pair
    def start_model(self, i: int, j: int, R: np.ndarray, t: np.ndarray) -> None:
        self.R[i], self.t[i] = np.eye(3), np.zeros(3)
        self.R[j], self.t[j] = R, t
        self.registered[[i, j]] = True
        self.num_registered = 2
        self.last_registered = j
        self.triangulate_new(j)
        log.info("%s: initial pair %s - %s, %d points", self.payload.label, self.names[i], self.names[j], int(self.track_valid.sum()))

    # ------------------------------------------------------------------ registration
    def next_image_candidates(self, stalled: bool = False) -> list[int]:
        """Unregistered images ordered by how many triangulated points they see and how well
        spread those are (distinct cells of a 16 x 16 grid), retrying failed ones only once
        they see 20% more points than at their last failure.  With ``stalled``, the failed
        images that see any more points, while they failed fewer than ``MAX_REG_TRIALS``
        times, follow in the same order: what to try when nothing else registers, from the
        same pass over the images."""
        ready, retry = [], []
        for i in np.flatnonzero(~self.registered & ~self.used):
            vis, _ = self.visible_points(i)
            if len(vis) < self.opts.abs_pose_min_num_inliers:
                continue
            queue = ready
            if self.failed[i] and len(vis) <= 1.2 * self.fail_visible[i]:
                if not (stalled and self.failed[i] < MAX_REG_TRIALS and len(vis) > self.fail_visible[i]):
                    continue
                queue = retry
            prior = self.camera_of(i)
            cells = np.unique((self.obs_px[vis] // [prior.width / 16, prior.height / 16]) @ [1, 16])
            queue.append((-len(cells), -len(vis), int(i)))
        return [i for _, _, i in sorted(ready) + sorted(retry)]

    def visible_points(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        rows = self.image_rows[i]
        rows = rows[self.track_valid[self.obs_track[rows]] & np.isfinite(self.obs_norm[rows]).all(axis=1)]
        return rows, self.track_xyz[self.obs_track[rows]]

    def note_failure(self, i: int, visible: int) -> None:
        self.failed[i] += 1
        self.fail_visible[i] = visible

    def register(self, i: int, R: np.ndarray, t: np.ndarray) -> None:
        self.R[i], self.t[i] = R, t
        self.registered[i] = True
        self.num_registered += 1
        self.last_registered = i
        rows, X = self.visible_points(i)
        self.obs_inlier[rows] = self.reprojection_errors(rows, X) < self.opts.max_reproj_error

    # ------------------------------------------------------------------ triangulation
    def _triangulate_tracks(self, tracks: np.ndarray) -> int:
        """(Re)triangulate tracks from their rows in registered images; a row is kept if it
        reprojects within ``max_reproj_error`` in front of the camera, a point if it keeps two
        rows and a triangulation angle >= ``min_tri_angle``.  Two passes: all rows, then the
        inliers of the first pass.  With ``ignore_two_view_tracks``, two-view tracks
        (:func:`sfm.mapper.tracks.two_view_tracks`) are left out once the model has more than
        its initial pair.  Returns the number of new valid points."""
        lengths = self.starts[tracks + 1] - self.starts[tracks]
        if self.opts.ignore_two_view_tracks and self.num_registered > 2:
            # COLMAP's tri_ignore_two_view_tracks: a match no third image confirms is a weak,
            # unchecked constraint; only the initial pair (nothing else to see yet) takes them.
            kept = ~self.two_view_track[tracks]
            tracks, lengths = tracks[kept], lengths[kept]
        cuts = work_cuts(np.cumsum(lengths), ROW_CHUNK)  # chunks: bounded temporaries
        return sum(self._triangulate_chunk(tracks[a:b]) for a, b in zip(cuts[:-1], cuts[1:]))

    def _triangulate_chunk(self, tracks: np.ndarray) -> int:
        rows, owner = track_rows(self.starts, tracks)
        # rows of registered images; not those a degenerate camera cannot unproject
        keep = self.registered[self.obs_image[rows]] & np.isfinite(self.obs_norm[rows]).all(axis=1)
        rows, owner = rows[keep], owner[keep]
        accepted = np.zeros(len(tracks), dtype=bool)
        xyz_out = np.full((len(tracks), 3), np.nan)
        for _ in range(2):  # rows stay grouped by owner (ascending) through every mask below
            counts = np.bincount(owner, minlength=len(tracks))
            sel = np.flatnonzero(counts >= 2)
            if len(sel) == 0:
                break
            mask = counts[owner] >= 2
            r = rows[mask]
            starts = np.concatenate([[0], np.cumsum(counts[sel])])
            img = self.obs_image[r]
            X = triangulate_dlt(self.R[img], self.t[img], self.obs_norm[r], starts)
            xyz_rows = np.repeat(X, np.diff(starts), axis=0)
            err = self.reprojection_errors(r, xyz_rows)
            ok = (err < self.opts.max_reproj_error) & (depths(self.R[img], self.t[img], xyz_rows) > 0)
            n_ok = np.add.reduceat(ok.astype(np.int64), starts[:-1])
            angles = max_triangulation_angles(self.centers(img), X, starts)
            good = (n_ok == np.diff(starts)) & (angles >= self.opts.min_tri_angle) & np.all(np.isfinite(X), axis=1)
            accepted[sel[good]] = True
            xyz_out[sel[good]] = X[good]
            # Second pass: the tracks that failed, from the rows that agreed with them.
            retry_rows = np.repeat(~good & (n_ok >= 2), np.diff(starts)) & ok
            rows, owner = r[retry_rows], owner[mask][retry_rows]
            if len(rows) == 0:
                break
        # Apply results.
        new = tracks[accepted]
        self.track_xyz[new] = xyz_out[accepted]
        self.track_valid[new] = True
        rows_all, _ = track_rows(self.starts, new)
        on = self.registered[self.obs_image[rows_all]]
        rows_all = rows_all[on]
        err = self.reprojection_errors(rows_all, self.track_xyz[self.obs_track[rows_all]])
        self.obs_inlier[rows_all] = err < self.opts.max_reproj_error
        return int(accepted.sum())

    def triangulate_new(self, i: int) -> int:
        rows = self.image_rows[i]
        tracks = np.unique(self.obs_track[rows])
        return self._triangulate_tracks(tracks[~self.track_valid[tracks]])

    def retriangulate(self) -> int:
        """Triangulate tracks that failed before, and re-admit rows of valid tracks that now
        reproject well (the model moved)."""
        reg_rows = np.flatnonzero(self.registered[self.obs_image])
        tr = self.obs_track[reg_rows]
        counts = np.bincount(tr, minlength=self.num_tracks)
        open_tracks = np.flatnonzero((counts >= 2) & ~self.track_valid)
        added = self._triangulate_tracks(open_tracks)
        cand = reg_rows[self.track_valid[tr] & ~self.obs_inlier[reg_rows]]
        if len(cand):
            err = self.reprojection_errors(cand, self.track_xyz[self.obs_track[cand]])
            self.obs_inlier[cand[err < self.opts.max_reproj_error]] = True
        return added

    # ------------------------------------------------------------------ rows of tracks
    def track_rows(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the given tracks and the position of each row's track in ``tracks``."""
        return track_rows(self.starts, tracks)

    def inlier_rows(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`track_rows` restricted to the inlier rows in registered images."""
        rows, owner = track_rows(self.starts, tracks)
        keep = self.obs_inlier[rows] & self.registered[self.obs_image[rows]]
        return rows[keep], owner[keep]

    # ------------------------------------------------------------------ filtering
    def drop_degenerate_cameras(self) -> None:
        """COLMAP's image filter after a global BA: the images of a camera whose refined
        intrinsics became bogus (``backend.camera_models.has_bogus_params``; a camera seen by a
        handful of observations can drift there) leave the model, and the camera returns to
        its prior, so one bad camera neither stays in the model nor poisons the others'
        points with non-finite coordinates.  An image dropped this way may register again.
        Cameras held fixed, or already outside the limits as given, are left alone; so is every
        camera when ``camera_filter`` is off (the refinement of merged poses, where nothing
        would register the images again).
        Not before ``MIN_IMAGES_FOR_CAMERA_FILTER`` images are registered: a young model's
        intrinsics still move a lot (COLMAP's rule and number).  Until then, rows a camera
        cannot unproject are left out of triangulation and registration."""
        if not self.camera_filter or self.num_registered < MIN_IMAGES_FOR_CAMERA_FILTER:
            return
        dropped = []
        for c, prior in enumerate(self.priors):
            images = np.flatnonzero(self.registered & (self.cam_index == c))
            if (prior.fixed or len(images) == 0
                    or not has_bogus_params(prior.model, self.params[c], prior.width, prior.height)
                    or has_bogus_params(prior.model, prior.params, prior.width, prior.height)):
                continue  # held, unused, sound, or already so as given: nothing to go back to
            log.info("%s: camera %d has degenerate intrinsics %s after BA: %d image(s) leave the model",
                     self.payload.label, c, np.array2string(self.params[c], precision=4), len(images))
            self._take_out(images)
            self.params[c] = np.array(prior.params, dtype=np.float64)
            dropped.extend(images.tolist())
        if dropped:
            self._update_normalised()
            for i in dropped:
                self._fail_until_more_points(i)

    def _take_out(self, images: np.ndarray) -> None:
        """``images`` leave the current model: unregistered, none of their rows an inlier."""
        self.registered[images] = False
        self.num_registered -= len(images)
        for i in images:
            self.obs_inlier[self.image_rows[i]] = False

    def _fail_until_more_points(self, i: int) -> None:
        """Image ``i`` counts as failed now: PnP and structure-less registration retry it once it
        sees 20% more points than it does."""
        self.note_failure(int(i), len(self.visible_points(i)[0]))
        self.structureless_failed[int(i)] = int(self.fail_visible[i])

    def drop_unsupported_images(self) -> list[int]:
        """The other half of COLMAP's image filter after a global BA: a registered image left
        with fewer than :data:`MIN_POSE_POINTS` inlier points (its rows rejected by the filtering,
        as where a model joined at a wrong scale or calibration fits nothing its images saw) has
        a pose nothing determines any more.  It leaves the model and may register again by PnP
        on the points it sees now; after ``MAX_REG_TRIALS`` such drops it counts as a failed
        registration, by PnP and without (retried once it sees 20% more points).  COLMAP drops
        an image with no point left; one with one or two is as undetermined, and a BA that holds
        it is singular wherever its covariance is asked (``sfm.mapper.self_calibration``).  Off
        with ``camera_filter`` (nothing registers the images again), and never below a
        two-image model.  Returns the images dropped."""
        if not self.camera_filter:
            return []
        rows = np.flatnonzero(self.obs_inlier & self.track_valid[self.obs_track])
        counts = np.bincount(self.obs_image[rows], minlength=len(self.names))
        dropped = np.flatnonzero(self.registered & (counts < MIN_POSE_POINTS))
        if len(dropped) == 0 or self.num_registered - len(dropped) < 2:
            return []
        log.info("%s: %s kept fewer than %d points after the BA's filtering: they leave the model",
                 self.payload.label, ", ".join(f"{self.names[i]} ({counts[i]})" for i in dropped), MIN_POSE_POINTS)
        self._take_out(dropped)
        self.unsupported[dropped] += 1
        for i in dropped[self.unsupported[dropped] >= MAX_REG_TRIALS]:
            self._fail_until_more_points(i)
        return dropped.tolist()

    def filter_observations(self, tracks: np.ndarray) -> None:
        """Drop rows above ``max_reproj_error`` and points left with < 2 rows or too small an
        angle (COLMAP's filtering after BA)."""
        rows, owner = track_rows(self.starts, tracks)
        rows_mask = self.obs_inlier[rows]
        rows, owner = rows[rows_mask], owner[rows_mask]
        err = self.reprojection_errors(rows, self.track_xyz[self.obs_track[rows]])
        bad = err >= self.opts.max_reproj_error
        self.obs_inlier[rows[bad]] = False
        rows, owner = rows[~bad], owner[~bad]
        counts = np.bincount(owner, minlength=len(tracks))
        order = np.argsort(owner, kind="stable")
        rows_sorted = rows[order]
        starts = np.concatenate([[0], np.cumsum(counts)])
        img = self.obs_image[rows_sorted]
        angles = np.zeros(len(tracks))
        has = counts >= 2
        if has.any():
            angles = max_triangulation_angles(self.centers(img), self.track_xyz[tracks], starts)
        dead = (counts < 2) | (angles < self.opts.min_tri_angle)
        dead_tracks = tracks[dead]
        self.track_valid[dead_tracks] = False
        drows, _ = track_rows(self.starts, dead_tracks)
        self.obs_inlier[drows] = False
