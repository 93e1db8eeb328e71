"""COLMAP camera models in numpy: parameter layouts, the Cal3DS2 equivalent and projection.

The camera model shared by bundle adjustment (:mod:`backend.bundle_adjustment`) and whoever
filters observations by reprojection error. Intrinsics are given per camera *group* (several
images share one camera) as COLMAP model names and parameter vectors: ``SIMPLE_PINHOLE
(f,cx,cy)``, ``PINHOLE (fx,fy,cx,cy)``, ``SIMPLE_RADIAL (f,cx,cy,k)``, ``RADIAL (f,cx,cy,k1,k2)``,
``OPENCV (fx,fy,cx,cy,k1,k2,p1,p2)``, with COLMAP's distortion on normalised coordinates
(u, v): r2 = u²+v², radial = k1 r2 + k2 r2², pixel = f u (1+radial) + cx (plus OpenCV's
tangential terms). Every model is exactly a GTSAM ``Cal3DS2`` vector
[fx, fy, s, u0, v0, k1, k2, p1, p2] (:func:`ds2_from_params`, :func:`params_from_ds2`).
The pixel convention is the caller's, as long as principal points and observations agree.

Poses are ``cam_from_world`` (x_cam = R X + t, OpenCV axes: x right, y down, z forward), given
per image as rotations (N,3,3) and translations (N,3); ``image_camera`` (N,) is each image's
group. Observations are three arrays: image index (M,), point index (M,) and pixel (M, 2).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Array = np.ndarray

#: COLMAP camera models supported here and their number of parameters.
MODEL_NUM_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}
#: The models with one focal length (fx = fy).
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def ds2_from_params(model: str, params: np.ndarray) -> np.ndarray:
    """Cal3DS2 vector [fx, fy, s, u0, v0, k1, k2, p1, p2] equivalent to COLMAP ``params``."""
    p = np.asarray(params, dtype=float)
    if len(p) != MODEL_NUM_PARAMS.get(model, -1):
        raise ValueError(f"camera model {model!r} with {len(p)} parameters is not supported")
    if model in SINGLE_FOCAL_MODELS:
        extra = list(p[3:]) + [0.0] * (2 - len(p[3:]))
        return np.array([p[0], p[0], 0.0, p[1], p[2], *extra, 0.0, 0.0])
    extra = list(p[4:]) + [0.0] * (4 - len(p[4:]))
    return np.array([p[0], p[1], 0.0, p[2], p[3], *extra])


def params_from_ds2(model: str, ds2: np.ndarray) -> np.ndarray:
    """Inverse of :func:`ds2_from_params` (single-focal models take the mean of fx and fy)."""
    if model in SINGLE_FOCAL_MODELS:
        return np.array(
            [0.5 * (ds2[0] + ds2[1]), ds2[3], ds2[4], *ds2[5 : 5 + MODEL_NUM_PARAMS[model] - 3]]
        )
    return np.array([ds2[0], ds2[1], ds2[3], ds2[4], *ds2[5 : 5 + MODEL_NUM_PARAMS[model] - 4]])


def project(
    camera_models: Sequence[str],
    camera_params: Sequence[Array],
    image_camera: Array,
    rotations: Array,
    translations: Array,
    points: Array,
    obs_image: Array,
    obs_point: Array,
) -> tuple[Array, Array]:
    """Pixels (M,2) and depths (M,) of the observed points, vectorised (COLMAP's models)."""
    ds2 = np.stack([ds2_from_params(m, p) for m, p in zip(camera_models, camera_params)])
    intr = ds2[np.asarray(image_camera)[obs_image]]
    x_cam = np.einsum("mij,mj->mi", rotations[obs_image], points[obs_point])
    x_cam += translations[obs_image]
    depth = x_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = x_cam[:, 0] / depth, x_cam[:, 1] / depth
    r2 = u * u + v * v
    radial = intr[:, 5] * r2 + intr[:, 6] * r2 * r2
    p1, p2 = intr[:, 7], intr[:, 8]
    ud = u * (1 + radial) + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    vd = v * (1 + radial) + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    xy = np.stack([intr[:, 0] * ud + intr[:, 2] * vd + intr[:, 3], intr[:, 1] * vd + intr[:, 4]], 1)
    return xy, depth


def reprojection_errors(
    camera_models: Sequence[str],
    camera_params: Sequence[Array],
    image_camera: Array,
    rotations: Array,
    translations: Array,
    points: Array,
    obs_image: Array,
    obs_point: Array,
    obs_xy: Array,
) -> Array:
    """Pixel distance (M,) between each observation and its projected point; inf behind camera.

    Same arrays as :func:`backend.bundle_adjustment.bundle_adjust` (without options): use it to
    filter observations.
    """
    cameras = (camera_models, camera_params, image_camera)
    xy, depth = project(*cameras, rotations, translations, points, obs_image, obs_point)
    return np.where(depth > 0, np.linalg.norm(xy - obs_xy, axis=1), np.inf)
