"""Bridges between the parts of the cluster graph that share no aligned cluster pair.

The merge aligns two local models through the cameras both registered (paper section 3.2.1):
at least ``min_common_cameras`` of them, and a similarity RANSAC agrees on.  Where the image
graph joins two clusters by a few image edges only, their expanded overlap holds a few images,
and a model may register too few of them, or register them too differently, to be aligned by
its cameras: the cluster graph then falls into parts that the merge leaves as separate models
(section 3.2.3 merges only along the graph's edges).  The same photos still see each other's
points: the images of one part are matched to those of the other, which is how the image graph
joined the clusters in the first place.

A part is registered to another as one rigid body on PnP's terms, as the mapper joins a finished
model to the one it grows (:mod:`sfm.mapper.joining`, the same estimate): the rotation between
the two frames from the essential matrix of a pair of images matched across them, the scale and
translation from every observation in one part's images of a point the other part holds,
accepted with at least ``abs_pose_min_num_inliers`` inliers within ``abs_pose_max_error``
pixels, ``abs_pose_min_inlier_ratio`` of the rays, in two images or more.  Each part is the
merged model of its own merge plan (its local models in its anchor's frame, with their own
points and the tracks their poses triangulate), so the similarity found maps one anchor's
frame into the other's: a cluster-graph edge between the two anchors.

A bridge is weaker evidence than an edge from common cameras (its inliers are rays at PnP's
threshold, not camera poses both models estimated): it is weighted above every edge the merge
keeps (``max_msd``), and among bridges the one with more inlier rays first, so the minimum
spanning tree takes a bridge only where no edge from common cameras joins the parts.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from backend.sim3 import Sim3
from sfm.mapper.joining import FinishedModel, estimate_similarity
from sfm.mapper.options import MapperOptions
from sfm.mapper.payload import MapperInput
from sfm.mapper.state import MapperState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Bridge:
    """Part ``moved``'s frame mapped into part ``into``'s (``into_from_moved``), found from
    ``inliers`` of the ``rays`` between them."""

    into: int
    moved: int
    into_from_moved: Sim3
    inliers: int
    rays: int
    common_images: int  # registered in both parts


def part_models(state: MapperState, parts: list[tuple[dict, dict, tuple]]) -> list[FinishedModel]:
    """Each part (``(poses, camera parameters, points)`` of a merge plan, as
    ``sfm.merge.alignment`` gives them) as a model of ``state``: its images at their merged
    poses, its local models' own points on the tracks they observe, and the other tracks its
    images see triangulated with those poses."""
    models = []
    for poses, params, points in parts:
        state.restart_model({})
        state.set_camera_params(params)
        state.set_poses(poses)
        state.seed_points(*points)
        state.retriangulate()
        models.append(FinishedModel.of(state))
    return models


def find_bridges(payload: MapperInput, opts: MapperOptions, parts: list[tuple[dict, dict, tuple]],
                 seed: int = 0, finished: list[bool] | None = None) -> list[Bridge]:
    """Every pair of ``parts`` (``(poses, camera parameters, points)`` of each merge plan, in
    the plans' order) that a similarity joins on PnP's terms (module docstring), the larger part
    as ``into``.  ``payload``: the images of all the parts and their verified matches.
    ``finished``: parts that are models of an earlier run (``graphsfm extend``): two of them are
    not tried together, as that run kept them apart."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # the parts are final: nothing registers a dropped image again
    models = part_models(state, parts)
    finished = finished or [False] * len(parts)
    bridges = []
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            if finished[a] and finished[b]:
                continue
            into, moved = (a, b) if models[a].size >= models[b].size else (b, a)
            current = models[into]
            registered, R, t, track_valid, track_xyz = current.arrays(state)
            state.load_model(registered, R, t, track_xyz, track_valid, current.params)
            found = estimate_similarity(state, models[moved], seed)
            if found is None:
                log.info("merge: parts %d and %d: no similarity from the rays between them", into, moved)
                continue
            log.info("merge: part %d joins part %d from %d of %d rays", moved, into, found.inliers, found.rays)
            common = len(np.intersect1d(models[into].images, models[moved].images))
            bridges.append(Bridge(into, moved, Sim3(found.scale, found.R, found.t), found.inliers, found.rays, common))
    return bridges


def bridge_edges(plans: list, bridges: list[Bridge], max_msd: float) -> dict:
    """Cluster-graph edges (``sfm.merge.cluster_graph``'s form, ``(u, v)`` with ``u < v`` and
    ``sim`` mapping ``u``'s frame into ``v``'s) between the anchors of the merge plans that
    ``bridges`` join: each part's models are in its anchor's frame, so a bridge between parts
    is an alignment of their anchors."""
    edges = {}
    for bridge in bridges:
        u, v, sim = plans[bridge.moved].anchor, plans[bridge.into].anchor, bridge.into_from_moved
        if u > v:
            u, v, sim = v, u, sim.inverse()
        edges[(u, v)] = {"sim": sim, "msd": None, "weight": bridge_weight(bridge.inliers, max_msd),
                         "inliers": bridge.inliers, "rays": bridge.rays, "common_cameras": bridge.common_images,
                         "common_points": 0, "used": True, "bridge": True}
    return edges


def bridge_weight(inliers: int, max_msd: float) -> float:
    """The cluster-graph weight of a bridge (module docstring): above every kept edge's MSD
    (at most ``max_msd``), lower with more inlier rays."""
    return max_msd + 1.0 / max(inliers, 1)
