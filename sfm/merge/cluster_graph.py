"""The ``merge`` stage: local models -> one model per merge component (paper section 3.2, Alg. 2).

1. Cluster graph [3.2.2]: every pair of local models that share >= 2 registered images gets a
   similarity from their common cameras (``backend.similarity``: median scale ratio, then
   rotation + translation by RANSAC) weighted by the normalised MSD over their common 3D points
   (points observed through the same (image, keypoint)); edges above ``max_msd`` are dropped
   (the paper's dotted edges, Figure 4).
2. Merge plan [3.2.3]: Kruskal MinST and the minimum-height-tree anchor (``graph.merge_plan``).
3. Every local model is moved along its tree path into the anchor's frame; an image shared by
   several models keeps the pose from the model nearest the anchor.
4. Global refinement [Figure 1]: all tracks of the component (fused through shared
   (image, keypoint) observations: the union-find tracks of every verified match of its images)
   are re-triangulated with the merged poses, then one global BA, filtering, re-triangulation
   and a last BA (``sfm.mapper.incremental.refine_with_poses``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from backend.similarity import SimilarityOptions, estimate_similarity
from graph.merge_plan import MergePlan, plan_merges
from sfm.io.colmap_model import read_model
from sfm.errors import InputError
from sfm.core.geometry import Sim3, rotation_to_quaternion
from sfm.core.model import INVALID_POINT3D, Reconstruction

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MergeOptions:
    """Options of the ``merge`` stage.

    max_msd: cluster-graph edges whose normalised MSD exceeds this are not used (the paper's
        dotted edges).
    min_common_cameras: registered images two local models must share to be aligned.
    """

    max_msd: float = SimilarityOptions().max_msd
    min_common_cameras: int = 2


@dataclass(frozen=True)
class LocalModel:
    label: str  # "C<k>/<m>"
    model: Reconstruction


def load_local_models(workspace: Path) -> list[LocalModel]:
    """Every ``clusters/C<k>/<m>`` model of the workspace, in (k, m) order."""
    root = Path(workspace) / "clusters"
    if not root.is_dir():
        raise InputError(f"no local models in {root}: run cluster and map first")
    out = []
    for cdir in sorted((d for d in root.iterdir() if d.is_dir() and d.name[1:].isdigit()), key=lambda d: int(d.name[1:])):
        for mdir in sorted((d for d in cdir.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name)):
            out.append(LocalModel(f"{cdir.name}/{mdir.name}", read_model(mdir)))
    return out


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
    """Similarity (``v_from_u``) and MSD of every pair of local models that can be aligned."""
    edges = {}
    sim_opts = SimilarityOptions(min_common_cameras=options.min_common_cameras, max_msd=options.max_msd, seed=seed)
    for u in range(len(models)):
        for v in range(u + 1, len(models)):
            data = common_data(models[u].model, models[v].model)
            if data is None or len(data[0]) < options.min_common_cameras:
                continue
            names, Ra, ta, Rb, tb, pa, pb = data
            res = estimate_similarity(Ra, ta, Rb, tb, pa if len(pa) else None, pb if len(pb) else None, sim_opts)
            if res is None:
                continue
            edges[(u, v)] = {
                "sim": Sim3(res.scale, res.rotation, res.translation),
                "msd": float(res.msd), "inliers": int(res.num_inliers), "common_cameras": len(names),
                "common_points": int(res.num_points), "used": bool(res.msd <= options.max_msd),
            }
    return edges


def anchor_from_model(plan: MergePlan, edges: dict) -> dict[int, Sim3]:
    """``anchor_from_node`` similarity of every node, composed along its tree path."""
    out = {}
    for node, path in plan.path.items():
        sim = Sim3()
        for x, y in zip(path[:-1], path[1:]):
            step = edges[(x, y)]["sim"] if (x, y) in edges else edges[(y, x)]["sim"].inverse()
            sim = step.compose(sim)
        out[node] = sim
    return out


def merged_poses(models: list[LocalModel], plan: MergePlan, sims: dict[int, Sim3]):
    """Poses (by image name) in the anchor frame, nearest-to-anchor model first, and camera
    parameters (by camera id) from the model that registered most images of that camera."""
    poses, params, votes = {}, {}, {}
    for node in sorted(plan.clusters, key=lambda n: (len(plan.path[n]), n)):
        model = models[node].model
        for image in sorted(model.images.values(), key=lambda im: im.name):
            if image.name not in poses:
                poses[image.name] = sims[node].transform_pose(image.cam_from_world_rotation, image.cam_from_world_translation)
        for cam_id, cam in model.cameras.items():
            n = sum(1 for im in model.images.values() if im.camera_id == cam_id)
            if n > votes.get(cam_id, 0):
                votes[cam_id], params[cam_id] = n, cam.params.copy()
    return poses, params


def merge_json(models: list[LocalModel], edges: dict, plans: list[MergePlan]) -> dict:
    return {
        "nodes": [{"id": k, "label": m.label, "images": len(m.model.images), "points": len(m.model.points3D)} for k, m in enumerate(models)],
        "edges": [
            {"a": u, "b": v, "scale": e["sim"].scale, "rotation_qvec": rotation_to_quaternion(e["sim"].rotation).tolist(),
             "translation": e["sim"].translation.tolist(), "msd": e["msd"], "inliers": e["inliers"],
             "common_cameras": e["common_cameras"], "common_points": e["common_points"], "used": e["used"]}
            for (u, v), e in sorted(edges.items())
        ],
        "components": [
            {"anchor": p.anchor, "clusters": list(p.clusters), "minst": [list(e) for e in p.edges],
             "layers": {str(k): v for k, v in p.layer.items()}, "parent": {str(k): v for k, v in p.parent.items()},
             "path": {str(k): list(v) for k, v in p.path.items()}, "num_layers": p.num_layers}
            for p in plans
        ],
    }


def plan_components(models: list[LocalModel], edges: dict) -> list[MergePlan]:
    sizes = {k: len(m.model.images) for k, m in enumerate(models)}
    weights = {(u, v): e["msd"] for (u, v), e in edges.items() if e["used"]}
    return plan_merges(list(range(len(models))), sizes, weights)

