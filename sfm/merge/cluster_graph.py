"""The cluster graph of the local models and its merge plan (paper section 3.2, Alg. 2, lines 1-2).

Every pair of local models that share at least ``min_common_cameras`` registered images gets a
similarity from their common cameras (section 3.2.1, ``backend.similarity``: median scale
ratio, Eq. 1-2, then rotation and translation by RANSAC, Eq. 3-6) weighted by the normalised
MSD over their common 3D points (points observed through the same (image, keypoint)), section
3.2.2, Eq. 10-11; edges above ``max_msd`` are dropped (the paper's dotted edges, Figure 3).  The
Kruskal MinST over what remains and the minimum-height-tree anchor of each connected part
(section 3.2.3, Alg. 2, lines 2-12) are ``graph.merge_plan``'s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from backend.similarity import SimilarityOptions, estimate_similarity
from graph.merge_plan import MergePlan, plan_merges
from sfm.core import progress
from sfm.core.model import INVALID_POINT3D, Reconstruction
from sfm.merge.options import MergeOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalModel:
    """One local model of the ``map`` stage: cluster ``k``'s model ``m`` (a node of the cluster graph)."""

    label: str  # "C<k>/<m>"
    model: Reconstruction


def common_data(a: Reconstruction, b: Reconstruction):
    """Common registered cameras (their poses in both models) and common 3D points (pairs of
    point ids observing the same keypoint of a common image)."""
    by_name_b = {im.name: im for im in b.images.values()}
    common = [(im, by_name_b[im.name]) for im in a.images.values() if im.name in by_name_b]
    if not common:
        return None
    Ra = np.array([x.cam_from_world_rotation for x, _ in common])
    ta = np.array([x.cam_from_world_translation for x, _ in common])
    Rb = np.array([y.cam_from_world_rotation for _, y in common])
    tb = np.array([y.cam_from_world_translation for _, y in common])
    pairs = set()
    for x, y in common:
        both = (x.point3D_ids != INVALID_POINT3D) & (y.point3D_ids != INVALID_POINT3D)
        pairs.update(zip(x.point3D_ids[both].tolist(), y.point3D_ids[both].tolist()))
    pairs = sorted(pairs)
    pa = np.array([a.points3D[p].xyz for p, _ in pairs]).reshape(-1, 3)
    pb = np.array([b.points3D[q].xyz for _, q in pairs]).reshape(-1, 3)
    return [x.name for x, _ in common], Ra, ta, Rb, tb, pa, pb


def build_cluster_graph(models: list[LocalModel], options: MergeOptions, seed: int = 0) -> dict:
    """Similarity (``v_from_u``) and MSD of every pair of local models that can be aligned: the
    cluster graph's edges (Alg. 2, line 1; section 3.2.1, Eq. 1-6, and section 3.2.2, Eq. 10-11)."""
    edges = {}
    sim_opts = SimilarityOptions(min_common_cameras=options.min_common_cameras, max_msd=options.max_msd, seed=seed)
    num_pairs, done = len(models) * (len(models) - 1) // 2, 0
    for u in range(len(models)):
        for v in range(u + 1, len(models)):
            done += 1
            progress.report("model_pairs", done, num_pairs)
            data = common_data(models[u].model, models[v].model)
            if data is None or len(data[0]) < options.min_common_cameras:
                continue
            names, Ra, ta, Rb, tb, pa, pb = data
            res = estimate_similarity(Ra, ta, Rb, tb, pa if len(pa) else None, pb if len(pb) else None, sim_opts)
            if res is None:
                continue
            edges[(u, v)] = {
                "sim": res.sim_b_from_a,
                "msd": float(res.msd), "inliers": int(res.num_inliers), "common_cameras": len(names),
                "common_points": int(res.num_points), "used": bool(res.msd <= options.max_msd),
            }
    return edges


def plan_components(models: list[LocalModel], edges: dict) -> list[MergePlan]:
    """The merge plan of every connected part of the cluster graph's used edges: Kruskal MinST and
    minimum-height-tree anchor (section 3.2.3, Alg. 2, lines 2-12; ``graph.merge_plan``), a
    model's size being its number of images; an edge's weight is its MSD, a bridge's its
    ``weight`` (``sfm.merge.bridging``)."""
    sizes = {k: len(m.model.images) for k, m in enumerate(models)}
    weights = {(u, v): e.get("weight", e["msd"]) for (u, v), e in edges.items() if e["used"]}
    return plan_merges(list(range(len(models))), sizes, weights)


def unjoined_parts(models: list[LocalModel], edges: dict, plans: list[MergePlan], options: MergeOptions,
                   bridge_failures: dict[tuple[frozenset, frozenset], str] | None = None) -> list[dict]:
    """Why each merge component other than the first (Alg. 2 merges only along cluster-graph
    edges) joins no other: the pair of local models, one inside and one outside, sharing the
    most registered images, and what stopped their edge (no common image, fewer than
    ``min_common_cameras``, no similarity found, or its MSD above ``max_msd``); with
    ``bridge_failures`` (the merge tried to bridge the parts, ``sfm.merge.bridging``: why each
    pair of parts tried did not join, by the node ids of each side), also why no bridge from
    the rays between it and the first component joined it."""
    names = [{im.name for im in m.model.images.values()} for m in models]
    found = []
    for plan in plans[1:]:
        inside = set(plan.clusters)
        outside = [v for v in range(len(models)) if v not in inside]
        best = max(((len(names[u] & names[v]), u, v) for u in sorted(inside) for v in outside), default=None)
        entry = {"models": [models[u].label for u in sorted(inside)]}
        if best is None:
            found.append({**entry, "nearest": None, "common_images": 0, "reason": "no other local model"})
            continue
        common, u, v = best
        edge = edges.get((min(u, v), max(u, v)))
        if common == 0:
            reason = "shares no registered image with any other local model"
        elif common < options.min_common_cameras:
            reason = (f"{models[u].label} and {models[v].label} share {common} registered images, fewer than "
                      f"--min-common-cameras {options.min_common_cameras}")
        elif edge is None:
            reason = (f"{models[u].label} and {models[v].label} share {common} registered images but no "
                      f"similarity fits them (RANSAC found no consensus)")
        else:
            reason = (f"{models[u].label} and {models[v].label} align with an MSD of {edge['msd']:.3g}, above "
                      f"--max-msd {options.max_msd:g}")
        found.append({**entry, "nearest": models[v].label, "common_images": common, "reason": reason})
    if bridge_failures is not None:
        first = frozenset(plans[0].clusters) if plans else frozenset()
        for plan, part in zip(plans[1:], found):
            inside = frozenset(plan.clusters)
            why = bridge_failures.get((first, inside)) or bridge_failures.get((inside, first))
            part["reason"] += ("; nor did the rays between its photos and the first part's points join it as one "
                               "rigid body" + (f": {why}" if why else ""))
    return found
