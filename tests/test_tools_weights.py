"""tools/bench_weights.py: the residual spread per keypoint-scale octave, against known noise."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pycolmap")  # the script imports the peer's helpers
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_weights import residuals_by_scale

from sfm.core.model import Camera, Image, Reconstruction
from sfm.io.colmap_model import write_model
from sfm.io.database import Database

SCALES = (1.0, 2.0, 4.0, 8.0)  # one in each of four half-octave bins: [0.8, 1.13), [1.6, 2.26), [3.2, 4.53), [6.4, 9.05)


def _two_views(tmp_path: Path, sigma_of_scale) -> tuple[Path, Path]:
    """Two posed images of 4000 points whose keypoints carry Gaussian noise of std
    ``sigma_of_scale(scale)`` per axis; the model's points and poses are the true ones, so the
    residuals are that noise.  (model folder, database)."""
    rng = np.random.default_rng(3)
    n, f = 4000, 500.0
    xyz = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 6, n)])
    scale = rng.choice(SCALES, size=(2, n))
    recon = Reconstruction()
    recon.add_camera(Camera(1, "PINHOLE", 640, 480, np.array([f, f, 319.5, 239.5])))
    db = Database(tmp_path / "database.db")
    db.add_camera("PINHOLE", 640, 480, [f, f, 319.5, 239.5], camera_id=1)
    for k, t in enumerate((np.zeros(3), np.array([-1.0, 0.0, 0.0]))):
        cam = xyz + t
        uv = f * cam[:, :2] / cam[:, 2:] + [319.5, 239.5]
        noisy = uv + rng.normal(size=(n, 2)) * sigma_of_scale(scale[k])[:, None]
        recon.add_image(Image(k + 1, f"im{k}.png", 1, np.eye(3), t, noisy))
        db.add_image(f"im{k}.png", 1, image_id=k + 1)
        db.write_keypoints(k + 1, np.column_stack([noisy, scale[k], np.zeros(n)]).astype(np.float32))
    db.close()
    for j in range(n):
        recon.add_point3D(xyz[j], [(1, j), (2, j)])
    write_model(recon, tmp_path / "model")
    return tmp_path / "model", tmp_path / "database.db"


def test_noise_in_proportion_to_the_scale_gives_a_constant_ratio(tmp_path):
    model, database = _two_views(tmp_path, lambda s: 0.05 * s)
    rows = residuals_by_scale(model, database)
    assert [r["median_scale"] for r in rows] == list(SCALES)
    assert sum(r["observations"] for r in rows) == 8000
    for r in rows:
        assert r["spread/scale"] == pytest.approx(0.05, rel=0.08)


def test_noise_that_does_not_grow_with_the_scale_gives_a_falling_ratio(tmp_path):
    model, database = _two_views(tmp_path, lambda s: np.full_like(s, 0.3))
    rows = residuals_by_scale(model, database)
    for r in rows:
        assert r["spread_px"] == pytest.approx(0.3, rel=0.08)
        assert r["spread/scale"] == pytest.approx(0.3 / r["median_scale"], rel=0.08)
