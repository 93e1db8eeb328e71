"""Rotations and camera poses: quaternions, angles, projection onto SO(3), look-at poses.

The one implementation of each, for ``sfm`` and ``backend`` alike.  Conventions:

* A pose ``cam_from_world`` maps world points into the camera frame, ``x_cam = R @ X + t``,
  exactly as COLMAP's ``images.txt`` stores it.  The camera centre is ``C = -R.T @ t``.
* Quaternions are ``(w, x, y, z)`` (COLMAP order), unit norm, ``w >= 0`` after normalisation.
"""

from __future__ import annotations

import numpy as np


def quaternion_to_rotation(qvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (normalised here)."""
    q = np.asarray(qvec, dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix.

    Uses the symmetric 4x4 eigen-decomposition (Bar-Itzhack), which is stable for every angle
    and tolerates slightly non-orthonormal input.
    """
    r = np.asarray(rotation, dtype=np.float64)
    k = np.array(
        [
            [r[0, 0] - r[1, 1] - r[2, 2], r[1, 0] + r[0, 1], r[2, 0] + r[0, 2], r[2, 1] - r[1, 2]],
            [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], r[2, 1] + r[1, 2], r[0, 2] - r[2, 0]],
            [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], r[1, 0] - r[0, 1]],
            [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
        ]
    ) / 3.0
    _, vecs = np.linalg.eigh(k)
    x, y, z, w = vecs[:, -1]
    q = np.array([w, x, y, z])
    if q[0] < 0:
        q = -q
    return q / np.linalg.norm(q)


def rotation_angle_deg(rot_a: np.ndarray, rot_b: np.ndarray | None = None) -> np.ndarray | float:
    """Angle in degrees of ``Q = R_a @ R_b.T`` (of ``R_a`` when ``R_b`` is None), for one
    rotation or stacks (..., 3, 3); a float for one rotation.

    ``atan2(|Q - Q^T|_F / (2 sqrt 2), (trace Q - 1) / 2)``, i.e. ``atan2(sin, cos)``: accurate at
    every angle, unlike ``arccos`` of the trace (1e-6 degrees of noise near 0).
    """
    q = np.asarray(rot_a, dtype=np.float64)
    if rot_b is not None:
        q = q @ np.swapaxes(np.asarray(rot_b, dtype=np.float64), -1, -2)
    skew = q - np.swapaxes(q, -1, -2)
    sin = np.sqrt(np.sum(skew * skew, axis=(-2, -1))) / (2.0 * np.sqrt(2.0))
    cos = (np.trace(q, axis1=-2, axis2=-1) - 1.0) / 2.0
    angle = np.degrees(np.arctan2(sin, cos))
    return float(angle) if np.ndim(angle) == 0 else angle


def project_to_so3(m: np.ndarray) -> np.ndarray:
    """The rotation nearest to a 3x3 matrix in the Frobenius norm (SVD, reflection corrected):
    the chordal L2 mean of rotations is the projection of their sum."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def angle_between_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle in degrees between vectors along the last axis (NaN-free; 0-length gives 90)."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    nu = np.linalg.norm(u, axis=-1)
    nv = np.linalg.norm(v, axis=-1)
    denom = nu * nv
    cos = np.divide(np.sum(u * v, axis=-1), denom, out=np.zeros_like(denom), where=denom > 0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def rotation_about_axis(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation matrix of ``angle_deg`` about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    theta = np.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)


def rotation_from_rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle in radians)."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:  # first order: the axis is undefined
        return np.eye(3) + np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    return rotation_about_axis(w, np.degrees(theta))


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` (R, t) of a camera at ``center`` looking at ``target`` (OpenCV axes:
    x right, y down, z forward); ``up`` is the world direction that appears upwards."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))  # right = forward x up
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rotation = np.stack([x, y, z])
    return rotation, -rotation @ np.asarray(center, float)
