"""Global refinement of the merged model (paper section 3 and Figure 1: after merging).

The tracks of a merge component start from the local models' own points, moved into the merged
frame (a local model's points fit its own poses and calibration, which a triangulation with the
pooled calibration would not see), the others are triangulated with the merged poses, then
global BA and filtering alternate with re-triangulation until re-triangulation changes almost
nothing (the
paper: "The re-triangulation step and bundle adjustment step can be executed alternatively until
convergence"; COLMAP's global refinement stops the same way).  Merged poses come from similarity
transforms, not from a BA over the merged tracks, so the first triangulation rejects observations
that the first BA brings back within reach: on clusters joined through thin overlaps one
alternation is not enough.  The merged model's final BAs decide each camera's distortion and
principal point again, on all its photos (``SelfCalibration.retest``): each cluster decided on
its part of them.  They do so only once the merged poses fit the merged tracks
(:func:`refine_merged`): the tests read the step and covariance of a BA linearised at the
current state, which the similarity transforms leave off a BA's optimum.

The merged model then registers the photos no local model holds (:func:`register_left_out`):
those of a cluster whose local SfM found no initial pair, and those a cluster's model could not
take.  Each is tried as incremental SfM tries an image (PnP on the points it sees, COLMAP's
terms), now against the whole merged model, whose tracks a small cluster's part of the scene
may lack; it goes to the merge component it shares the most verified matches with
(:func:`left_out_by_component`).
"""

from __future__ import annotations

import logging

import numpy as np

from backend.memory import return_freed_memory
from sfm.core.model import Reconstruction
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.incremental import MAX_REFINEMENT_CHANGE, grow
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.payload import MapperInput
from sfm.mapper.state import MapperState

log = logging.getLogger(__name__)

# The most global BAs of the refinement (COLMAP's ba_global_max_refinements).
MAX_REFINEMENTS = 5


def refine_with_poses(payload: MapperInput, opts: MapperOptions, poses: dict[str, tuple[np.ndarray, np.ndarray]],
                      camera_params: dict[int, np.ndarray], calibration: list[str] | None = None,
                      points=None) -> Reconstruction:
    """Global refinement of merged poses (paper Figure 1, after merging; section 3): the
    tracks start from ``points`` (``sfm.merge.alignment.merged_points``: the local models' own
    points in the merged frame, with the rows each model kept; ``MapperState.seed_points``),
    every other track of the payload is triangulated with the given ``cam_from_world`` poses
    (by image name) and camera parameters (by camera id), then global BA and filtering
    alternate with re-triangulation (:func:`alternate_until_converged`).  The payload's images
    without a pose are then registered where PnP takes them (:func:`register_left_out`).  These
    BAs keep the local BAs' robust loss scale (``opts.loss_scale``), as
    the merged clusters' own global BAs do (``MapperOptions.global_loss_scale``): the merged
    tracks were filtered against poses moved by similarity transforms, not by a BA over them.
    ``calibration``: a list that receives what the BAs refined of each camera, a line per
    camera (``SelfCalibration.report``)."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # nothing would register the dropped images again
    state.release_pairs(keep=np.array([i for i, name in enumerate(state.names) if name not in poses], np.int64))
    del payload  # the caller passes its only reference: the matches go with it
    return_freed_memory()
    state.set_camera_params(camera_params)
    state.set_poses(poses)
    adjuster = BundleAdjuster(state)
    if points is not None:
        log.info("%s: %d tracks start from the local models' points", state.payload.label, state.seed_points(*points))
    state.retriangulate()
    refine_merged(state, adjuster, opts.loss_scale)
    register_left_out(state, adjuster, opts.loss_scale)
    if calibration is not None:
        calibration.extend(adjuster.calibration.report())
    model = to_reconstruction(state)
    model.final_ba = adjuster.final_bas[-1] if adjuster.final_bas else None
    return model


def refine_merged(state: MapperState, adjuster: BundleAdjuster, loss_scale: float) -> None:
    """Global BAs of a merged model with the robust loss at ``loss_scale`` pixels, alternating
    with re-triangulation (:func:`alternate_until_converged`) twice: first with what the local
    models decided of each camera (``decide=False``), which fits the poses the similarity
    transforms gave to the merged tracks; then with every camera's self-calibration decided
    again on all the photos (``SelfCalibration.retest``).  The tests linearise the BA at the
    current state (``backend.calibration_step.calibration_step``), which the first
    alternation brings to a BA's optimum: from the merged poses a few pixels off, the
    principal point's covariance comes out several times too wide and a shift the photos
    show is held.  When the first alternation converged and the tests keep every camera as it
    was, the model is already at the second alternation's optimum, which then runs no BA."""
    converged = alternate_until_converged(
        state, lambda: adjuster.global_(final=True, loss_scale=loss_scale, decide=False)) < MAX_REFINEMENTS
    adjuster.calibration.retest()
    skippable = converged  # only the first BA may be skipped: later ones follow a re-triangulation

    def adjust() -> bool:
        nonlocal skippable
        ran = adjuster.global_(final=True, loss_scale=loss_scale, only_if_changed=skippable)
        skippable = False
        return ran

    alternate_until_converged(state, adjust)


def alternate_until_converged(state: MapperState, adjust) -> int:
    """Run ``adjust`` (a BA with its filtering), then re-triangulate, until re-triangulation
    changes at most :data:`~sfm.mapper.incremental.MAX_REFINEMENT_CHANGE` of the inlier
    observations (COLMAP's ba_global_max_refinement_change) or :data:`MAX_REFINEMENTS` BAs ran
    (paper section 3: re-triangulation and BA "executed alternatively until convergence").
    Returns the number of BAs."""
    for rounds in range(1, MAX_REFINEMENTS + 1):
        if adjust() is False:  # nothing to adjust: converged
            return rounds - 1
        before = int(state.obs_inlier.sum())
        state.retriangulate()
        changed = int(state.obs_inlier.sum()) - before
        log.info("%s: refinement %d, re-triangulation changed %d of %d observations",
                 state.payload.label, rounds, changed, before)
        if changed <= MAX_REFINEMENT_CHANGE * max(before, 1):
            break
    return rounds


def register_left_out(state: MapperState, adjuster: BundleAdjuster, loss_scale: float) -> int:
    """Register the images of the refined merged model's payload that have no pose (module
    docstring) by incremental SfM's growth (``sfm.mapper.incremental.grow``: PnP, triangulation,
    local and global BAs), then refine again as :func:`refine_merged` does, every camera's
    self-calibration decided on all the photos; the number of images registered."""
    before = state.num_registered
    if before == len(state.names):
        return 0
    grow(state, adjuster, None, lambda: None)
    added = state.num_registered - before
    if added:
        log.info("%s: %d of the %d images no local model holds registered in the merged model",
                 state.payload.label, added, len(state.names) - before)
        alternate_until_converged(state, lambda: adjuster.global_(final=True, loss_scale=loss_scale))
    return added


def left_out_by_component(component: np.ndarray, first: np.ndarray, second: np.ndarray,
                          inliers: np.ndarray, num_components: int) -> list[np.ndarray]:
    """Which images no component holds each component takes (module docstring): ``component``
    gives each image's component (-1: in none), ``first``, ``second`` and ``inliers`` the verified
    pairs (image indices, inlier counts).  An image goes to the component whose registered images
    it shares the most inliers with (the first of equals), an image sharing none to no component;
    the image indices of each component, ascending."""
    first, second = np.asarray(first, np.int64), np.asarray(second, np.int64)
    votes = np.zeros((len(component), max(num_components, 1)))
    for image, other in ((first, second), (second, first)):
        rows = (component[image] < 0) & (component[other] >= 0)
        np.add.at(votes, (image[rows], component[other[rows]]), np.asarray(inliers, float)[rows])
    voted = np.flatnonzero((component < 0) & (votes.sum(axis=1) > 0))
    choice = np.argmax(votes[voted], axis=1)
    return [voted[choice == k] for k in range(num_components)]
