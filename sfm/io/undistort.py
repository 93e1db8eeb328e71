"""Undistorted images and a PINHOLE model: COLMAP's ``image_undistorter`` layout.

``OUT/images/<name>`` holds each registered image resampled (OpenCV ``remap``, bilinear) into a
``PINHOLE`` camera, ``OUT/sparse/0`` the model with those cameras and the keypoints moved with
the pixels: what the Gaussian-splatting reference code, OpenMVS and other dense methods read.

The undistorted camera of a camera (:func:`undistorted_camera`) keeps its focal lengths; its
image is the largest rectangle, centred on the principal axis's image, whose every pixel comes
from inside the original image (COLMAP's ``blank_pixels = 0``), within 0.2 and 2 times the
original size (COLMAP's ``min_scale``, ``max_scale``).  Pixels follow graphsfm's convention
(pixel centres at integers) in memory, COLMAP's in the files.  Images are read upright (EXIF
orientation applied), as extraction saw them.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
from PIL import Image as PILImage, ImageOps

from backend.camera_models import focal_lengths, model_spec, project, unproject
from sfm.core.model import Camera, Reconstruction
from sfm.errors import InputError
from sfm.io.colmap_model import write_model

logger = logging.getLogger(__name__)

MIN_SCALE, MAX_SCALE = 0.2, 2.0  # COLMAP's image_undistorter defaults


def _has_distortion(camera: Camera) -> bool:
    return bool(np.any(np.asarray(camera.params)[list(model_spec(camera.model).extra_idx)] != 0))


def undistorted_camera(camera: Camera) -> Camera:
    """The PINHOLE camera of ``camera``'s undistorted image (module docstring)."""
    fx, fy = focal_lengths(camera.model, camera.params)
    spec = model_spec(camera.model)
    w, h = camera.width, camera.height
    if not _has_distortion(camera):
        cx, cy = np.asarray(camera.params)[list(spec.pp_idx)]
        return Camera(camera.camera_id, "PINHOLE", w, h, np.array([fx, fy, cx, cy]))
    xs, ys = np.linspace(0, w - 1, max(w, 2)), np.linspace(0, h - 1, max(h, 2))
    edge = lambda px: unproject(camera.model, camera.params, px)  # noqa: E731
    left = edge(np.column_stack([np.zeros_like(ys), ys]))[:, 0].max()
    right = edge(np.column_stack([np.full_like(ys, w - 1), ys]))[:, 0].min()
    top = edge(np.column_stack([xs, np.zeros_like(xs)]))[:, 1].max()
    bottom = edge(np.column_stack([xs, np.full_like(xs, h - 1)]))[:, 1].min()
    if not np.all(np.isfinite([left, right, top, bottom])):
        raise InputError(f"camera {camera.camera_id} ({camera.model} {np.round(camera.params, 4).tolist()}): its "
                         "distortion folds back inside the image, so its edge pixels have no ray to undistort to")
    new_w = int(np.clip(np.floor((right - left) * fx) + 1, MIN_SCALE * w, MAX_SCALE * w))
    new_h = int(np.clip(np.floor((bottom - top) * fy) + 1, MIN_SCALE * h, MAX_SCALE * h))
    cx = (new_w - 1) / 2.0 - fx * (left + right) / 2.0
    cy = (new_h - 1) / 2.0 - fy * (top + bottom) / 2.0
    return Camera(camera.camera_id, "PINHOLE", new_w, new_h, np.array([fx, fy, cx, cy]))


def undistortion_maps(camera: Camera, pinhole: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps: for each pixel of ``pinhole``'s image, where it is in ``camera``'s."""
    fx, fy, cx, cy = pinhole.params
    u, v = np.meshgrid(np.arange(pinhole.width, dtype=np.float64), np.arange(pinhole.height, dtype=np.float64))
    rays = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=1)
    src = project(camera.model, camera.params, rays).astype(np.float32)
    return src[:, 0].reshape(u.shape), src[:, 1].reshape(u.shape)


def undistort_model(recon: Reconstruction) -> Reconstruction:
    """A copy of ``recon`` with PINHOLE cameras (:func:`undistorted_camera`) and every keypoint
    moved to its pixel in the undistorted image; poses and points unchanged."""
    out = recon.copy()
    out.cameras = {cid: undistorted_camera(cam) for cid, cam in recon.cameras.items()}
    for image in out.images.values():
        cam, pin = recon.cameras[image.camera_id], out.cameras[image.camera_id]
        if len(image.keypoints):
            normalised = unproject(cam.model, cam.params, image.keypoints)
            fx, fy, cx, cy = pin.params
            image.keypoints = np.column_stack([fx * normalised[:, 0] + cx, fy * normalised[:, 1] + cy])
    return out


def read_upright(path: Path) -> np.ndarray:
    """An image file as an upright (EXIF orientation applied) array, RGB(A) or grey as stored."""
    with PILImage.open(path) as im:
        return np.asarray(ImageOps.exif_transpose(im))


def export_undistorted(recon: Reconstruction, image_dir: Path, out: Path) -> dict:
    """``out/images`` and ``out/sparse/0`` (module docstring); returns counts for the user."""
    image_dir, out = Path(image_dir), Path(out)
    undistorted = undistort_model(recon)
    maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    registered = [recon.images[i] for i in recon.registered_image_ids]
    for image in registered:
        src = image_dir / image.name
        if not src.is_file():
            raise InputError(f"image {image.name} of the model is not in {image_dir}")
        cam, pin = recon.cameras[image.camera_id], undistorted.cameras[image.camera_id]
        pixels = read_upright(src)
        if pixels.shape[:2] != (cam.height, cam.width):
            raise InputError(f"{src} is {pixels.shape[1]}x{pixels.shape[0]} (upright) but its camera is "
                             f"{cam.width}x{cam.height}: not the images of this model")
        if image.camera_id not in maps:
            maps[image.camera_id] = undistortion_maps(cam, pin)
        map_x, map_y = maps[image.camera_id]
        resampled = cv2.remap(pixels, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        target = out / "images" / image.name
        target.parent.mkdir(parents=True, exist_ok=True)
        PILImage.fromarray(resampled).save(target, **({"quality": 95} if target.suffix.lower() in (".jpg", ".jpeg") else {}))
    write_model(undistorted, out / "sparse" / "0")
    logger.info("undistorted %d images into %s", len(registered), out)
    return {"images": len(registered), "cameras": {cid: [c.width, c.height] for cid, c in undistorted.cameras.items()}}
