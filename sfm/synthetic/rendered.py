"""A small rendered-image scene with exact ground truth, for end-to-end tests without downloads.

A facade of procedurally textured planes (a back wall, two boxes standing out of it, a strip of
ground) is photographed by cameras on an arc in front of it.  Each image is rendered with a
z-buffer: every textured rectangle is mapped into the image by the homography its plane
induces, and the nearest surface wins at each pixel.  Cameras never see a plane from behind or
cross one, so no clipping is needed.  Everything is seeded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from backend.geometry import look_at, rotation_to_quaternion
from sfm.synthetic.options import RenderOptions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plane:
    """A textured rectangle ``origin + s * u + t * v`` for ``s, t`` in [0, 1]."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: np.ndarray  # (S, S, 3) uint8, BGR


def procedural_texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """Rich, non-repetitive texture: multi-octave colour noise plus random shapes and strokes,
    so SIFT finds many distinctive keypoints at several scales."""
    img = np.zeros((size, size, 3), np.float32)
    for cells, weight in ((4, 0.5), (16, 0.3), (64, 0.2)):
        noise = rng.random((cells, cells, 3)).astype(np.float32)
        img += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img * 255, 0, 255).astype(np.uint8)
    for _ in range(size // 4):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        center = tuple(int(c) for c in rng.integers(0, size, 2))
        kind = rng.integers(0, 3)
        if kind == 0:
            cv2.circle(img, center, int(rng.integers(3, size // 20)), color, -1, cv2.LINE_AA)
        elif kind == 1:
            half = rng.integers(3, size // 20, 2)
            p0 = (center[0] - int(half[0]), center[1] - int(half[1]))
            cv2.rectangle(img, p0, (center[0] + int(half[0]), center[1] + int(half[1])), color, -1)
        else:
            end = tuple(int(c) for c in rng.integers(0, size, 2))
            cv2.line(img, center, end, color, int(rng.integers(1, 5)), cv2.LINE_AA)
    return img


def facade_planes(rng: np.random.Generator, texture_size: int) -> list[Plane]:
    """World: x right, y towards the cameras, z up; the wall is the plane y = 0."""
    boxes = [((-3.0, 0.0), 1.6, 1.2, 2.2), ((1.4, 0.0), 1.8, 0.9, 1.6)]  # (x, y), width, depth, height
    planes = [Plane(np.array([-6.0, 0, 0]), np.array([12.0, 0, 0]), np.array([0, 0, 5.0]), None)]
    planes.append(Plane(np.array([-6.0, 0, 0]), np.array([12.0, 0, 0]), np.array([0, 3.5, 0.0]), None))
    for (x, y), w, d, h in boxes:
        planes.append(Plane(np.array([x, y + d, 0]), np.array([w, 0, 0]), np.array([0, 0, h]), None))  # front
        planes.append(Plane(np.array([x, y, 0]), np.array([0, d, 0]), np.array([0, 0, h]), None))  # left
        planes.append(Plane(np.array([x + w, y + d, 0]), np.array([0, -d, 0]), np.array([0, 0, h]), None))
        planes.append(Plane(np.array([x, y, h]), np.array([w, 0, 0]), np.array([0, d, 0]), None))  # top
    return [Plane(p.origin, p.u, p.v, procedural_texture(texture_size, rng)) for p in planes]


def arc_cameras(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` poses on an arc of +-50 degrees, 9 m from the wall, looking at it."""
    rs, ts = [], []
    for a in np.radians(np.linspace(-50, 50, n)):
        center = np.array([9.0 * np.sin(a), 9.0 * np.cos(a), 1.6 + 0.8 * np.sin(3 * a)])
        target = np.array([0.0, 0.5, 1.5]) + rng.normal(0, 0.2, 3)
        r, t = look_at(center, target, up=np.array([0.0, 0.0, 1.0]))
        rs.append(r)
        ts.append(t)
    return np.array(rs), np.array(ts)


def render(planes: list[Plane], K: np.ndarray, rotation: np.ndarray, translation: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """One image (BGR uint8) by z-buffered homography warps; background is mid grey."""
    width, height = size
    image = np.full((height, width, 3), 90, np.uint8)
    depth = np.full((height, width), np.inf)
    rays = np.linalg.inv(K) @ np.stack(
        [*np.meshgrid(np.arange(width), np.arange(height)), np.ones((height, width))]
    ).reshape(3, -1)
    for plane in planes:
        s = plane.texture.shape[0] - 1
        # Texture pixel (a, b) -> world origin + a/s u + b/s v -> camera -> image.
        world_from_tex = np.column_stack([plane.u / s, plane.v / s, plane.origin])
        H = K @ (rotation @ world_from_tex + np.column_stack([np.zeros((3, 2)), translation]))
        warped = cv2.warpPerspective(plane.texture, H, (width, height), flags=cv2.INTER_AREA)
        mask = cv2.warpPerspective(np.ones(plane.texture.shape[:2], np.uint8), H, (width, height), flags=cv2.INTER_NEAREST) > 0
        normal_cam = rotation @ np.cross(plane.u, plane.v)
        offset = normal_cam @ (rotation @ plane.origin + translation)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (offset / (normal_cam @ rays)).reshape(height, width)  # depth along the ray (z = 1)
        nearer = mask & (z > 0) & (z < depth)
        image[nearer] = warped[nearer]
        depth[nearer] = z[nearer]
    return image


def write_rendered_scene(out_dir: Path, opts: RenderOptions) -> dict:
    """Render the scene into ``out_dir/images/*.png`` and its GT into
    ``out_dir/gt/cameras_gt_opencv.txt``; returns a summary."""
    rng = np.random.default_rng(opts.seed)
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "gt").mkdir(parents=True, exist_ok=True)
    planes = facade_planes(rng, opts.texture_size)
    rotations, translations = arc_cameras(opts.num_images, rng)
    K = np.array([[opts.focal, 0, (opts.width - 1) / 2], [0, opts.focal, (opts.height - 1) / 2], [0, 0, 1]])
    lines = ["# IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ (cam_from_world, OpenCV pixels)"]
    for i, (r, t) in enumerate(zip(rotations, translations)):
        name = f"view_{i:03d}.png"
        image = render(planes, K, r, t, (opts.width, opts.height))
        tmp = out_dir / "images" / f".{name}.tmp.png"
        cv2.imwrite(str(tmp), image)
        tmp.replace(out_dir / "images" / name)
        vals = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *rotation_to_quaternion(r), *t]
        lines.append(f"{name} {opts.width} {opts.height} " + " ".join(f"{v:.17g}" for v in vals))
    (out_dir / "gt" / "cameras_gt_opencv.txt").write_text("\n".join(lines) + "\n")
    log.info("rendered %d images into %s", opts.num_images, out_dir / "images")
    return {"scene": "rendered", "images": opts.num_images, "image_dir": str(out_dir / "images"), "gt_table": str(out_dir / "gt" / "cameras_gt_opencv.txt")}
