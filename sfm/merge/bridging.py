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
frame into the other's: a cluster-graph edge between the two anchors.  As the mapper grows one
model, a part that joins another becomes one with it, and the parts left are tried again
against their union: a part may see too few points of each of two parts alone.

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
from sfm.mapper.joining import FinishedModel, estimate_similarity, join
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
                 seed: int = 0, finished: list[bool] | None = None,
                 why_not: dict[tuple[frozenset, frozenset], str] | None = None) -> list[Bridge]:
    """The bridges that join ``parts`` (``(poses, camera parameters, points)`` of each merge
    plan, in the plans' order) on PnP's terms (module docstring), found as the mapper joins its
    models: the larger of two parts receives the other, their union (in the receiver's frame,
    its tracks triangulated again) is one part from then on, and the parts are tried again
    until no pair joins: a small part may see too few points of any one part, yet enough of
    two joined ones.  ``into`` and ``moved`` name the parts whose frames a bridge relates (each
    union keeps its receiver's frame).  ``payload``: the images of all the parts and their
    verified matches.  ``finished``: parts that are models of an earlier run (``graphsfm
    extend``): two unions of only such parts are not tried together, as that run kept them
    apart.  ``why_not``: receives why each pair of unions tried did not join (their parts, the
    receiver's first -> in words, ``sfm.mapper.joining.estimate_similarity``)."""
    state = MapperState(payload, opts)
    state.camera_filter = False  # the parts are final: nothing registers a dropped image again
    unions = dict(enumerate(part_models(state, parts)))  # frame's part -> the union in its frame
    members = {k: {k} for k in unions}
    finished = finished or [False] * len(parts)
    failed: set[tuple[frozenset, frozenset]] = set()
    bridges = []
    joined = True
    while joined:
        joined = False
        order = sorted(unions, key=lambda k: (-unions[k].size, k))
        for x, a in enumerate(order):
            into, loaded = unions[a], False
            for b in order[x + 1:]:
                key = (frozenset(members[a]), frozenset(members[b]))
                if key in failed or all(finished[k] for k in members[a] | members[b]):
                    continue
                if not loaded:  # the receiver is the state's current model for all its tries
                    registered, R, t, track_valid, track_xyz = into.arrays(state)
                    state.load_model(registered, R, t, track_xyz, track_valid, into.params)
                    loaded = True
                found, why = estimate_similarity(state, unions[b], seed)
                if found is None:
                    log.info("merge: parts %s and %s do not join: %s", sorted(members[a]), sorted(members[b]), why)
                    failed.add(key)
                    if why_not is not None:
                        why_not[key] = why
                    continue
                log.info("merge: parts %s join parts %s from %d of %d rays", sorted(members[b]), sorted(members[a]),
                         found.inliers, found.rays)
                common = len(np.intersect1d(into.images, unions[b].images))
                bridges.append(Bridge(a, b, Sim3(found.scale, found.R, found.t), found.inliers, found.rays, common))
                join(state, unions[b], found)  # the larger receives: the union stays in a's frame
                state.retriangulate()
                unions[a] = FinishedModel.of(state)
                members[a] |= members.pop(b)
                del unions[b]
                joined = True
                break
            if joined:
                break
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
