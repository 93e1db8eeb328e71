"""New images merged into a finished model held as the anchor (``graphsfm extend``; paper
section 3.2, Alg. 2 with the anchor given).

The finished model is one more node of the cluster graph, next to the local models of the new
images' clusters; the cluster graph's edges are the similarities and MSDs of section 3.2.1-3.2.2
(:func:`sfm.merge.cluster_graph.build_cluster_graph`), the MinST is Alg. 2's line 2, and the
tree is rooted at the finished model instead of a minimum-height-tree centre
(``graph.merge_plan.plan_merges(anchor=...)``), so the finished model never moves: every new
model is mapped into its frame along its tree path, and an image it already registered keeps
its pose there.  Parts of the graph that no common cameras join are bridged where their photos
see each other's points, as in the ``merge`` stage (``sfm.merge.bridging``; two models of the
earlier run are not bridged to each other); local models that no path joins to it then stay
models of their own.

The merged model is then re-triangulated with every pose, and bundle-adjusted in the region of
the new images only (``BundleAdjuster.region``: the new images and the old ones that share
points with them free, the images beyond held), the points outside that region re-estimated
with their cameras held.  ``full_ba``, or a region of at least :data:`FULL_BA_REGION_SHARE` of
the model, runs the global BA of the ``merge`` stage instead, from the intrinsics pooled over
the finished model and the new models, with the self-calibration decisions made again.
"""

from __future__ import annotations

import logging

import numpy as np

from backend.memory import return_freed_memory
from graph.merge_plan import MergePlan, plan_merges
from sfm.core.model import Reconstruction
from sfm.mapper.bundle_adjuster import BundleAdjuster
from sfm.mapper.options import MapperOptions
from sfm.mapper.output import to_reconstruction
from sfm.mapper.payload import MapperInput
from sfm.mapper.state import MapperState
from sfm.merge.alignment import anchor_from_model, merged_poses
from sfm.merge.cluster_graph import LocalModel, build_cluster_graph
from sfm.merge.options import MergeOptions
from sfm.merge.refinement import alternate_until_converged, refine_merged

log = logging.getLogger(__name__)

ANCHOR = 0  # the finished model is node 0 of the extension's cluster graph
# A region BA that frees at least this share of the extended model's images costs about what a
# global BA costs, yet cannot refine the intrinsics of a camera that the held images share: the
# extension then gets the global BA.  Its new images are then as much of the model as the old
# ones, and the finished model's calibration decisions (``sfm.mapper.distortion``,
# ``sfm.mapper.principal_point``) rested on half of the data or less: they are made again.
FULL_BA_REGION_SHARE = 0.5


def plan_extension(nodes: list[LocalModel], options: MergeOptions, seed: int = 0) -> tuple[dict, list[MergePlan]]:
    """The cluster graph of the finished model (``nodes[0]``) and the new local models
    (section 3.2.1-3.2.2, Alg. 2, line 1), and its merge plans: Kruskal MinST (line 2), the
    component of the finished model rooted at it (Alg. 2 with the anchor given), every other
    component planned as in the ``merge`` stage (lines 3-12).  The anchor's plan comes first."""
    edges = build_cluster_graph(nodes, options, seed=seed)
    return edges, extension_plans(nodes, edges)


def extension_plans(nodes: list[LocalModel], edges: dict) -> list[MergePlan]:
    """The merge plans of :func:`plan_extension` over ``edges`` (bridges among them, weighted
    by their ``weight``, ``sfm.merge.bridging``)."""
    sizes = {k: len(m.model.images) for k, m in enumerate(nodes)}
    weights = {(u, v): e.get("weight", e["msd"]) for (u, v), e in edges.items() if e["used"]}
    return plan_merges(list(range(len(nodes))), sizes, weights, anchor=ANCHOR)


def extended_poses(nodes: list[LocalModel], plan: MergePlan, edges: dict, nominal: dict[int, np.ndarray] | None = None):
    """Poses (by image name) and camera parameters (by camera id) of the anchor's component in
    the anchor's frame (Alg. 2, lines 6 and 10, composed along each tree path): the anchor's own
    images keep their poses exactly; each new image takes the pose of the model nearest the
    anchor that registered it.  ``(poses, params, pooled, sims)``: ``params`` keep the anchor's
    cameras exactly (a region BA holds the images beyond the region with them), ``pooled`` are
    every camera's parameters pooled over the models as the merge pools them (``merged_poses``,
    ``nominal`` as there), the start of a global BA."""
    sims = anchor_from_model(plan, edges)
    poses, pooled = merged_poses(nodes, plan, sims, nominal)
    params = {cam_id: p.copy() for cam_id, p in pooled.items()}
    anchor = nodes[plan.anchor].model
    for cam_id, cam in anchor.cameras.items():
        params[cam_id] = cam.params.copy()
    return poses, params, pooled, sims


def refine_extension(payload: MapperInput, opts: MapperOptions, poses: dict[str, tuple[np.ndarray, np.ndarray]],
                     camera_params: dict[int, np.ndarray], new_names: set[str], full_ba: bool = False,
                     pooled_params: dict[int, np.ndarray] | None = None) -> Reconstruction:
    """The extended model's refinement (Figure 1's re-triangulation and BA after merging, with
    a cost that grows with the new part): every track triangulated with the merged poses, a BA
    of the new images' region (``BundleAdjuster.region``) with the rest held and filtering,
    alternating with re-triangulation until it converges (``alternate_until_converged``, as the
    merge's refinement); the points outside the region are
    re-estimated with their cameras held.  ``full_ba``, or a region of at least
    :data:`FULL_BA_REGION_SHARE` of the model: the global BA of the ``merge`` stage
    (:func:`sfm.merge.refinement.refine_with_poses`) from ``pooled_params`` (None:
    ``camera_params``), every camera's self-calibration tested again (``refine_merged``)."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # nothing would register the dropped images again
    state.release_pairs()
    del payload
    return_freed_memory()
    state.set_camera_params(camera_params)
    state.set_poses(poses)
    new = np.array([i for i, n in enumerate(state.names) if n in new_names], dtype=np.int64)
    adjuster = BundleAdjuster(state)
    state.retriangulate()
    region_images = adjuster.region_images(new)
    if full_ba or len(region_images) >= FULL_BA_REGION_SHARE * state.num_registered:
        log.info("%s: global BA (%s: %d of the %d images in the new images' region)", state.payload.label,
                 "--full-ba" if full_ba else f"at least {FULL_BA_REGION_SHARE:.0%}", len(region_images),
                 state.num_registered)
        if pooled_params is not None:
            state.set_camera_params(pooled_params)
            state.retriangulate()
        refine_merged(state, adjuster, opts.loss_scale)
        return to_reconstruction(state)
    region = np.zeros(0, np.int64)

    def adjust_region() -> None:
        nonlocal region
        region = adjuster.region(new, loss_scale=opts.loss_scale)

    alternate_until_converged(state, adjust_region)
    outside = np.setdiff1d(np.flatnonzero(state.track_valid), region)
    if len(outside):
        adjuster.refine_points(outside)
        state.filter_observations(outside)
    return to_reconstruction(state)
