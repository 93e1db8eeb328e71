"""Synthetic images and database readers shared by the extract-stage tests (test_features.py,
test_features_input.py, test_features_cameras.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from sfm.io.database import Database

FAST = {"max_num_features": 1000}


def textured(height: int, width: int, seed: int) -> np.ndarray:
    """A BGR image of random filled shapes with mild noise: plenty of SIFT corners and blobs."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width, 3), 128, np.uint8)
    for _ in range(80):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        if rng.random() < 0.5:
            w, h = int(rng.integers(5, width // 6)), int(rng.integers(5, height // 6))
            cv2.rectangle(img, (x, y), (x + w, y + h), color, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, min(width, height) // 10)), color, -1)
    noise = rng.normal(0.0, 3.0, img.shape)
    return cv2.GaussianBlur(np.clip(img + noise, 0, 255).astype(np.uint8), (3, 3), 0)


def write(path: Path, bgr: np.ndarray, exif: Image.Exif | None = None, **kw) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    im.save(path, exif=exif, **kw) if exif is not None else im.save(path, **kw)
    return path


def read_db(workspace: Path) -> tuple[dict, dict, dict, dict]:
    """(cameras, images by name, keypoints by name, descriptors by name)."""
    with Database(workspace / "database.db", readonly=True) as db:
        cams = db.read_cameras()
        images = {r.name: r for r in db.read_images().values()}
        kps = {n: db.read_keypoints(r.image_id) for n, r in images.items()}
        descs = {n: db.read_descriptors(r.image_id) for n, r in images.items()}
    return cams, images, kps, descs


def close_sets(a: np.ndarray, b: np.ndarray, tol: float) -> float:
    """Share of points of ``a`` with a point of ``b`` within ``tol`` pixels."""
    d = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=2)
    return float(np.mean(d.min(axis=1) <= tol))
