"""What each final BA of a model refines of each camera under ``intrinsics_refinement="auto"``:
the decisions of self-calibration, and their record for the recording.

The focal length is always refined.  The distortion of a camera is refined when the model
determines it (``sfm.mapper.distortion``), its principal point when the model determines its
shift from the nominal value and two independent halves of the photos reproduce it, or are
each too weak to check it and do not contradict each other (``sfm.mapper.principal_point``).
Both tests read the Gauss-Newton step a BA freeing those parameters would take at the current
state, with its covariance
(``backend.calibration_step.calibration_step``), so they run before the final BA they decide,
on the growing model's track subset (each image's best track per grid cell, so every image and
every part of it counts): its covariance is larger than the full problem's, a conservative
screen, at the cost of a fraction of the final BA.

:class:`SelfCalibration` belongs to a :class:`sfm.mapper.bundle_adjuster.BundleAdjuster`, whose
problems it tests on, and remembers within one model what it decided: a camera whose principal
point is already off its nominal value passed before and keeps it free unless
:meth:`SelfCalibration.retest` asks for the test again, as a merged model does of what its
clusters decided (each on its part of the photos; with many clusters, one passes by chance
more often than one test on the whole model would); one the split-sample step held stays
held, untested again.  The first two steps of the principal
point's test are cheap and run at every final BA, as does the distortion test; the split-sample
step, two BAs of half the images each, runs only for a camera that passed them.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from backend.ba_problem import BAOptions, BAProblem
from backend.bundle_adjustment import bundle_adjust, free_ds2, refine_level
from backend.calibration_step import calibration_step
from backend.camera_models import ds2_from_params, model_spec
from sfm.execution.spare_cores import run_beside
from sfm.mapper.distortion import DistortionTest, check_distortion, distortion_components, hold_components
from sfm.mapper.principal_point import MIN_HALF_IMAGES, PrincipalPointTest, check_principal_point, confirm_by_halves, split_halves

log = logging.getLogger(__name__)

def half_calibration(task: tuple[BAProblem, BAOptions]):
    """One half of the principal point's split-sample step (:meth:`SelfCalibration.halves`): the
    problem of one camera's half of the images, bundle-adjusted alone with ``options``, then the
    calibration step from where it stopped, which completes the estimate to first order: a half
    that converges slowly is one that determines the principal point poorly, and its covariance
    says so.  ``(the camera's parameters, (Cal3DS2 step, (9, 9) covariance) or None for a
    singular system, iterations, seconds)``; arrays only, so a spare core's process can compute
    it (``sfm.execution.spare_cores``)."""
    problem, options = task
    result = bundle_adjust(problem, options)
    adjusted = replace(problem, camera_params=result.camera_params, rotations=result.rotations,
                       translations=result.translations, points=result.points)
    [step] = calibration_step(adjusted, options)
    return np.asarray(result.camera_params[0], float), step, result.iterations, result.time_s


class SelfCalibration:
    """The self-calibration decisions of one model's final BAs (module docstring)."""

    def __init__(self, adjuster) -> None:
        """``adjuster``: the :class:`sfm.mapper.bundle_adjuster.BundleAdjuster` that owns this
        and builds the problems the tests run on."""
        self.adjuster = adjuster
        self.state = adjuster.state
        # camera index -> the principal point and distortion tests of the last final BA that ran them
        self.principal_point_tests: dict[int, PrincipalPointTest] = {}
        self.distortion_tests: dict[int, DistortionTest] = {}
        # cameras whose distortion a final BA of the model's last refinement estimated beyond any lens
        self.beyond_lens: set[int] = set()
        # cameras whose split-sample step held the principal point in this model: not tested again
        self.held_by_halves: set[int] = set()
        # cameras whose principal point is to be tested again although it passed before (retest)
        self._retest: set[int] = set()

    def final_levels(self, free: np.ndarray, tracks: np.ndarray, loss_scale: float) -> list[str]:
        """What the final BA of the images ``free`` on ``tracks`` (robust loss at ``loss_scale``
        pixels) refines of each camera of the state: the focal length always, the distortion of
        the cameras that pass :func:`check_distortion` (its estimate with the principal point
        held), the principal point of those that pass :func:`check_principal_point` and then
        :func:`confirm_by_halves` on :meth:`halves`.  A camera whose distortion or principal point
        is held goes back to its nominal values for the BA."""
        s = self.state
        levels = ["focal_radial"] * len(s.priors)
        pp_free: dict[int, bool] = {}  # the cameras the tests decide, and whether the principal point is free
        untested = []  # cameras whose principal point is tested now
        for c in np.unique(s.cam_index[free]).tolist():
            prior = s.priors[c]
            if prior.fixed:
                continue
            nominal, current = ds2_from_params(prior.model, prior.params), ds2_from_params(prior.model, s.params[c])
            pp_free[c] = bool(np.any(nominal[[3, 4]] != current[[3, 4]]))
            if (c in self._retest or not pp_free[c]) and c not in self.held_by_halves:
                untested.append(c)
            levels[c] = refine_level(True, pp_free[c])
        if not untested and not any(distortion_components(s.priors[c].model) for c in pp_free):
            return levels
        problem, _, _, cams = self.adjuster.problem(free, self.adjuster.track_subset(tracks))
        if problem is None:
            return levels
        trial = tuple("all" if c in untested else "focal_radial" if c in pp_free else "none" for c in cams)
        held: dict[int, np.ndarray] = {}  # camera key -> its parameters, held ones back at their nominal values

        def hold(c: int, components: list[int]) -> None:  # camera c's components back at their nominal values
            nominal_params = np.asarray(s.priors[c].params, float)
            held.setdefault(s.cam_keys[c], s.params[c].copy())[components] = nominal_params[components]

        # None where the system is singular (images joined to the rest by too few tracks): the
        # tests then keep COLMAP's choice (principal point held, distortion refined).
        steps = calibration_step(problem, BAOptions(loss=s.opts.loss, loss_scale=loss_scale, refine_intrinsics=trial))
        for k, c in enumerate(cams.tolist()):
            if c not in pp_free:
                continue
            prior = s.priors[c]
            nominal, current = ds2_from_params(prior.model, prior.params), ds2_from_params(prior.model, s.params[c])
            step, cov = steps[k] if steps[k] is not None else (None, None)
            num_images = int(np.sum(s.registered & (s.cam_index == c)))
            if c in untested:
                estimate = current + (step if step is not None else 0.0)
                test = check_principal_point(nominal, estimate, cov, free_ds2(prior.model, "all"))
                if test.accepted:
                    test = confirm_by_halves(test, nominal, self.halves(c, free, tracks, loss_scale))
                    if not test.accepted:
                        self.held_by_halves.add(c)
                if pp_free[c]:  # tested again (retest)
                    if not np.isfinite(test.chi2):  # nothing to test it with yet: the earlier decision stands
                        test = replace(test, accepted=True, reason="refined before, not testable now")
                    else:
                        self._retest.discard(c)
                    if not test.accepted:  # held now: back to the nominal value
                        hold(c, list(model_spec(prior.model).pp_idx))
                self.principal_point_tests[c] = test
                log.info("%s: camera %d (%d images): %s", s.payload.label, c, num_images, test.summary())
                pp_free[c] = test.accepted
                if step is not None:  # the distortion's estimate with the principal point held
                    try:
                        step, cov = hold_components(step, cov, free_ds2(prior.model, "all"), [3, 4])
                    except np.linalg.LinAlgError:
                        step, cov = None, None
            distortion = check_distortion(prior.model, nominal, current + (step if step is not None else 0.0), cov)
            if distortion_components(prior.model):
                self.distortion_tests[c] = distortion
                if distortion.beyond_lens:
                    self.beyond_lens.add(c)
                log.info("%s: camera %d (%d images): %s", s.payload.label, c, num_images, distortion.summary())
            if not distortion.accepted and distortion_components(prior.model):
                hold(c, list(model_spec(prior.model).extra_idx))
            levels[c] = refine_level(distortion.accepted, pp_free[c])
        if held:
            s.set_camera_params(held)  # one update of the normalised coordinates
        return levels

    def decided_levels(self, free: np.ndarray) -> list[str]:
        """What a final BA of the images ``free`` refines of each camera without testing: the
        focal length, and the distortion and the principal point where they are off their
        nominal values, i.e. where earlier tests refined them (in this model, or in the models
        whose estimates a merge pooled).  For a BA from a state that is not a BA's optimum, where
        the tests' linearisation would not hold (a merged model's poses come from similarity
        transforms)."""
        s = self.state
        levels = ["focal_radial"] * len(s.priors)
        for c in np.unique(s.cam_index[free]).tolist():
            prior = s.priors[c]
            if prior.fixed:
                continue
            spec, nominal = model_spec(prior.model), np.asarray(prior.params, float)
            off = s.params[c] != nominal
            levels[c] = refine_level(bool(np.any(off[list(spec.extra_idx)])), bool(np.any(off[list(spec.pp_idx)])))
        return levels

    def halves(self, camera: int, free: np.ndarray, tracks: np.ndarray, loss_scale: float):
        """The split-sample step of the principal point test (``principal_point.confirm_by_halves``):
        camera ``camera``'s images among ``free``, split in two by :func:`split_halves`; each half
        bundle-adjusted alone on the observations of ``tracks`` in its images (every pose and
        point free, the camera's intrinsics all refined, the gauge held by the BA's priors), then
        its Cal3DS2 estimate and covariance (:func:`half_calibration`).  The two are independent:
        the first runs on a spare core when this task has one (``sfm.execution.spare_cores``: a
        map stage of one cluster) and the two fit in one BA's memory budget together, with the
        same result as here.  Every track, unless the two halves together would exceed twice
        ``ba_max_observations``: then the growing model's track subset.  None when a half has
        fewer than ``MIN_HALF_IMAGES`` images or its system is singular."""
        s = self.state
        _, owner = s.inlier_rows(tracks)
        budget = self.adjuster.observation_budget(np.bincount(owner))
        if budget and len(owner) > 2 * budget:
            tracks = self.adjuster.track_subset(tracks)  # each half within the BA memory budget
        images = free[s.cam_index[free] == camera]
        centers = -np.einsum("nji,nj->ni", s.R[images], s.t[images])
        low = split_halves(centers)
        halves = (images[low], images[~low])
        if min(len(half) for half in halves) < MIN_HALF_IMAGES:
            return None
        problems = [self.adjuster.problem(half, tracks, alone=True)[0] for half in halves]
        if any(problem is None for problem in problems):
            return None
        # Each half stops as a growing model's global BA does; the calibration step from where
        # it stopped completes its estimate (half_calibration).
        options = self.adjuster.growing_options("all", loss_scale)
        together = sum(len(problem.obs_image) for problem in problems)  # both in memory at once
        first = run_beside(half_calibration, (problems[0], options), fits=not budget or together <= budget)
        try:
            second = half_calibration((problems[1], options))
        finally:
            first_solved = first()  # the side process is waited for (and ended) whatever happened here
        estimates = []
        for half, problem, (params, step, iterations, seconds) in zip(halves, problems, (first_solved, second)):
            log.debug("%s: camera %d, %d images alone: %d observations, %d iterations, %.2f s", s.payload.label,
                      camera, len(half), len(problem.obs_image), iterations, seconds)
            if step is None:
                return None
            estimates.append((ds2_from_params(s.priors[camera].model, params) + step[0], step[1]))
        return tuple(estimates)

    def forget(self) -> None:
        """Start a new model: its first final BA tests every camera's principal point and
        distortion again."""
        self.principal_point_tests.clear()
        self.distortion_tests.clear()
        self.beyond_lens.clear()
        self.held_by_halves.clear()
        self._retest.clear()

    def retest(self) -> None:
        """The next final BAs decide every camera's self-calibration again, from the current
        values: also a principal point that passed the test before (in a model that held part
        of the data only), which is set back to its nominal value if it fails now.  Until a
        final BA's system gives a covariance to test it with (a merged model's parts may meet
        in too few tracks at first), the earlier decision stands and it stays refined."""
        self.forget()
        self._retest = set(range(len(self.state.priors)))

    def report(self) -> list[str]:
        """What the model's last final BAs decided of each camera they tested, a line per camera
        (its database id, then each test's summary): for the recording."""
        s = self.state
        cameras = sorted(set(self.principal_point_tests) | set(self.distortion_tests))
        return [f"camera {s.cam_keys[c]} ({s.priors[c].model}): " + "; ".join(
                    test.summary() for test in (self.distortion_tests.get(c), self.principal_point_tests.get(c)) if test)
                for c in cameras]
