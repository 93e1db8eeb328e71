"""Rerun views of 3D models: cameras as frustums with their images, points in their colours,
and the final model (``world/``) with its reprojection errors as a second colouring."""

from __future__ import annotations

import numpy as np

from backend.geometry import rotation_to_quaternion
from sfm.viz.frontend import even_sample
from sfm.viz.palette import ramp
from sfm.viz.recorder import Recorder, entity_part
from sfm.viz.tour import final_text


def frustum_depth(points: np.ndarray, centers: np.ndarray) -> float:
    """How deep to draw the frustums: a twentieth of the median distance from the cameras to
    the points' median (models have no scale of their own), 1 without points."""
    if len(points) == 0 or len(centers) == 0:
        return 1.0
    middle = np.median(np.asarray(points, dtype=np.float64), axis=0)
    depth = 0.05 * float(np.median(np.linalg.norm(np.asarray(centers, dtype=np.float64) - middle, axis=1)))
    return depth if np.isfinite(depth) and depth > 0 else 1.0


def world_centres(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Camera centres ``-R.T t`` of ``cam_from_world`` poses (N, 3, 3), (N, 3)."""
    return -np.einsum("nji,nj->ni", rotations, translations)


def world_quaternions(rotations: np.ndarray) -> np.ndarray:
    """``world_from_cam`` rotations of ``cam_from_world`` ones as Rerun's ``(x, y, z, w)``."""
    q = np.array([rotation_to_quaternion(R.T) for R in np.asarray(rotations, dtype=np.float64)]).reshape(-1, 4)
    return q[:, [1, 2, 3, 0]]


def log_pose(recorder: Recorder, entity: str, rotation: np.ndarray, translation: np.ndarray) -> None:
    """``entity``: the camera's pose given ``cam_from_world`` (logged as ``world_from_cam``)."""
    import rerun as rr

    rotation = np.asarray(rotation, dtype=np.float64)[None]
    translation = np.asarray(translation, dtype=np.float64)[None]
    recorder.log(entity, rr.Transform3D(translation=world_centres(rotation, translation)[0],
                                        quaternion=world_quaternions(rotation)[0]))


def log_frustum(recorder: Recorder, entity: str, name: str, K: np.ndarray, width: int, height: int,
                depth: float, with_image: bool = True) -> None:
    """``<entity>/image``: the camera's pinhole (OpenCV axes: x right, y down, z forward) drawn
    ``depth`` deep, with the image's thumbnail in it when there is one."""
    import rerun as rr

    thumb = recorder.thumbnail(name) if with_image else None
    K = np.asarray(K, dtype=np.float64)
    if thumb is not None:  # the pinhole of the thumbnail's pixels: the image fills the frustum
        s = np.array([thumb.scale_x, thumb.scale_y])
        K = K.copy()
        K[0, 0], K[1, 1] = K[0, 0] * s[0], K[1, 1] * s[1]
        K[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5
        width, height = thumb.width, thumb.height
    recorder.log(f"{entity}/image", rr.Pinhole(image_from_camera=K, resolution=[width, height],
                                                image_plane_distance=depth))
    if thumb is not None:
        recorder.log(f"{entity}/image", rr.EncodedImage(contents=thumb.jpeg, media_type="image/jpeg"))


def log_model(recorder: Recorder, prefix: str, recon, max_points: int = 0, color=None,
              with_images: bool = True) -> None:
    """``<prefix>/points`` (in their colours, or all in ``color``; ``max_points > 0``: an even
    sample) and ``<prefix>/cams/<name>`` (pose, frustum, image) of a
    :class:`sfm.core.model.Reconstruction`."""
    if not recorder.enabled:
        return
    import rerun as rr

    ids = sorted(recon.points3D)
    if max_points > 0:
        ids = [ids[k] for k in even_sample(len(ids), max_points)]
    xyz = np.array([recon.points3D[i].xyz for i in ids]).reshape(-1, 3)
    rgb = np.array([recon.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    recorder.log(f"{prefix}/points", rr.Points3D(xyz, colors=rgb if color is None else color))
    centers = np.array([im.center for im in recon.images.values()]).reshape(-1, 3)
    depth = frustum_depth(xyz, centers)
    for image in sorted(recon.images.values(), key=lambda im: im.name):
        cam = recon.cameras[image.camera_id]
        entity = f"{prefix}/cams/{entity_part(image.name)}"
        log_pose(recorder, entity, image.cam_from_world_rotation, image.cam_from_world_translation)
        log_frustum(recorder, entity, image.name, cam.K, cam.width, cam.height, depth, with_images)


def log_final_models(recorder: Recorder, models: list, num_images: int, mapper_options) -> None:
    """Stage final: the largest model at ``world/`` (``points`` in colour, ``points_error``
    coloured by each point's mean reprojection error, blue 0 px to red at the mapper's
    ``max_reproj_error``, ``cams/<name>`` with images), any other at ``world_models/<k>/``; and
    the stage's text of the tour."""
    if not recorder.enabled:
        return
    import rerun as rr

    recorder.stage("final")
    max_error = float(mapper_options.max_reproj_error)
    errors = np.zeros(0)
    for k, model in enumerate(models):
        prefix = "world" if k == 0 else f"world_models/{k}"
        log_model(recorder, prefix, model)
        ids = sorted(model.points3D)
        err = np.array([model.points3D[i].error for i in ids], dtype=np.float64)
        xyz = np.array([model.points3D[i].xyz for i in ids]).reshape(-1, 3)
        recorder.log(f"{prefix}/points_error", rr.Points3D(xyz, colors=ramp(err, 0.0, max_error)))
        if k == 0:
            errors = err
        recorder.views["world"].append(prefix)
    summaries = [m.summary() for m in models]
    recorder.tour("final", final_text(summaries, num_images, errors, max_error))
