"""Similarity transforms (Sim3): the one type for merging local models and aligning to ground truth.

A similarity named ``b_from_a`` maps points of frame ``a`` into frame ``b``:
``X_b = scale * rotation @ X_a + translation``.  Poses are ``cam_from_world``
(``x_cam = R @ X + t``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
