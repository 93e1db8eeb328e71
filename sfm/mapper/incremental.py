"""Incremental SfM over one set of images (paper section 3.2: "we choose incremental SfM").

The loop, as COLMAP's incremental mapper: choose an initial pair with many inliers and a wide
triangulation angle (not a homography-dominated pair) and reconstruct it from its essential
matrix (``sfm.mapper.initialization``); then repeatedly register the next best image (most
visible triangulated tracks, well spread) by PnP RANSAC refined on its inliers
(``sfm.mapper.registration``, or ``sfm.mapper.structureless`` when PnP cannot); triangulate the
tracks it newly sees (batched multi-view DLT with angle, depth and reprojection checks); run a
local BA around it; run a global BA (and re-triangulation, and filtering of observations above
``max_reproj_error``) whenever the model has grown by ``global_ba_ratio``
(``sfm.mapper.bundle_adjuster``).  When no image can be registered any more, the model is
refined one last time; a model finished earlier that shares no image with it, but whose points
its images see or the other way round, then joins it as a whole (``sfm.mapper.joining``) and the
model grows on; otherwise a new model is started from the remaining images: several models are
a result, not an error.  A model whose last BAs moved a guessed focal length far
(``FOCAL_RESTART_RATIO``), or less far while they find the camera beyond any lens, is first
grown again from the refined value, as every later model of the camera is, and an earlier model
grown from the rejected value is taken apart.

State lives in flat numpy arrays over the observations of the tracks (``sfm.mapper.tracks``),
so each step is vectorised; the bookkeeping is :class:`sfm.mapper.state.MapperState`.
"""

from __future__ import annotations

import logging

import numpy as np

from backend.camera_models import has_bogus_params
from sfm.core import progress
from sfm.core.model import Reconstruction
from sfm.mapper.bundle_adjuster import FINAL_TOLERANCE, GROWING_TOLERANCE, BundleAdjuster
from sfm.mapper.growth import Growth
from sfm.mapper.initialization import try_initial_pair
from sfm.mapper.joining import FinishedModel, estimate_similarity, join
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.payload import MapperInput
from sfm.mapper.registration import FOCAL_SEARCH_STEP, register_next
from sfm.mapper.state import MapperState
from sfm.mapper.structureless import register_structureless

log = logging.getLogger(__name__)

# A second final BA runs when re-triangulation after the first changed more than this share of
# the observations (COLMAP's ba_global_max_refinement_change, 0.0005): below it the second BA
# moves nothing that matters and costs as much as the first.
MAX_REFINEMENT_CHANGE = 0.0005
# Models of up to this many images get a global BA after every registration (young models
# move a lot).
EARLY_GLOBAL_BA_IMAGES = 10
# A model whose final BAs moved a guessed focal length (no EXIF: 1.2 x the longer side) by more
# than this factor, either way, is grown again from the refined value.  Its registrations and
# filters were decided at a focal length the model rejects, and a growing model cannot always
# correct that: a narrow-field ring grown from a guess several times too short can end at a
# focal length traded against a strong radial distortion, its poses far off.  A lens about
# twice as long as the guess is common (a short telephoto) and its models grow to the right
# focal length; the factor lies above it, so that they are not grown again for nothing.  A
# model whose final BAs also find the camera beyond any lens is grown again from a smaller move
# (``rejected_focal_lengths``).
FOCAL_RESTART_RATIO = 3.0
# Regrowths of one model at most (each starts from the focal length the previous attempt refined).
MAX_FOCAL_RESTARTS = 2


def reconstruct_incremental(payload: MapperInput, opts: MapperOptions, growth: Growth | None = None) -> list[Reconstruction]:
    """All models incremental SfM makes of ``payload``'s images, largest first (paper section
    3.2: the local SfM of one cluster).  ``growth``: filled with each registration step and why
    images were left out (``sfm.mapper.growth``), for the recording."""
    state = MapperState(payload, opts)
    adjuster = BundleAdjuster(state)
    models: list[Reconstruction] = []
    finished: list[FinishedModel] = []  # the closed models, for a later model to join
    tried: set = set()
    min_size = opts.smallest_model(len(payload.names))
    num_images, closed = len(payload.names), 0  # images in the models already closed
    restarts = 0  # of the current model, from the focal lengths its last attempt refined

    def report() -> None:
        progress.report("registered", closed + state.num_registered, num_images)

    while len(models) < opts.max_num_models:
        tried_before = set(tried)
        if not try_initial_pair(state, tried):
            break
        adjuster.global_()
        report()
        if growth is not None:
            growth.record(state, adjuster.last_rms, list(np.flatnonzero(state.registered)))
        grow_and_refine(state, adjuster, growth, report)
        moved, why = rejected_focal_lengths(state, adjuster)
        if moved and restarts < MAX_FOCAL_RESTARTS:
            restarts += 1
            log.info("%s: the model of %d images refined a guessed focal length %s%s: grown again from it",
                     payload.label, state.num_registered,
                     ", ".join(f"{state.start_focal(c):.0f} -> {f:.0f} px" for c, f in moved.items()), why)
            state.restart_model(moved)
            closed -= free_models_grown_far_from(state, moved, finished, models, growth)
            tried.clear()
            tried.update(tried_before)
            if growth is not None:
                growth.discard()
            continue
        restarts = 0
        while (joined := join_a_finished_model(state, adjuster, finished, growth)) is not None:
            if joined.kept is not None:
                models[:] = [m for m in models if m is not joined.kept]
            closed -= joined.size
            grow_and_refine(state, adjuster, growth, report)
        model = to_reconstruction(state)
        model.final_ba = adjuster.final_bas[-1] if adjuster.final_bas else None
        adjuster.final_bas.clear()  # the next model's own
        n = state.num_registered
        closed += n
        if growth is not None:
            growth.record(state, adjuster.last_rms, [])  # the refined model
            growth.close(state, adjuster.calibration.report())
        kept = model if n >= min_size else None
        finished.append(FinishedModel.of(state, kept, len(growth.models) - 1 if growth is not None else None))
        state.close_model()
        if kept is not None:
            models.append(model)
            log.info("%s: model %d with %d images, %d points", payload.label, len(models) - 1, n, len(model.points3D))
        if int(np.sum(~state.used)) < 2:
            break
    models.sort(key=lambda m: -len(m.images))
    if growth is not None:
        growth.finish(min_size)
    return models


def rejected_focal_lengths(state: MapperState, adjuster: BundleAdjuster) -> tuple[dict[int, float], str]:
    """The cameras whose guessed focal length the finished model rejects (camera index -> its
    refined focal length), and why in words when not for the distance alone: refined more than
    ``FOCAL_RESTART_RATIO`` away from the value the model grew from
    (``MapperState.guessed_focal_moves``), or more than ``FOCAL_SEARCH_STEP`` away while the final
    BAs find the camera beyond any lens: COLMAP's bogus camera (a principal point outside the
    image, a distortion parameter above 1: ``backend.camera_models.has_bogus_params``), or a
    distortion estimate the test held for that in any of them (``sfm.mapper.distortion``; held,
    the next final BA may fit the wrong focal length within a lens's range).  A model grown at a
    focal length several times too short makes up for it with intrinsics no lens has, and its
    focal length can stop short of the truth, its poses bent.  Closer than the focal search's
    resolution, a model grown again would start where this one did."""
    moved = state.guessed_focal_moves(FOCAL_RESTART_RATIO)
    beyond = {}
    for c, focal in state.guessed_focal_moves(FOCAL_SEARCH_STEP).items():
        prior = state.priors[c]
        if c not in moved and (has_bogus_params(prior.model, state.params[c], prior.width, prior.height)
                               or c in adjuster.calibration.beyond_lens):
            beyond[c] = focal
    return moved | beyond, " (its final BAs found the camera beyond any lens)" if beyond else ""


def free_models_grown_far_from(state: MapperState, focals: dict[int, float], finished: list[FinishedModel],
                               models: list[Reconstruction], growth: Growth | None) -> int:
    """Take apart the ``finished`` models (and their ``models`` entries) grown from a focal
    length more than ``FOCAL_RESTART_RATIO`` away from the value ``focals`` gives the camera: a
    later model of the camera rejected the focal length they grew at, as the restart rule
    rejects it for the current model, and they would join it as a whole with their poses and
    points made at that focal length (a bent ring).  Their images are free again, for the current
    model to register one by one, or for later models to start from ``focals``.  Returns the
    number of images freed."""
    freed = 0
    for candidate in [m for m in finished if m.grew_far_from(focals, FOCAL_RESTART_RATIO)]:
        against = ", ".join(f"{candidate.start_focals[c]:.0f} px against {f:.0f}"
                            for c, f in focals.items() if c in candidate.start_focals)
        why = (f"the finished model of {candidate.size} images grew at a focal length a later model rejects "
               f"({against}): its images are free again")
        log.info("%s: %s", state.payload.label, why)
        finished.remove(candidate)
        if candidate.kept is not None:
            models[:] = [m for m in models if m is not candidate.kept]
        if growth is not None and candidate.growth_index is not None:
            growth.take_apart(candidate.growth_index, why)
        state.free_images(candidate.images)
        freed += candidate.size
    return freed


def grow(state: MapperState, adjuster: BundleAdjuster, growth: Growth | None, report) -> None:
    """Register images into the current model while any passes (PnP, then structure-less),
    triangulating what each newly sees, with a local BA after each and a global BA (then
    re-triangulation, and the images left without the points that fix a pose leave:
    ``MapperState.drop_unsupported_images``) whenever the model has grown by
    ``global_ba_ratio``; ``report()`` after each registration.  A failed image is retried once
    it sees 20% more points (cheap on large clusters); when nothing else registers, with any
    growth (at most MAX_REG_TRIALS failures), then without PnP."""
    opts = state.opts
    last_global = state.num_registered
    while register_next(state) or register_structureless(state):
        state.triangulate_new(state.last_registered)
        if state.num_registered >= opts.global_ba_ratio * last_global or state.num_registered <= EARLY_GLOBAL_BA_IMAGES:
            adjuster.global_()  # covers what the local BA would adjust
            state.retriangulate()
            state.drop_unsupported_images()
            last_global = state.num_registered
        else:
            adjuster.local(state.last_registered)
        report()
        if growth is not None:
            new = state.last_registered  # a global BA's filtering may have dropped it again
            growth.record(state, adjuster.last_rms, [new] if state.registered[new] else [])


def join_a_finished_model(state: MapperState, adjuster: BundleAdjuster, finished: list[FinishedModel],
                          growth: Growth | None) -> FinishedModel | None:
    """Join the largest of the ``finished`` models that can be registered as one body in the
    current model (``sfm.mapper.joining``), then a global BA and re-triangulation; the model
    joined (removed from ``finished``), or None when none can be, and then ``growth`` notes why
    each could not (``Growth.not_joined``)."""
    why_not: dict[int, str] = {}  # growth index of a finished model -> why it did not join
    for k in sorted(range(len(finished)), key=lambda k: -finished[k].size):
        candidate = finished[k]
        sim, why = estimate_similarity(state, candidate, state.opts.seed)
        if sim is None:
            if candidate.growth_index is not None:
                why_not[candidate.growth_index] = why
            continue
        before = state.num_registered
        images = join(state, candidate, sim)
        how = (f"at {before} images, the finished model of {candidate.size} images joined it as a whole: scale "
               f"{sim.scale:.3g}, {sim.inliers} of the {sim.rays} rays between them within "
               f"{state.opts.abs_pose_max_error:g} px; {state.num_registered} images")
        log.info("%s: %s", state.payload.label, how)
        del finished[k]
        adjuster.global_()
        state.retriangulate()
        state.drop_unsupported_images()
        if growth is not None:
            if candidate.growth_index is not None:
                growth.absorb(candidate.growth_index, how)
            growth.record(state, adjuster.last_rms, images.tolist())
        return candidate
    if growth is not None:
        growth.not_joined(why_not)
    return None


def grow_and_refine(state: MapperState, adjuster: BundleAdjuster, growth: Growth | None, report) -> None:
    """:func:`grow`, then :func:`final_refinement`; when the refinement's filtering leaves an
    image too few points to determine its pose (``MapperState.drop_unsupported_images``), the
    model grows again, as it may register that image anew, and is refined again if it did."""
    grow(state, adjuster, growth, report)
    final_refinement(state, adjuster)
    while state.drop_unsupported_images():
        before = state.num_registered
        grow(state, adjuster, growth, report)
        if state.num_registered == before:
            return
        final_refinement(state, adjuster)


def final_refinement(state: MapperState, adjuster: BundleAdjuster) -> None:
    """Final global BA, re-triangulation, and a second final BA if that changed enough.

    The first BA stops at the growing model's looser tolerance (``GROWING_TOLERANCE``):
    re-triangulation usually changes the problem, and the second BA, run to
    ``FINAL_TOLERANCE``, starts from there.  When nothing changed enough, the second BA runs
    only if the first stopped short of ``FINAL_TOLERANCE`` (its last decrease was larger), so
    the last BA of every model reaches it."""
    adjuster.calibration.forget()  # another model than the last one refined
    adjuster.global_(final=True, tolerance=GROWING_TOLERANCE)
    first_decrease = adjuster.last_decrease
    before = int(state.obs_inlier.sum())
    state.retriangulate()
    changed = int(state.obs_inlier.sum()) - before
    if changed > MAX_REFINEMENT_CHANGE * max(before, 1) or first_decrease >= FINAL_TOLERANCE:
        adjuster.global_(final=True)
    else:
        log.debug("%s: re-triangulation changed %d of %d observations and the first final BA "
                  "converged: no second final BA", state.payload.label, changed, before)
