"""COLMAP camera models: parameter layouts, projection and unprojection (vectorised).

Parameters follow COLMAP's order for each model.  Inside graphsfm the principal point uses
OpenCV's pixel convention (pixel centres at integer coordinates); COLMAP files and databases put
the image corner at (0, 0), so ``cx, cy`` (like keypoints) are shifted by +0.5 when written and
-0.5 when read: :func:`params_to_colmap` / :func:`params_from_colmap` do that, in one place.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraModelSpec:
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
        CameraModelSpec(
            4,
            "OPENCV",
            ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
            (0, 1),
            (2, 3),
            (4, 5, 6, 7),
        ),
    ]
}
CAMERA_MODEL_BY_ID: dict[int, CameraModelSpec] = {s.model_id: s for s in CAMERA_MODELS.values()}


def model_spec(model: str | int) -> CameraModelSpec:
    """The spec of a model given by name or COLMAP id; a clear error for unsupported ones."""
    spec = CAMERA_MODEL_BY_ID.get(model) if isinstance(model, (int, np.integer)) else CAMERA_MODELS.get(model)
    if spec is None:
        raise ValueError(f"unsupported camera model {model!r}; supported: {', '.join(CAMERA_MODELS)}")
    return spec


def focal_lengths(model: str, params: np.ndarray) -> tuple[float, float]:
    spec = model_spec(model)
    fx = params[spec.focal_idx[0]]
    fy = params[spec.focal_idx[-1]]
    return float(fx), float(fy)


def has_bogus_params(model: str, params: np.ndarray, width: int, height: int, min_focal_ratio: float = 0.1,
                     max_focal_ratio: float = 10.0, max_extra_param: float = 1.0) -> bool:
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


def calibration_matrix(model: str, params: np.ndarray) -> np.ndarray:
    """Pinhole K (OpenCV convention) ignoring distortion."""
    spec = model_spec(model)
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _distortion(spec: CameraModelSpec, params: np.ndarray, u: np.ndarray, v: np.ndarray):
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


def project(model: str, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3).  Points with z <= 0 give NaN."""
    spec = model_spec(model)
    params = np.asarray(params, dtype=np.float64)
    pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(z > 0, pts[:, 0] / z, np.nan)
        v = np.where(z > 0, pts[:, 1] / z, np.nan)
    du, dv = _distortion(spec, params, u, v)
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    return np.stack([fx * (u + du) + cx, fy * (v + dv) + cy], axis=1)


def unproject(model: str, params: np.ndarray, pixels: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalised image coordinates (N, 2) of pixels (N, 2): removes the distortion by fixed-point
    iteration (converges for the mild distortion SfM cameras have; stops early once an
    iteration changes nothing, which more iterations would not either)."""
    spec = model_spec(model)
    params = np.asarray(params, dtype=np.float64)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    fx, fy = focal_lengths(model, params)
    cx, cy = params[spec.pp_idx[0]], params[spec.pp_idx[1]]
    ud = (px[:, 0] - cx) / fx
    vd = (px[:, 1] - cy) / fy
    u, v = ud.copy(), vd.copy()
    if spec.extra_idx:
        for _ in range(iterations):
            du, dv = _distortion(spec, params, u, v)
            u_next, v_next = ud - du, vd - dv
            if np.array_equal(u_next, u) and np.array_equal(v_next, v):
                break
            u, v = u_next, v_next
    return np.stack([u, v], axis=1)


def params_to_colmap(model: str, params: np.ndarray) -> np.ndarray:
    """Internal (OpenCV pixel centres) -> COLMAP (corner at 0,0): principal point + 0.5."""
    out = np.array(params, dtype=np.float64, copy=True)
    out[list(model_spec(model).pp_idx)] += 0.5
    return out


def params_from_colmap(model: str, params: np.ndarray) -> np.ndarray:
    """COLMAP (corner at 0,0) -> internal (OpenCV pixel centres): principal point - 0.5."""
    out = np.array(params, dtype=np.float64, copy=True)
    out[list(model_spec(model).pp_idx)] -= 0.5
    return out


def default_params(model: str, width: int, height: int, focal: float) -> np.ndarray:
    """Parameters with the given focal, principal point at the image centre, no distortion."""
    spec = model_spec(model)
    params = np.zeros(spec.num_params)
    params[list(spec.focal_idx)] = focal
    params[spec.pp_idx[0]] = (width - 1) / 2.0
    params[spec.pp_idx[1]] = (height - 1) / 2.0
    return params
