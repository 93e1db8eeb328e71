"""nerfstudio's ``transforms.json``: cameras and a coloured point cloud to train a NeRF or splats on.

The convention is the one nerfstudio's own COLMAP conversion (``colmap_to_json``) writes:

- ``frames[k].transform_matrix``: camera-to-world 4 x 4 with OpenGL camera axes (x right, y up,
  z backwards: COLMAP's / OpenCV's y and z negated), in nerfstudio's world, which is the
  model's world with its y and z axes swapped and the new z negated; that change of world is
  recorded as ``applied_transform`` (3 x 4), and the point cloud is written in the same world.
- Intrinsics ``fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2`` with ``camera_model`` ``OPENCV`` (every
  COLMAP model here is an OPENCV camera with some coefficients zero), principal point in
  COLMAP's pixel convention (image corner at 0, 0), as nerfstudio reads it; at the top level
  when the images share one camera, else in every frame.
- ``file_path``: the image, relative to the folder of ``transforms.json``; ``colmap_im_id``.
- ``ply_file_path``: the PLY (``sfm.io.colmap_model.write_ply_arrays``: colours and normals),
  relative to the same folder.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from backend.camera_models import focal_lengths, model_spec
from sfm.core.model import Camera, Reconstruction
from sfm.io.colmap_model import ply_arrays, write_ply_arrays
from sfm.io.pixel_convention import COLMAP_OFFSET

#: nerfstudio's world from the model's world (rows: x, z, -y), as ``applied_transform``.
APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
PLY_NAME = "sparse_pc.ply"


def opencv_intrinsics(camera: Camera) -> dict:
    """A camera as nerfstudio's OPENCV intrinsics (COLMAP's pixel convention)."""
    spec = model_spec(camera.model)
    params = np.asarray(camera.params, np.float64)
    fx, fy = focal_lengths(camera.model, params)
    extra = list(params[list(spec.extra_idx)]) + [0.0] * (4 - len(spec.extra_idx))
    if camera.model in ("SIMPLE_RADIAL", "RADIAL"):
        extra = extra[:2] + [0.0, 0.0]  # radial terms only
    return {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy,
            "cx": float(params[spec.pp_idx[0]]) + COLMAP_OFFSET, "cy": float(params[spec.pp_idx[1]]) + COLMAP_OFFSET,
            "w": int(camera.width), "h": int(camera.height),
            "k1": float(extra[0]), "k2": float(extra[1]), "p1": float(extra[2]), "p2": float(extra[3])}


def transform_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """nerfstudio's ``transform_matrix`` of a ``cam_from_world`` pose (module docstring)."""
    c2w = np.eye(4)
    c2w[:3, :3] = APPLIED_TRANSFORM[:, :3] @ rotation.T @ _OPENGL_FROM_OPENCV
    c2w[:3, 3] = APPLIED_TRANSFORM[:, :3] @ (-rotation.T @ translation)
    return c2w


def pose_from_transform_matrix(c2w: np.ndarray, applied_transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`transform_matrix`: the ``cam_from_world`` (R, t) in the model's world."""
    c2w, applied = np.asarray(c2w, np.float64), np.asarray(applied_transform, np.float64)
    model_from_ns = applied[:, :3].T  # a rotation: its inverse is its transpose
    world_from_cam = model_from_ns @ c2w[:3, :3] @ _OPENGL_FROM_OPENCV
    center = model_from_ns @ (c2w[:3, 3] - applied[:, 3])
    rotation = world_from_cam.T
    return rotation, -rotation @ center


def write_nerfstudio(recon: Reconstruction, path: Path, image_dir: Path | None = None) -> dict:
    """``transforms.json`` at ``path`` and the PLY beside it (module docstring); images named
    relative to ``path``'s folder: in ``image_dir`` when given, else in its ``images/``."""
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    registered = [recon.images[i] for i in recon.registered_image_ids]
    cameras = sorted({im.camera_id for im in registered})
    shared = len(cameras) == 1
    out: dict = opencv_intrinsics(recon.cameras[cameras[0]]) if shared else {"camera_model": "OPENCV"}
    frames = []
    for image in registered:
        source = (Path(image_dir) / image.name) if image_dir is not None else folder / "images" / image.name
        frame = {"file_path": Path(os.path.relpath(source.absolute(), folder.absolute())).as_posix(),
                 "transform_matrix": transform_matrix(image.cam_from_world_rotation,
                                                      image.cam_from_world_translation).tolist(),
                 "colmap_im_id": image.image_id}
        if not shared:
            frame.update({k: v for k, v in opencv_intrinsics(recon.cameras[image.camera_id]).items()
                          if k != "camera_model"})
        frames.append(frame)
    out["frames"] = frames
    out["applied_transform"] = APPLIED_TRANSFORM.tolist()
    xyz, rgb, normals = ply_arrays(recon)
    rotation, shift = APPLIED_TRANSFORM[:, :3], APPLIED_TRANSFORM[:, 3]
    ply_name = PLY_NAME if path.name == "transforms.json" else f"{path.stem}.ply"
    write_ply_arrays(folder / ply_name, xyz @ rotation.T + shift, rgb, normals @ rotation.T)
    out["ply_file_path"] = ply_name
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(out, indent=4) + "\n")
    tmp.replace(path)
    return {"frames": len(frames), "cameras": len(cameras), "ply": str(folder / ply_name)}


def read_nerfstudio(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, dict]]:
    """``transforms.json`` read back: file path -> (rotation, translation) ``cam_from_world``
    in the model's world, and the frame's intrinsics."""
    data = json.loads(Path(path).read_text())
    applied = np.asarray(data.get("applied_transform", np.eye(4)[:3]), np.float64)
    keys = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2")
    shared = {k: data[k] for k in keys if k in data}
    out = {}
    for frame in data["frames"]:
        rotation, translation = pose_from_transform_matrix(np.asarray(frame["transform_matrix"]), applied)
        out[frame["file_path"]] = (rotation, translation, {**shared, **{k: frame[k] for k in keys if k in frame}})
    return out
