"""The incremental mapper's bundle adjustment driver: which images, points and intrinsics each BA
moves, and when it stops.

:class:`BundleAdjuster` belongs to one :class:`sfm.mapper.state.MapperState`.  It chooses what a
BA optimises, builds the :class:`backend.ba_problem.BAProblem` from the state's arrays,
runs it (``backend``: a GTSAM factor graph) and hands the result back to the state
(:meth:`MapperState.apply_adjustment`), which then filters its observations.

- Local BA after each registration (COLMAP's local bundle, OpenSfM's neighbourhood): the points
  the new image sees, with that image and the ``local_ba_num_images - 1`` registered images
  sharing most of them free, every other image that sees them held; the intrinsics only of the
  cameras whose registered images are all free (one camera per image: the new image's own).
- Global BA when the model has grown by ``global_ba_ratio``: every registered image, on a subset
  of the tracks (TheiaSfM's selection: each image's best track per grid cell keeps the poses
  from drifting; the rest are re-estimated with the cameras held).
- BA of a region (a model extended by new images, ``graphsfm extend``): the given images and
  the registered images that share points with them free, every point those free images see,
  the other images that see those points held; its cost grows with the region, not the model.
- Final BAs of a model: every image and every track seen by three images or more (a point
  only two images see joins when one of them needs it), to a tighter tolerance, the other
  points then re-estimated with the cameras held; with
  ``intrinsics_refinement="auto"`` the distortion only of the cameras whose distortion the model
  determines and the principal point too of each camera whose shift from its nominal value the
  model determines, both tested before the BA at the current state
  (``sfm.mapper.self_calibration``); above
  ``ba_max_observations`` observations (by default as many as fit in half of the machine's
  memory, an observation costing more the longer its track) as the consensus of BAs over random
  track parts (``backend.partitioned_ba``), the points then re-estimated with the cameras held.
  Each final BA's size, cost, iterations and why it stopped go to the log and to the model
  (``Reconstruction.final_ba``, ``report.json``).

Stopping rules: Levenberg-Marquardt stops when an iteration lowers the cost by less than
:data:`GROWING_TOLERANCE` of it in a growing model (later BAs refine again), by less than
:data:`FINAL_TOLERANCE` in the last BA of a model, whose late iterations still move the poses on
nearly flat costs (aerial blocks).  The growing model's BAs also stop once the rest of their
decrease, predicted from the last two iterations as a geometric series, is below their tolerance
(``BAOptions.predictive_stop``): the iteration that would only confirm convergence is skipped.
COLMAP stops its global BA on a gradient tolerance instead (Ceres).
"""

from __future__ import annotations

import logging

import numpy as np

from backend.ba_problem import BAOptions, BAProblem, BAResult
from backend.partitioned_ba import bundle_adjust_partitioned, observations_in_memory
from backend.track_subset import select_tracks
from sfm.core import progress
from sfm.mapper.self_calibration import SelfCalibration
from sfm.mapper.state import ROW_CHUNK, MapperState
from sfm.mapper.tracks import work_cuts
from sfm.mapper.triangulation import refine_points

log = logging.getLogger(__name__)

GROWING_TOLERANCE = 1e-3
GROWING_MAX_ITERATIONS = 25
FINAL_TOLERANCE = 1e-4
# Registered images that must see a track for the final BAs to adjust the poses with it
# (BundleAdjuster.posing_tracks; COLMAP's global mapper: min_track_length 3).
FINAL_MIN_VIEWS = 3


class BundleAdjuster:
    """Local, global and final BAs of one :class:`MapperState` (module docstring).

    ``last_rms`` and ``last_decrease`` describe the last BA: its final RMS reprojection error in
    pixels and the relative cost decrease of its last iteration (how far from the optimum a
    loose tolerance stopped it); ``final_bas`` what each final BA did
    (:func:`final_ba_summary`)."""

    def __init__(self, state: MapperState) -> None:
        self.state = state
        self.opts = state.opts
        self.last_rms = float("nan")
        self.last_decrease = 0.0
        self.final_bas: list[dict] = []  # final_ba_summary of each final BA, in order
        self.calibration = SelfCalibration(self)  # what the final BAs refine of each camera under "auto"

    # ------------------------------------------------------------------ the three kinds
    def local(self, i: int) -> None:
        """BA around the new image ``i``: the points it sees, with ``i`` and the registered
        images sharing most of those points free and every other image that sees them fixed
        (OpenSfM's local bundle; the points of the neighbours alone were already adjusted).
        Gauss-Newton first: the new image's PnP pose and fresh points are a good start."""
        s = self.state
        rows = s.image_rows[i]
        tracks = np.unique(s.obs_track[rows[s.obs_inlier[rows]]])
        tracks = tracks[s.track_valid[tracks]]
        trows, _ = s.track_rows(tracks)
        trows = trows[s.obs_inlier[trows]]
        neigh = np.bincount(s.obs_image[trows], minlength=len(s.names))
        neigh[i] = 0
        best = np.argsort(-neigh, kind="stable")[: self.opts.local_ba_num_images - 1]
        free = np.concatenate([[i], best[neigh[best] > 0]])
        self._adjust(free, tracks, self._local_levels(free), GROWING_MAX_ITERATIONS, tolerance=GROWING_TOLERANCE,
                     optimizer="gauss_newton_or_lm", predictive=True)
        s.filter_observations(tracks)

    def global_(self, final: bool = False, tolerance: float = FINAL_TOLERANCE,
                loss_scale: float | None = None, decide: bool = True, only_if_changed: bool = False) -> bool:
        """BA of every registered image: on a track subset while the model grows, on every
        track when ``final`` (LM stopping at ``tolerance``), with the robust loss at
        ``loss_scale`` pixels (None: ``opts.global_loss_scale``, see ``MapperOptions``).
        Under ``intrinsics_refinement="auto"`` a final BA's self-calibration tests decide what
        it refines of each camera; ``decide=False`` skips them and refines what earlier tests
        decided (``SelfCalibration.decided_levels``); ``only_if_changed``: no BA when the tests
        decide what was decided before and move no camera parameter (the model, at an earlier
        final BA's optimum, is at this one's too).
        Then COLMAP's filtering: degenerate cameras, observations, points.  Whether a BA ran."""
        s = self.state
        loss_scale = self._global_loss_scale() if loss_scale is None else loss_scale
        free = np.flatnonzero(s.registered)
        tracks = np.flatnonzero(s.track_valid)
        if final:
            posing = self.posing_tracks(tracks)
            parts = self._num_parts(posing)
            refine = self.opts.intrinsics_refinement
            if refine == "auto" and decide:
                before = (self.calibration.decided_levels(free), [p.copy() for p in s.params])
                refine = self.calibration.final_levels(free, posing, loss_scale)
                if only_if_changed and refine == before[0] and all(map(np.array_equal, before[1], s.params)):
                    log.info("%s: the self-calibration tests keep every camera as the last final BA left it: "
                             "no further final BA", s.payload.label)
                    return False
            elif refine == "auto":
                refine = self.calibration.decided_levels(free)
            result = self._adjust(free, posing, refine, 100, tolerance, parts=parts, loss_scale=loss_scale,
                                  on_iteration=_report_final_ba(len(free)))
            if parts > 1:
                self.refine_points(posing)
            if result is not None:
                summary = final_ba_summary(result, len(free), parts)
                if parts > 1:  # the parts' points were each fitted to their part's cameras, not to the mean
                    rows, _ = s.inlier_rows(posing)
                    err = s.reprojection_errors(rows, s.track_xyz[s.obs_track[rows]])
                    summary["rms_after_px"] = round(float(np.sqrt(np.mean(err**2))), 4) if len(err) else 0.0
                self.final_bas.append(summary)
                log.info("%s: final BA %s", s.payload.label, describe_final_ba(summary))
            if len(posing) < len(tracks):
                self.refine_points(np.setdiff1d(tracks, posing, assume_unique=True))
        else:
            subset = self.track_subset(tracks)
            self._adjust(free, subset, self._growing_level(), GROWING_MAX_ITERATIONS, GROWING_TOLERANCE,
                         predictive=True, loss_scale=loss_scale)
            if len(subset) < len(tracks):
                self.refine_points(np.setdiff1d(tracks, subset))
        s.drop_degenerate_cameras()
        s.filter_observations(tracks)
        return True

    def posing_tracks(self, tracks: np.ndarray) -> np.ndarray:
        """The tracks a final BA adjusts the poses with: those seen by at least
        :data:`FINAL_MIN_VIEWS` registered images, and a point only two images see when one of
        them sees fewer than ``abs_pose_min_num_inliers`` of the others (the points PnP needs
        to register an image; a two-image model keeps all its points).  A point two images see
        has four coordinates for three unknowns: each observation's redundancy number is about
        1/4 (1/2 with three views), so an error in it shows in the residual at a quarter of its
        size, and a wrong match well inside ``max_reproj_error`` moves the two poses unseen
        (Baarda's internal reliability) where a third view would expose it.  COLMAP's global
        mapper adjusts only tracks of three views or more.  The other points are re-estimated
        with the cameras held after the BA, so the model keeps them."""
        s = self.state
        rows, owner = s.inlier_rows(tracks)
        views = np.bincount(owner, minlength=len(tracks))
        confirmed = views >= FINAL_MIN_VIEWS
        image = s.obs_image[rows]
        seen = np.bincount(image[confirmed[owner]], minlength=len(s.names))
        weak = seen < self.opts.abs_pose_min_num_inliers
        needed = np.bincount(owner, weights=weak[image], minlength=len(tracks)) > 0
        return tracks[confirmed | needed]

    def region(self, images: np.ndarray, loss_scale: float | None = None) -> np.ndarray:
        """Final BA around ``images`` (the images added to a finished model): they and the
        registered images that share an inlier point with them are free, every point a free
        image sees is optimised, and the other images that see those points are held, so the
        rest of the model anchors the region (the local BA of :meth:`local` grown to a set of
        new images, with the neighbours' own points in it).  Intrinsics are refined only when
        no image outside the free ones uses the camera.  Then COLMAP's filtering of those
        points.  Returns the optimised tracks."""
        s = self.state
        images = np.asarray(images, dtype=np.int64)
        images = images[s.registered[images]]
        free = self.region_images(images)
        if len(free) == 0:
            return np.zeros(0, np.int64)
        own = np.concatenate([s.image_rows[i] for i in free])
        tracks = np.unique(s.obs_track[own[s.obs_inlier[own]]])
        tracks = tracks[s.track_valid[tracks]]
        outside = s.registered.copy()
        outside[free] = False
        refine = self._growing_level()
        if np.intersect1d(np.unique(s.cam_index[free]), np.unique(s.cam_index[outside])).size:
            refine = "none"
        parts = self._num_parts(tracks)
        log.info("%s: BA of the region around %d images: %d images free, %d points", s.payload.label,
                 len(images), len(free), len(tracks))
        self._adjust(free, tracks, refine, 100, FINAL_TOLERANCE, parts=parts,
                     loss_scale=self._global_loss_scale() if loss_scale is None else loss_scale)
        if parts > 1:
            self.refine_points(tracks)
        s.drop_degenerate_cameras()
        s.filter_observations(tracks)
        return tracks

    def region_images(self, images: np.ndarray) -> np.ndarray:
        """The images :meth:`region` frees around ``images``: those of them registered and the
        registered images that share an inlier point with them."""
        s = self.state
        images = np.asarray(images, dtype=np.int64)
        images = images[s.registered[images]]
        if len(images) == 0:
            return np.zeros(0, np.int64)
        seen = np.unique(s.obs_track[np.concatenate([s.image_rows[i] for i in images])])
        rows, _ = s.inlier_rows(seen[s.track_valid[seen]])
        return np.union1d(images, np.unique(s.obs_image[rows]))

    def refine_points(self, tracks: np.ndarray) -> None:
        """Re-estimate the given points from their inlier rows with the cameras held (in
        chunks of about ``ROW_CHUNK`` rows: the per-row temporaries stay bounded)."""
        s = self.state
        lengths = s.starts[tracks + 1] - s.starts[tracks]
        cuts = work_cuts(np.cumsum(lengths), ROW_CHUNK)
        focal = np.array([s.camera_focal(c) for c in range(len(s.priors))])
        for a, b in zip(cuts[:-1], cuts[1:]):
            chunk = tracks[a:b]
            rows, owner = s.inlier_rows(chunk)
            starts = np.searchsorted(owner, np.arange(len(chunk) + 1))
            img = s.obs_image[rows]
            huber = self.opts.loss_scale / focal[s.cam_index[img]] if self.opts.loss != "none" else np.full(len(rows), 1e6)
            xyz = refine_points(s.R[img], s.t[img], s.obs_norm[rows], starts, s.track_xyz[chunk], huber)
            s.set_points(chunk, xyz)

    def growing_options(self, refine: str, loss_scale: float) -> BAOptions:
        """The options of a BA that stops as a growing model's global BA does
        (``GROWING_MAX_ITERATIONS``, ``GROWING_TOLERANCE``, or the rest of the decrease predicted
        below it), refining ``refine`` with the robust loss at ``loss_scale`` pixels: the
        principal point's half-BAs (``sfm.mapper.self_calibration``)."""
        return BAOptions(loss=self.opts.loss, loss_scale=loss_scale, refine_intrinsics=refine,
                         max_iterations=GROWING_MAX_ITERATIONS, relative_tolerance=GROWING_TOLERANCE,
                         predictive_stop=True)

    # ------------------------------------------------------------------ helpers
    def _local_levels(self, free: np.ndarray) -> list[str]:
        """What a local BA refines of each camera: the growing model's level for a camera all of
        whose registered images are free in it (one camera per image: the new image's own), none
        for the others, whose intrinsics images outside the local BA also determine (COLMAP's
        local BA holds the intrinsics of those cameras alone)."""
        s = self.state
        level = self._growing_level()
        outside = np.zeros(len(s.priors), dtype=bool)
        held = s.registered.copy()
        held[free] = False
        outside[np.unique(s.cam_index[held])] = True
        return ["none" if outside[c] else level for c in range(len(s.priors))]

    def _growing_level(self) -> str:
        """What the growing model's global BAs refine: "auto" holds the principal point."""
        level = self.opts.intrinsics_refinement
        return "focal_radial" if level == "auto" else level

    def _global_loss_scale(self) -> float:
        """``opts.global_loss_scale``; unresolved (``MapperOptions.for_model``), the final
        model's ``max_reproj_error``."""
        return self.opts.for_model(final=True).global_loss_scale

    def _num_parts(self, tracks: np.ndarray) -> int:
        """Number of random track parts a final BA is split into so that each holds at most
        ``ba_max_observations`` observations (``backend.partitioned_ba``); 1: one BA."""
        _, owner = self.state.inlier_rows(tracks)
        budget, num_rows = self.observation_budget(np.bincount(owner)), len(owner)
        parts = -(-num_rows // budget) if budget > 0 else 1
        source = ("ba_max_observations" if self.opts.ba_max_observations is not None
                  else "what half of the memory holds with these tracks' lengths")
        if parts > 1:
            log.info("%s: final BA over %d observations as the consensus of %d BAs over random track parts "
                     "(at most %d observations each: %s); the points are then re-estimated with the cameras "
                     "held", self.state.payload.label, num_rows, parts, budget, source)
        return parts

    def observation_budget(self, track_lengths: np.ndarray) -> int:
        """The most observations one BA over tracks of ``track_lengths`` (inlier rows in
        registered images) holds: ``ba_max_observations``; None: as many as fit in this machine's
        memory at these lengths (``backend.partitioned_ba.observations_in_memory``); 0: no limit."""
        budget = self.opts.ba_max_observations
        return observations_in_memory(track_lengths=track_lengths) if budget is None else budget

    def track_subset(self, tracks: np.ndarray) -> np.ndarray:
        """The tracks a global BA optimises while the model grows: each image's best track in
        each grid cell (``select_tracks``' first level), as TheiaSfM does: it only has to keep
        the growing model from drifting, and the final BAs refine everything."""
        s = self.state
        rows, owner = s.inlier_rows(tracks)
        if len(rows) == 0:
            return tracks
        err = s.reprojection_errors(rows, s.track_xyz[s.obs_track[rows]])
        sizes = np.array([[p.width, p.height] for p in s.priors], dtype=np.float64)[s.cam_index]
        keep = select_tracks(s.obs_image[rows], owner, s.obs_px[rows], sizes, np.minimum(err, 1e6), len(tracks), 0)
        return tracks[keep]

    def problem(self, free: np.ndarray, tracks: np.ndarray, alone: bool = False):
        """The BA problem of ``tracks`` with the images ``free`` free and the others that see
        them held: ``(problem, image order, number of free images, the state's cameras of its
        groups)``; ``(None, ...)`` without observations.  ``alone``: the images ``free`` by
        themselves, their observations only and the tracks they see at least twice (the gauge
        then held by the BA's priors)."""
        s = self.state
        rows, owner = s.inlier_rows(tracks)
        if alone:
            inside = np.isin(s.obs_image[rows], free)
            rows, owner = rows[inside], owner[inside]
            seen, count = np.unique(owner, return_counts=True)
            twice = np.isin(owner, seen[count >= 2])
            rows, tracks = rows[twice], tracks[seen[count >= 2]]
        if len(rows) == 0:
            return None, None, 0, None
        images = np.unique(s.obs_image[rows])
        fixed = np.setdiff1d(images, free)
        order = np.concatenate([np.intersect1d(free, images), fixed])
        img_local = np.full(len(s.names), -1)
        img_local[order] = np.arange(len(order))
        point_local = np.full(s.num_tracks, -1)
        point_local[tracks] = np.arange(len(tracks))
        cams = np.unique(s.cam_index[order])
        cam_local = np.full(len(s.priors), -1)
        cam_local[cams] = np.arange(len(cams))
        n_free = len(order) - len(fixed)
        problem = BAProblem(
            camera_models=[s.priors[c].model for c in cams], camera_params=[s.params[c] for c in cams],
            image_camera=cam_local[s.cam_index[order]], rotations=s.R[order], translations=s.t[order],
            points=s.track_xyz[tracks], obs_image=img_local[s.obs_image[rows]],
            obs_point=point_local[s.obs_track[rows]], obs_xy=s.obs_px[rows], obs_sigma=s.obs_sigma[rows],
            fixed_poses=tuple(range(n_free, len(order))),
        )
        return problem, order, n_free, cams

    def _adjust(self, free: np.ndarray, tracks: np.ndarray, refine: str | list[str], max_iterations: int,
                tolerance: float = 1e-5, parts: int = 1, optimizer: str = "lm",
                predictive: bool = False, loss_scale: float | None = None, on_iteration=None) -> BAResult | None:
        """BA of ``tracks`` with the images ``free`` free and the others that see them held;
        ``refine``: one level for every camera, or one per camera of the state;
        ``loss_scale``: of the robust loss (None: ``opts.loss_scale``, the local BAs' one).
        The BA's result (None: no observations)."""
        s = self.state
        problem, order, n_free, cams = self.problem(free, tracks)
        if problem is None:
            return None
        levels = [refine] * len(s.priors) if isinstance(refine, str) else list(refine)
        levels = ["none" if prior.fixed else level for prior, level in zip(s.priors, levels)]  # given intrinsics
        group_levels = tuple(levels[c] for c in cams)
        refined = any(level != "none" for level in group_levels)
        options = BAOptions(loss=self.opts.loss, loss_scale=self.opts.loss_scale if loss_scale is None else loss_scale,
                            refine_intrinsics=group_levels, max_iterations=max_iterations,
                            relative_tolerance=tolerance, optimizer=optimizer, predictive_stop=predictive,
                            on_iteration=on_iteration)
        result = bundle_adjust_partitioned(problem, parts, options, seed=self.opts.seed)
        s.apply_adjustment(order[:n_free], result.rotations[:n_free], result.translations[:n_free], tracks,
                           result.points, cams if refined else None, result.camera_params)
        self.last_rms = float(result.final_rms)
        self.last_decrease = float(result.last_decrease)
        return result


def final_ba_summary(result: BAResult, num_images: int, parts: int) -> dict:
    """What a final BA did, for the log and ``report.json`` (each model's ``final_ba``): its
    size, its cost (summed over the parts of a partitioned BA) and RMS reprojection error before
    and after (a partitioned BA's: with the points re-estimated for the pooled cameras, set by
    the caller), its iterations, why it stopped and the lines GTSAM printed (kept off the
    terminal)."""
    return {"images": num_images, "observations": int(result.num_observations), "parts": parts,
            "iterations": int(result.iterations), "cost_before": float(result.initial_cost),
            "cost_after": float(result.final_cost), "rms_before_px": round(float(result.initial_rms), 4),
            "rms_after_px": round(float(result.final_rms), 4), "stopped": result.stopped,
            "solver_messages": int(result.solver_messages), "time_s": round(float(result.time_s), 2)}


def describe_final_ba(summary: dict) -> str:
    """One line of :func:`final_ba_summary`."""
    parts = f" in {summary['parts']} parts" if summary["parts"] > 1 else ""
    printed = f"; GTSAM printed {summary['solver_messages']} lines (debug log)" if summary["solver_messages"] else ""
    return (f"over {summary['images']} images and {summary['observations']} observations{parts}: cost "
            f"{summary['cost_before']:.6g} -> {summary['cost_after']:.6g}, RMS {summary['rms_before_px']:.3f} -> "
            f"{summary['rms_after_px']:.3f} px, {summary['iterations']} iterations, {summary['time_s']:.1f} s; "
            f"stopped: {summary['stopped']}{printed}")


def _report_final_ba(num_images: int):
    """A final BA's iterations as progress events (``sfm.core.progress``): the iteration and
    its cost, so a display can show a long BA moving."""

    def on_iteration(iteration: int, before: float, after: float) -> None:
        progress.report("final_ba", iteration + 1, None, cost=after, images=num_images)

    return on_iteration
