"""Small rigid-geometry helpers shared by the application layer.

Conventions (see DESIGN.md):

* A pose ``cam_from_world`` maps world points into the camera frame, ``x_cam = R @ X + t``,
  exactly as COLMAP's ``images.txt`` stores it.  The camera centre is ``C = -R.T @ t``.
* Quaternions are ``(w, x, y, z)`` (COLMAP order), unit norm, ``w >= 0`` after normalisation.
* A similarity ``Sim3`` named ``b_from_a`` maps points of frame ``a`` into frame ``b``:
  ``X_b = s * R @ X_a + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle in degrees of a rotation matrix (0 for identity), robust near 0 and 180."""
    cos = (np.trace(rotation) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def rotation_angles_deg(rotations_a: np.ndarray, rotations_b: np.ndarray) -> np.ndarray:
    """Angles in degrees of ``R_a @ R_b.T`` for stacks of rotations of shape (N, 3, 3)."""
    traces = np.einsum("nij,nij->n", rotations_a, rotations_b)
    return np.degrees(np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0)))


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


@dataclass(frozen=True)
class Sim3:
    """Similarity ``b_from_a``: ``X_b = scale * rotation @ X_a + translation``."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points of shape (N, 3) or (3,)."""
        return self.scale * (np.asarray(points) @ self.rotation.T) + self.translation

    def inverse(self) -> Sim3:
        r_inv = self.rotation.T
        return Sim3(1.0 / self.scale, r_inv, -(r_inv @ self.translation) / self.scale)

    def compose(self, other: Sim3) -> Sim3:
        """``self ∘ other``: apply ``other`` first (``c_from_a = c_from_b.compose(b_from_a)``)."""
        return Sim3(
            self.scale * other.scale,
            self.rotation @ other.rotation,
            self.scale * (self.rotation @ other.translation) + self.translation,
        )

    def transform_pose(self, rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """New ``cam_from_world`` after the world is mapped by this similarity.

        With ``X_new = s R_s X + t_s``: ``R' = R R_s^T`` and ``t' = s t - R' t_s`` so that the
        camera sees the same points (scaled by ``s``).
        """
        new_rotation = rotation @ self.rotation.T
        return new_rotation, self.scale * translation - new_rotation @ self.translation

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991) for (N, 3) arrays, N >= 3
    (N = 2 determines it up to a rotation about the baseline; the minimal-norm one is returned)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s0, d0 = src - mu_s, dst - mu_d
    cov = d0.T @ s0 / len(src)
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1
    rotation = u @ np.diag(d) @ vt
    var_s = (s0**2).sum() / len(src)
    scale = float((sig * d).sum() / var_s) if with_scale and var_s > 0 else 1.0
    return Sim3(scale, rotation, mu_d - scale * rotation @ mu_s)
