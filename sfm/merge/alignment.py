"""Moving every local model into its anchor's frame (paper section 3.2.3, Alg. 2, lines 6 and 10).

Alg. 2 merges each leaf into its neighbour, layer by layer, until the anchor holds every
cluster; applied to the models, each local model is mapped by the similarities composed along
its MinST path to the anchor (``MergePlan.path``: the merges it takes part in).  An
image registered in several models keeps the pose from the model nearest the anchor.  A camera
(its intrinsics do not depend on a model's frame) takes the mean of the parameters every local
model estimated for it, each weighted by the observations that model has in that camera's
images: independent self-calibrations of parts of the scene pooled as the final bundle
adjustment would weigh them, so the merged model does not start from the calibration error of
one cluster (which a final BA split into track parts, ``ba_max_observations``, would keep).
The principal point and the distortion are each pooled only over the models that refined them
(their values are off the camera's nominal ones, ``sfm.mapper.principal_point``,
``sfm.mapper.distortion``): a model that held them has no estimate of them to contribute, and
averaging its nominal values in would pull the others' estimates back part of the way.
"""

from __future__ import annotations

import numpy as np

from graph.merge_plan import MergePlan
from backend.camera_models import model_spec
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


def merged_poses(models: list[LocalModel], plan: MergePlan, sims: dict[int, Sim3],
                 nominal: dict[int, np.ndarray] | None = None):
    """Poses (by image name) in the anchor frame, nearest-to-anchor model first, and camera
    parameters (by camera id) pooled over the models (module docstring): the merged cluster
    ``C_final`` of Alg. 2 (section 3.2.3), before its refinement.  ``nominal``: each camera's
    parameters before any model refined them (the database's), which tell the models that
    refined its principal point or distortion from those that held them; None: pooled over
    every model."""
    poses = {}
    estimates: dict[int, list[tuple[int, np.ndarray]]] = {}  # camera id -> (observations, params) per model
    camera_model: dict[int, str] = {}
    for node in sorted(plan.clusters, key=lambda n: (len(plan.path[n]), n)):
        model = models[node].model
        for image in sorted(model.images.values(), key=lambda im: im.name):
            if image.name not in poses:
                poses[image.name] = sims[node].transform_pose(image.cam_from_world_rotation, image.cam_from_world_translation)
        observations: dict[int, int] = {}
        for image in model.images.values():
            observations[image.camera_id] = observations.get(image.camera_id, 0) + image.num_points3D
        for cam_id, cam in model.cameras.items():
            estimates.setdefault(cam_id, []).append((observations.get(cam_id, 0), np.asarray(cam.params, np.float64)))
            camera_model[cam_id] = cam.model
    params = {}
    for cam_id, found in sorted(estimates.items()):
        w = np.array([n for n, _ in found], dtype=np.float64)
        if w.sum() == 0:  # no model observes it: the parameters of the one nearest the anchor
            w[0] = 1.0
        values = np.stack([p for _, p in found])
        params[cam_id] = (w[:, None] * values).sum(axis=0) / w.sum()
        if nominal is None or cam_id not in nominal:
            continue
        spec = model_spec(camera_model[cam_id])
        for part in (list(spec.pp_idx), list(spec.extra_idx)):
            if not part:
                continue
            refined = np.any(values[:, part] != np.asarray(nominal[cam_id], np.float64)[part], axis=1) & (w > 0)
            if refined.any():
                params[cam_id][part] = (w[refined, None] * values[refined][:, part]).sum(axis=0) / w[refined].sum()
    return poses, params


def merged_points(models: list[LocalModel], plan: MergePlan, sims: dict[int, Sim3]):
    """The local models' own points in the anchor frame, nearest-to-anchor model first (Alg. 2's
    merged cluster ``C_final`` holds them with the cameras; the order breaks ties between points
    of a track seen by as many rows in two models): ``(names, keypoints, point_of_row,
    xyz)``, one row per observation (image name, keypoint index, point number), the points
    numbered in that order (``MapperState.seed_points``)."""
    names: list[str] = []
    keypoints, owners, coordinates = [], [], []
    count = 0
    for node in sorted(plan.clusters, key=lambda n: (len(plan.path[n]), n)):
        model = models[node].model
        name_of = {image_id: image.name for image_id, image in model.images.items()}
        points = list(model.points3D.values())
        if not points:
            continue
        xyz = sims[node].apply(np.array([p.xyz for p in points], dtype=np.float64))
        for k, point in enumerate(points):
            for image_id, kp in point.track:
                names.append(name_of[image_id])
                keypoints.append(kp)
                owners.append(count + k)
        coordinates.append(xyz)
        count += len(points)
    xyz = np.concatenate(coordinates) if coordinates else np.zeros((0, 3))
    return names, np.asarray(keypoints, np.int64), np.asarray(owners, np.int64), xyz


def align_components(models: list[LocalModel], plans: list[MergePlan], edges: dict, nominal: dict | None):
    """Every merge plan's models in its anchor's frame (Alg. 2): ``(plan, poses, camera
    parameters, points)`` per plan (:func:`merged_poses`, :func:`merged_points`), and each
    plan's ``anchor_from_model`` similarities."""
    components, all_sims = [], []
    for plan in plans:
        sims = anchor_from_model(plan, edges)
        all_sims.append(sims)
        poses, params = merged_poses(models, plan, sims, nominal)
        components.append((plan, poses, params, merged_points(models, plan, sims)))
    return components, all_sims
