"""The bundle adjustment and filtering steps of :class:`sfm.mapper.state.MapperState`.

Local BA around a new image, global BA (on a track subset while the model grows; the final
ones on every track, split into parts above ``ba_max_observations``), point re-estimation with
the cameras held, and COLMAP's filtering after BA.  A mixin: the methods work on the state's
arrays (observation rows grouped by track, poses, intrinsics, points), described in
``sfm.mapper.state``.
"""

from __future__ import annotations

import logging

import numpy as np

from backend.bundle_adjustment import BAOptions
from backend.partitioned_ba import bundle_adjust_partitioned
from backend.track_subset import select_tracks
from sfm.core.camera_models import has_bogus_params
from sfm.mapper.tracks import work_cuts
from sfm.mapper.triangulation import max_triangulation_angles, refine_points

log = logging.getLogger("sfm.mapper.state")  # one logger for the mapper's messages

# Track rows triangulated at once: the per-row temporaries stay around 100 MB.
_TRIANGULATION_ROWS = 250_000

# Levenberg-Marquardt stops when an iteration lowers the cost by less than this share: 1e-3
# for the BAs of a growing model (later BAs refine again), 1e-4 for the last BA of a model.
# A final BA's cost falls by less than 1e-4 per iteration within 3-6 iterations and then creeps
# on for as many again at GTSAM's default 1e-5: measured with both, lund_door, temple_ring,
# synthetic orbit 100 and the 500-image aerial merge gave the same poses to 4 digits of AUC
# and of the median rotation error, in 0-20% less mapping time.  1e-3 for the last BA too gave
# the same lund_door and temple_ring models but a 20% larger median rotation error on the
# 2,000-image aerial scene (0.0219 instead of 0.0182 deg), whose nearly flat cost still moves
# the poses at 1e-3 per iteration.  A final BA that re-triangulation and another BA follow
# stops at 1e-3 (``sfm.mapper.incremental._final_refinement``).  COLMAP stops its global BA on a
# gradient tolerance instead (Ceres, 1 in cost units, 50 iterations).
GROWING_TOLERANCE = 1e-3
FINAL_TOLERANCE = 1e-4
# The growing BAs also stop as soon as the rest of their decreases is predicted below
# GROWING_TOLERANCE (``BAOptions.predictive_stop``): a local BA from PnP and fresh points
# typically lowers its cost by 30-90%, then by 1e-3-1e-2, and a third iteration only confirmed
# that.  Measured: temple_ring's 37 local BAs go from 2-7 to 2 iterations each (mapping about 1 s
# faster over eight alternating runs; median rotation error 0.5463 instead of 0.5467 deg, AUC@5
# 0.8155 instead of 0.8154), the synthetic aerial 250's local BAs from 670 to 448 iterations
# (BA time 47 instead of 60 s, the same 0.0119 deg); lund_door's model is unchanged
# (AUC@1 0.9747).  The final BAs keep the plain rule: on nearly flat costs their late
# iterations still move the poses.

# Registered images from which a camera with degenerate intrinsics takes its images out of the
# model (COLMAP's IncrementalMapper::FilterImages waits for 20).
MIN_IMAGES_FOR_CAMERA_FILTER = 20


def _gather(starts: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the given tracks (concatenated) and the position of each row's track in ``tracks``."""
    lengths = starts[tracks + 1] - starts[tracks]
    owner = np.repeat(np.arange(len(tracks)), lengths)
    first = np.repeat(starts[tracks], lengths)
    offset = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return first + offset, owner


class BundleAdjustmentSteps:
    """BA, point refinement and filtering over a :class:`sfm.mapper.state.MapperState`."""

    def _inlier_rows(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_gather`` restricted to the inlier rows in registered images."""
        rows, owner = _gather(self.starts, tracks)
        keep = self.obs_inlier[rows] & self.registered[self.obs_image[rows]]
        return rows[keep], owner[keep]

    def _bundle_adjust(self, free: np.ndarray, tracks: np.ndarray, refine: str, max_iterations: int,
                       tolerance: float = 1e-5, parts: int = 1, optimizer: str = "lm",
                       predictive: bool = False, loss_scale: float | None = None) -> None:
        """BA of ``tracks`` with the images ``free`` free and the others that see them held;
        ``loss_scale``: of the robust loss (None: ``opts.loss_scale``, the local BAs' one)."""
        rows, _ = self._inlier_rows(tracks)
        if len(rows) == 0:
            return
        images = np.unique(self.obs_image[rows])
        fixed = np.setdiff1d(images, free)
        order = np.concatenate([np.intersect1d(free, images), fixed])
        img_local = np.full(len(self.names), -1)
        img_local[order] = np.arange(len(order))
        point_local = np.full(self.num_tracks, -1)
        point_local[tracks] = np.arange(len(tracks))
        cams = np.unique(self.cam_index[order])
        cam_local = np.full(len(self.priors), -1)
        cam_local[cams] = np.arange(len(cams))
        if any(self.priors[c].fixed for c in cams):
            refine = "none"
        n_free = len(order) - len(fixed)
        result = bundle_adjust_partitioned(
            [self.priors[c].model for c in cams], [self.params[c] for c in cams], cam_local[self.cam_index[order]],
            self.R[order], self.t[order], self.track_xyz[tracks],
            img_local[self.obs_image[rows]], point_local[self.obs_track[rows]], self.obs_px[rows], parts,
            BAOptions(loss=self.opts.loss, loss_scale=self.opts.loss_scale if loss_scale is None else loss_scale, fixed_poses=tuple(range(n_free, len(order))),
                      refine_intrinsics=refine, max_iterations=max_iterations, relative_tolerance=tolerance,
                      optimizer=optimizer, predictive_stop=predictive),
            seed=self.opts.seed, obs_sigma=self.obs_sigma[rows],
        )
        self.R[order[:n_free]] = result.rotations[:n_free]
        self.t[order[:n_free]] = result.translations[:n_free]
        self.track_xyz[tracks] = result.points
        self.last_ba_rms = float(result.final_rms)
        self.last_ba_decrease = float(result.last_decrease)
        if refine != "none":
            for c, p in zip(cams, result.camera_params):
                self.params[c] = np.asarray(p, dtype=np.float64)
            self._update_normalised()

    def local_ba(self, i: int) -> None:
        """BA around the new image ``i``: the points it sees, with ``i`` and the registered
        images sharing most of those points free and every other image that sees them fixed
        (OpenSfM's local bundle; the points of the neighbours alone were already adjusted)."""
        rows = self.image_rows[i]
        tracks = np.unique(self.obs_track[rows[self.obs_inlier[rows]]])
        tracks = tracks[self.track_valid[tracks]]
        trows, _ = _gather(self.starts, tracks)
        trows = trows[self.obs_inlier[trows]]
        neigh = np.bincount(self.obs_image[trows], minlength=len(self.names))
        neigh[i] = 0
        best = np.argsort(-neigh, kind="stable")[: self.opts.local_ba_num_images - 1]
        free = np.concatenate([[i], best[neigh[best] > 0]])
        # Gauss-Newton first: the new image's PnP pose and fresh points are a good start
        self._bundle_adjust(free, tracks, "none", 25, tolerance=GROWING_TOLERANCE, optimizer="gauss_newton_or_lm",
                            predictive=True)
        self.filter_observations(tracks)

    def global_ba(self, final: bool = False, tolerance: float = FINAL_TOLERANCE,
                  loss_scale: float | None = None) -> None:
        """BA of every registered image: on a track subset while the model grows, on every
        track when ``final`` (LM stopping at ``tolerance``, see ``FINAL_TOLERANCE``), with the
        robust loss at ``loss_scale`` pixels (None: ``opts.global_loss_scale``, see
        ``MapperOptions``)."""
        loss_scale = self._global_loss_scale() if loss_scale is None else loss_scale
        free = np.flatnonzero(self.registered)
        tracks = np.flatnonzero(self.track_valid)
        if final:
            parts = self._ba_parts(tracks)
            self._bundle_adjust(free, tracks, self.opts.refine_intrinsics, 100, tolerance, parts=parts,
                                loss_scale=loss_scale)
            if parts > 1:
                self._refine_points(tracks)
        else:
            subset = self._ba_subset(tracks)
            self._bundle_adjust(free, subset, self.opts.refine_intrinsics, 25, GROWING_TOLERANCE, predictive=True,
                                loss_scale=loss_scale)
            if len(subset) < len(tracks):
                self._refine_points(np.setdiff1d(tracks, subset))
        self.drop_degenerate_cameras()
        self.filter_observations(tracks)

    def _global_loss_scale(self) -> float:
        """``opts.global_loss_scale``; unresolved (``MapperOptions.for_model``), the final
        model's ``max_reproj_error``."""
        return self.opts.for_model(final=True).global_loss_scale

    def drop_degenerate_cameras(self) -> None:
        """COLMAP's image filter after a global BA: the images of a camera whose refined
        intrinsics became bogus (``sfm.core.camera_models.has_bogus_params``; a camera seen by a
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
            self.registered[images] = False
            for i in images:
                self.obs_inlier[self.image_rows[i]] = False
            self.num_registered -= len(images)
            self.params[c] = np.array(prior.params, dtype=np.float64)
            dropped.extend(images.tolist())
        if dropped:
            self._update_normalised()
            for i in dropped:  # retried once they see 20% more points (PnP and structure-less)
                self.failed[i] += 1
                self.fail_visible[i] = len(self.visible_points(i)[0])
                self.structureless_failed[i] = int(self.fail_visible[i])

    def _ba_parts(self, tracks: np.ndarray) -> int:
        """Number of random track parts a final BA is split into so that each holds at most
        ``ba_max_observations`` observations (``backend.partitioned_ba``); 1: one BA."""
        budget = self.opts.ba_max_observations
        num_rows = len(self._inlier_rows(tracks)[0])
        parts = -(-num_rows // budget) if budget > 0 else 1
        if parts > 1:
            log.info("%s: final BA over %d observations as the consensus of %d BAs over random track parts "
                     "(ba_max_observations %d); the points are then re-estimated with the cameras held",
                     self.payload.label, num_rows, parts, budget)
        return parts

    def _ba_subset(self, tracks: np.ndarray) -> np.ndarray:
        """The tracks a global BA optimises while the model grows: each image's best track in
        each grid cell (``select_tracks``' first level), as TheiaSfM does: it only has to keep
        the growing model from drifting, and the final BAs refine everything."""
        rows, owner = self._inlier_rows(tracks)
        if len(rows) == 0:
            return tracks
        err = self.reprojection_errors(rows, self.track_xyz[self.obs_track[rows]])
        sizes = np.array([[p.width, p.height] for p in self.priors], dtype=np.float64)[self.cam_index]
        keep = select_tracks(self.obs_image[rows], owner, self.obs_px[rows], sizes, np.minimum(err, 1e6),
                             len(tracks), 0)
        return tracks[keep]

    def _refine_points(self, tracks: np.ndarray) -> None:
        """Re-estimate the given points from their inlier rows with the cameras held (in
        chunks of about ``_TRIANGULATION_ROWS`` rows: the per-row temporaries stay bounded)."""
        lengths = self.starts[tracks + 1] - self.starts[tracks]
        cuts = work_cuts(np.cumsum(lengths), _TRIANGULATION_ROWS)
        for a, b in zip(cuts[:-1], cuts[1:]):
            self._refine_chunk(tracks[a:b])

    def _refine_chunk(self, tracks: np.ndarray) -> None:
        rows, owner = self._inlier_rows(tracks)
        starts = np.searchsorted(owner, np.arange(len(tracks) + 1))
        img = self.obs_image[rows]
        focal = np.array([self._camera_focal(c) for c in range(len(self.priors))])[self.cam_index[img]]
        huber = self.opts.loss_scale / focal if self.opts.loss != "none" else np.full(len(rows), 1e6)
        self.track_xyz[tracks] = refine_points(self.R[img], self.t[img], self.obs_norm[rows], starts,
                                               self.track_xyz[tracks], huber)

    def filter_observations(self, tracks: np.ndarray) -> None:
        """Drop rows above ``max_reproj_error`` and points left with < 2 rows or too small an
        angle (COLMAP's filtering after BA)."""
        rows, owner = _gather(self.starts, tracks)
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
        drows, _ = _gather(self.starts, dead_tracks)
        self.obs_inlier[drows] = False
