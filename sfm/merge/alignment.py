"""Moving every local model into its anchor's frame (paper section 3.2.3, Alg. 2, lines 6 and 10).

Alg. 2 merges each leaf into its neighbour, layer by layer, until the anchor holds every
cluster; applied to the models, each local model is mapped by the similarities composed along
its MinST path to the anchor (``MergePlan.path``: the merges it takes part in).  An
image registered in several models keeps the pose from the model nearest the anchor, and each
camera the parameters of the model that registered most of its images.
"""

from __future__ import annotations

from graph.merge_plan import MergePlan
from backend.sim3 import Sim3
from sfm.merge.cluster_graph import LocalModel


def anchor_from_model(plan: MergePlan, edges: dict) -> dict[int, Sim3]:
    """``anchor_from_node`` similarity of every node, composed along its tree path (Alg. 2's
    merges of a leaf into its neighbour, lines 6 and 10, from the node up to the anchor)."""
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
    parameters (by camera id) from the model that registered most images of that camera: the
    merged cluster ``C_final`` of Alg. 2 (section 3.2.3), before its refinement."""
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
