"""Reader for BAL ("Bundle Adjustment in the Large", Agarwal et al. 2010) problem files.

The format: a header ``ncams npoints nobs``; ``nobs`` lines ``cam point x y``; then 9 numbers per
camera (Rodrigues rotation vector, translation, f, k1, k2) and 3 per point. Whitespace, line
breaks included, is not significant. BAL's camera model (Bundler's):

    P = R X + t,   p = -P[:2] / P[2],   (x, y) = f (1 + k1 |p|² + k2 |p|⁴) p,

with (x, y) relative to the image centre, x right, **y up**, and the camera looking down -z.

Converted here to graphsfm's conventions: OpenCV camera axes (x right, y down, z forward) are
x_cv = D P with D = diag(1, -1, -1), so cam_from_world is (D R, D t); then u = x_cv/z_cv = p_x and
v = y_cv/z_cv = -p_y, so the pixel, relative to the centre and with y down, is (x, -y). Each
camera becomes its own group with COLMAP model ``RADIAL`` (f, cx=0, cy=0, k1, k2), whose
distortion (k1 r2 + k2 r2² on normalised coordinates) is BAL's exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from backend.ba_problem import BAProblem

_FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def read_bal(path: str | Path) -> BAProblem:
    """Read a BAL file (see the module docstring for the conversion to OpenCV conventions)."""
    tokens = Path(path).read_text().split()
    num_cams, num_points, num_obs = (int(tok) for tok in tokens[:3])
    expected = 3 + 4 * num_obs + 9 * num_cams + 3 * num_points
    if len(tokens) != expected:
        raise ValueError(
            f"{path}: {len(tokens)} numbers, expected {expected} for the header "
            f"{num_cams} {num_points} {num_obs}"
        )
    values = np.asarray(tokens[3:], dtype=float)
    obs = values[: 4 * num_obs].reshape(num_obs, 4)
    cams = values[4 * num_obs : 4 * num_obs + 9 * num_cams].reshape(num_cams, 9)
    points = values[4 * num_obs + 9 * num_cams :].reshape(num_points, 3)
    obs_image, obs_point = obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64)
    if obs_image.max(initial=0) >= num_cams or obs_point.max(initial=0) >= num_points:
        raise ValueError(f"{path}: an observation refers to a missing camera or point")
    rotations = _FLIP_YZ @ Rotation.from_rotvec(cams[:, :3]).as_matrix()
    translations = cams[:, 3:6] @ _FLIP_YZ
    zeros = np.zeros(num_cams)
    camera_params = np.stack([cams[:, 6], zeros, zeros, cams[:, 7], cams[:, 8]], axis=1)
    return BAProblem(
        camera_models=("RADIAL",) * num_cams,
        camera_params=camera_params,
        image_camera=np.arange(num_cams),
        rotations=rotations,
        translations=translations,
        points=points,
        obs_image=obs_image,
        obs_point=obs_point,
        obs_xy=obs[:, 2:] * np.array([1.0, -1.0]),
    )
