"""COLMAP camera models in numpy: parameter layouts, projection, unprojection, reprojection errors.

Parameters follow COLMAP's order for each model: ``SIMPLE_PINHOLE (f, cx, cy)``, ``PINHOLE (fx,
fy, cx, cy)``, ``SIMPLE_RADIAL (f, cx, cy, k)``, ``RADIAL (f, cx, cy, k1, k2)``, ``OPENCV (fx, fy,
cx, cy, k1, k2, p1, p2)``, with COLMAP's distortion on normalised coordinates (u, v):
r2 = u² + v², radial = k1 r2 + k2 r2², pixel = f (u + du) + c, plus OpenCV's tangential terms.
Every model is exactly a GTSAM ``Cal3DS2`` vector [fx, fy, s, u0, v0, k1, k2, p1, p2]
(:func:`ds2_from_params`, :func:`params_from_ds2`), which is how bundle adjustment holds it.

The pixel convention is the caller's, as long as principal points and observations agree
(graphsfm: pixel centres at integer coordinates).  Poses are ``cam_from_world`` (x_cam = R X + t,
OpenCV axes: x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

Array = np.ndarray
_ERROR_ROWS = 1_000_000  # reprojection errors computed this many rows at a time (72 bytes of rotation each)


@dataclass(frozen=True)
class CameraModelSpec:
    """A COLMAP camera model: its id, name, parameter names and where the focal lengths, the
    principal point and the distortion parameters are among them."""

    model_id: int
    name: str
    param_names: tuple[str, ...]
    focal_idx: tuple[int, ...]
    pp_idx: tuple[int, int]
    extra_idx: tuple[int, ...]

    @property
    def num_params(self) -> int:
        return len(self.param_names)


CAMERA_MODELS: dict[str, CameraModelSpec] = {
    spec.name: spec
    for spec in [
        CameraModelSpec(0, "SIMPLE_PINHOLE", ("f", "cx", "cy"), (0,), (1, 2), ()),
        CameraModelSpec(1, "PINHOLE", ("fx", "fy", "cx", "cy"), (0, 1), (2, 3), ()),
        CameraModelSpec(2, "SIMPLE_RADIAL", ("f", "cx", "cy", "k"), (0,), (1, 2), (3,)),
        CameraModelSpec(3, "RADIAL", ("f", "cx", "cy", "k1", "k2"), (0,), (1, 2), (3, 4)),
        CameraModelSpec(4, "OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"), (0, 1), (2, 3), (4, 5, 6, 7)),
    ]
}
CAMERA_MODEL_BY_ID: dict[int, CameraModelSpec] = {s.model_id: s for s in CAMERA_MODELS.values()}
#: The models with one focal length (fx = fy).
SINGLE_FOCAL_MODELS = tuple(name for name, spec in CAMERA_MODELS.items() if len(spec.focal_idx) == 1)


def model_spec(model: str | int) -> CameraModelSpec:
    """The spec of a model given by name or COLMAP id; a clear error for unsupported ones."""
    spec = CAMERA_MODEL_BY_ID.get(model) if isinstance(model, (int, np.integer)) else CAMERA_MODELS.get(model)
    if spec is None:
        raise ValueError(f"camera model {model!r} is not supported; supported: {', '.join(CAMERA_MODELS)}")
    return spec


def focal_lengths(model: str, params: Array) -> tuple[float, float]:
    spec = model_spec(model)
    return float(params[spec.focal_idx[0]]), float(params[spec.focal_idx[-1]])


def calibration_matrix(model: str, params: Array) -> Array:
    """Pinhole K, ignoring distortion."""
    spec = model_spec(model)
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def default_params(model: str, width: int, height: int, focal: float) -> Array:
    """Parameters with the given focal, principal point at the image centre (pixel centres at
    integers), no distortion."""
    spec = model_spec(model)
    params = np.zeros(spec.num_params)
    params[list(spec.focal_idx)] = focal
    params[spec.pp_idx[0]] = (width - 1) / 2.0
    params[spec.pp_idx[1]] = (height - 1) / 2.0
    return params


# The largest magnitude of a distortion parameter a lens has (COLMAP's mapper option
# max_extra_param): beyond it, a bundle adjustment has traded the parameter against the geometry.
MAX_EXTRA_PARAM = 1.0


def has_bogus_params(model: str, params: Array, width: int, height: int, min_focal_ratio: float = 0.1,
                     max_focal_ratio: float = 10.0, max_extra_param: float = MAX_EXTRA_PARAM) -> bool:
    """COLMAP's test for intrinsics a bundle adjustment has driven somewhere no lens is (its
    mapper's defaults): a focal length outside [0.1, 10] x the longer image side, a principal
    point outside the image, a distortion parameter above 1 in magnitude, or anything not
    finite."""
    spec = model_spec(model)
    params = np.asarray(params, dtype=np.float64)
    if not np.all(np.isfinite(params)):
        return True
    size = float(max(width, height))
    ratios = params[list(spec.focal_idx)] / size
    cx, cy = params[list(spec.pp_idx)]
    return bool(
        np.any(ratios < min_focal_ratio) or np.any(ratios > max_focal_ratio)
        or not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5)
        or np.any(np.abs(params[list(spec.extra_idx)]) > max_extra_param)
    )  # fmt: skip


def _distortion(spec: CameraModelSpec, params: Array, u: Array, v: Array):
    """COLMAP's distortion offsets (du, dv) at normalised coordinates (u, v)."""
    if not spec.extra_idx:
        return np.zeros_like(u), np.zeros_like(v)
    r2 = u * u + v * v
    extra = params[list(spec.extra_idx)]
    if spec.name == "SIMPLE_RADIAL":
        radial = extra[0] * r2
        return u * radial, v * radial
    if spec.name == "RADIAL":
        radial = extra[0] * r2 + extra[1] * r2 * r2
        return u * radial, v * radial
    k1, k2, p1, p2 = extra
    radial = k1 * r2 + k2 * r2 * r2
    uv = u * v
    du = u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u * u)
    dv = v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v * v)
    return du, dv


def project(model: str, params: Array, points_cam: Array) -> Array:
    """Pixels (N, 2) of camera-frame points (N, 3).  Points with z <= 0 give NaN; points so
    close to the image plane that the distortion overflows give inf (no warning: callers treat
    non-finite pixels as unusable)."""
    spec = model_spec(model)
    params = np.asarray(params, dtype=np.float64)
    pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = pts[:, 2]
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u = np.where(z > 0, pts[:, 0] / z, np.nan)
        v = np.where(z > 0, pts[:, 1] / z, np.nan)
        du, dv = _distortion(spec, params, u, v)
        return np.stack([fx * (u + du) + cx, fy * (v + dv) + cy], axis=1)


def unproject(model: str, params: Array, pixels: Array, iterations: int = 20) -> Array:
    """Normalised image coordinates (N, 2) of pixels (N, 2): removes the distortion by fixed-point
    iteration (converges for the mild distortion SfM cameras have; stops early once an
    iteration changes nothing, which more iterations would not either).  A pixel the iteration
    cannot undistort (beyond where the distortion is invertible, as with intrinsics a young
    model's BA has not settled) comes out NaN."""
    spec = model_spec(model)
    params = np.asarray(params, dtype=np.float64)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    ud = (px[:, 0] - cx) / fx
    vd = (px[:, 1] - cy) / fy
    u, v = ud.copy(), vd.copy()
    if spec.extra_idx:
        with np.errstate(over="ignore", invalid="ignore"):  # diverging rows end as inf/NaN: reported NaN
            for _ in range(iterations):
                du, dv = _distortion(spec, params, u, v)
                u_next, v_next = ud - du, vd - dv
                if np.array_equal(u_next, u) and np.array_equal(v_next, v):
                    break
                u, v = u_next, v_next
    out = np.stack([u, v], axis=1)
    out[~np.all(np.isfinite(out), axis=1)] = np.nan
    return out


def ds2_from_params(model: str, params: Array) -> Array:
    """Cal3DS2 vector [fx, fy, s, u0, v0, k1, k2, p1, p2] equivalent to COLMAP ``params``."""
    spec = model_spec(model)
    p = np.asarray(params, dtype=float)
    if len(p) != spec.num_params:
        raise ValueError(f"camera model {model!r} takes {spec.num_params} parameters, got {len(p)}")
    if model in SINGLE_FOCAL_MODELS:
        extra = list(p[3:]) + [0.0] * (2 - len(p[3:]))
        return np.array([p[0], p[0], 0.0, p[1], p[2], *extra, 0.0, 0.0])
    extra = list(p[4:]) + [0.0] * (4 - len(p[4:]))
    return np.array([p[0], p[1], 0.0, p[2], p[3], *extra])


def params_from_ds2(model: str, ds2: Array) -> Array:
    """Inverse of :func:`ds2_from_params` (single-focal models take the mean of fx and fy)."""
    num_params = model_spec(model).num_params
    if model in SINGLE_FOCAL_MODELS:
        return np.array([0.5 * (ds2[0] + ds2[1]), ds2[3], ds2[4], *ds2[5 : 5 + num_params - 3]])
    return np.array([ds2[0], ds2[1], ds2[3], ds2[4], *ds2[5 : 5 + num_params - 4]])


def reprojection_errors(camera_models: Sequence[str], camera_params: Sequence[Array], image_camera: Array,
                        rotations: Array, translations: Array, obs_image: Array, obs_xyz: Array,
                        obs_xy: Array) -> Array:
    """Pixel distance (M,) between each observation and its point: observation m sees the point
    ``obs_xyz[m]`` in image ``obs_image[m]`` (camera group ``image_camera[obs_image[m]]``) at
    pixel ``obs_xy[m]``; inf behind the camera or where the projection is not finite."""
    obs_image = np.asarray(obs_image, dtype=np.int64)
    if len(obs_image) > _ERROR_ROWS:
        return np.concatenate([
            reprojection_errors(camera_models, camera_params, image_camera, rotations, translations,
                                obs_image[a : a + _ERROR_ROWS], obs_xyz[a : a + _ERROR_ROWS], obs_xy[a : a + _ERROR_ROWS])
            for a in range(0, len(obs_image), _ERROR_ROWS)])
    x_cam = np.einsum("nij,nj->ni", rotations[obs_image], obs_xyz) + translations[obs_image]
    err = np.full(len(obs_image), np.inf)
    cams = np.asarray(image_camera)[obs_image]
    for c in np.unique(cams):
        sel = np.flatnonzero(cams == c)
        px = project(camera_models[c], camera_params[c], x_cam[sel])
        err[sel] = np.linalg.norm(px - obs_xy[sel], axis=1)
    err[~np.isfinite(err) | (x_cam[:, 2] <= 0)] = np.inf
    return err
