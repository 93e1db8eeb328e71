"""Global refinement of the merged model (paper section 3 and Figure 1: after merging).

All tracks of a merge component are triangulated with the merged poses, then one global BA and
filtering, re-triangulation, and a second BA only when re-triangulation added enough ("in
practice, it is enough to perform them once").
"""

from __future__ import annotations

import numpy as np

from backend.memory import return_freed_memory
from sfm.core.model import Reconstruction
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.payload import MapperInput
from sfm.mapper.state import MapperState

# A second BA runs when re-triangulation after the first added more than this share of observations.
MIN_RETRIANGULATION_GAIN = 0.02


def refine_with_poses(payload: MapperInput, opts: MapperOptions, poses: dict[str, tuple[np.ndarray, np.ndarray]],
                      camera_params: dict[int, np.ndarray]) -> Reconstruction:
    """Global refinement of merged poses (paper Figure 1, after merging; section 3): every
    track of the payload is triangulated with the given ``cam_from_world`` poses (by image
    name) and camera parameters (by camera id), then global BA and filtering, then
    re-triangulation, and a second global BA only if re-triangulation added more than
    :data:`MIN_RETRIANGULATION_GAIN` of the observations.  Images without a pose stay
    unregistered.  These BAs keep the local BAs' robust loss scale (``opts.loss_scale``), as
    the merged clusters' own global BAs do (``MapperOptions.global_loss_scale``): the merged
    tracks were filtered against poses moved by similarity transforms, not by a BA over them."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # nothing would register the dropped images again
    state.release_pairs()
    del payload  # the caller passes its only reference: the matches go with it
    return_freed_memory()
    state.set_camera_params(camera_params)
    state.set_poses(poses)
    adjuster = BundleAdjuster(state)
    state.retriangulate()
    adjuster.global_(final=True, loss_scale=opts.loss_scale)
    before = int(state.obs_inlier.sum())
    state.retriangulate()
    if state.obs_inlier.sum() > (1 + MIN_RETRIANGULATION_GAIN) * before:
        adjuster.global_(final=True, loss_scale=opts.loss_scale)
    return to_reconstruction(state)
