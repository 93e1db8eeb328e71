"""Image files: finding them, decoding them to upright 8-bit grey or RGB.

Conventions (the ``extract`` stage relies on them; see ``sfm.stages.extract``):

- An image is named by its path relative to the image folder with ``/`` separators
  (:func:`find_images`: extensions jpg, jpeg, png, tif, tiff, bmp, webp in any case, searched
  recursively, sorted by name).
- EXIF ``Orientation`` (tag 0x0112) is honoured: the pixels are rotated/flipped to the upright
  image *before* anything else sees them, so keypoints, widths and heights are all those of the
  upright image (what a photo viewer shows). Pillow's TIFF reader applies the tag itself on
  load; we rotate only images whose tag is still there after decoding.
- Grey levels: 8-bit images are converted with ITU-R 601 luma (``0.299 R + 0.587 G + 0.114 B``,
  as Pillow and ``cv2.cvtColor`` do; JPEGs are decoded straight to their luma channel, the same
  formula); alpha is dropped; palette images are expanded; 16-bit images are divided by 257
  (65535 -> 255, the same as keeping the high byte, like COLMAP's FreeImage conversion); float
  and 32-bit integer images are stretched from their min to their max.
- Colour (:func:`read_rgb`, for the colours of the 3D points and the recording's thumbnails): the
  same decoding and orientation, to 8-bit RGB; grey images give three equal channels.
- EXIF (``sfm.io.exif``): the focal prior, GPS, orientation, make and model.
- Masks (:func:`read_mask`, COLMAP's convention): ``MASKS/<image name>.png``, a grey or colour
  image of the upright image's size whose zero pixels are to be ignored (a mask of the stored,
  unrotated size is turned upright with its image's EXIF orientation).
- A file that cannot be used raises :class:`BadImageError` whose message is the reason (empty
  file, not an image, truncated, ...). Pillow's decompression-bomb limit is lifted while we read:
  a 100-megapixel photo is a normal input here.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from sfm.io.exif import (MAKE, MODEL, ORIENTATION, exif_number, exif_tags, exif_text, focal_prior_from_exif,
                         gps_from_exif, gps_tags)

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"})

# EXIF orientation -> the Pillow transpose that makes the image upright (as ImageOps.exif_transpose)
_UPRIGHT = {
    2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180,
    4: Image.Transpose.FLIP_TOP_BOTTOM, 5: Image.Transpose.TRANSPOSE,
    6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE, 8: Image.Transpose.ROTATE_90,
}  # fmt: skip
_SIXTEEN_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N")


class BadImageError(Exception):
    """A file that cannot be used as an image; the message says why."""


@dataclass(frozen=True)
class ImageInfo:
    """What the camera of an image needs: upright size and EXIF facts.

    ``focal_px`` is the EXIF focal prior in pixels of the upright image (None: EXIF gives none);
    ``focal_source`` is ``"exif-35mm"``, ``"exif-focal-plane"`` or ``"none"``; ``gps`` is
    ``(latitude deg, longitude deg, altitude m)`` on WGS84 from EXIF, or None.
    """

    width: int
    height: int
    orientation: int = 1
    make: str = ""
    model: str = ""
    focal_px: float | None = None
    focal_source: str = "none"
    gps: tuple[float, float, float] | None = None


def find_images(image_dir: Path) -> list[str]:
    """Names (relative paths, ``/`` separators) of the image files under ``image_dir``, sorted.

    Symbolic links are followed, but each real folder and file is visited once: a link back to
    a folder already visited (a loop) or to a file already found is skipped, with one warning
    line for all of them (the first name in walking order, folders and files sorted, wins)."""
    image_dir = Path(image_dir)
    names, seen_dirs, seen_files, skipped = [], set(), set(), []

    def key(path: str) -> tuple[int, int] | None:
        try:
            st = os.stat(path)
        except OSError:  # a dangling link
            return None
        return st.st_dev, st.st_ino

    for root, dirs, files in os.walk(image_dir, followlinks=True):
        here = key(root)
        if here in seen_dirs:
            skipped.append(Path(root).relative_to(image_dir).as_posix() + "/")
            dirs[:] = []
            continue
        seen_dirs.add(here)
        dirs.sort()
        for f in sorted(files):
            if os.path.splitext(f)[1].lower() not in IMAGE_EXTENSIONS:
                continue
            path = os.path.join(root, f)
            k = key(path)
            name = Path(path).relative_to(image_dir).as_posix()
            if k is not None and k in seen_files:
                skipped.append(name)
                continue
            if k is not None:
                seen_files.add(k)
            names.append(name)
    if skipped:
        logger.warning("%d link(s) in %s lead to a folder or file already found and are skipped: %s", len(skipped),
                       image_dir, ", ".join(skipped[:3]) + (" ..." if len(skipped) > 3 else ""))
    return sorted(names)


@contextmanager
def _no_pixel_limit() -> Iterator[None]:
    """Lift Pillow's decompression-bomb check (large photos are normal input) for a block."""
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            yield
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def _info_from_pil(im: Image.Image) -> ImageInfo:
    tags = exif_tags(im)
    orientation = int(exif_number(tags.get(ORIENTATION)) or 1)
    orientation = orientation if orientation in _UPRIGHT else 1
    width, height = im.size
    # Pillow's TIFF reader already reports the upright size (and rotates the pixels on load)
    upright_already = getattr(im, "_tile_size", im.size) != im.size
    if orientation in (5, 6, 7, 8) and not upright_already:
        width, height = height, width
    focal, source = focal_prior_from_exif(tags, width, height)
    return ImageInfo(
        width, height, orientation, exif_text(tags.get(MAKE)), exif_text(tags.get(MODEL)), focal, source,
        gps_from_exif(gps_tags(im)) if tags else None,
    )


def _cv2_gray(data: bytes) -> np.ndarray | None:
    """Decode with OpenCV (files Pillow cannot identify) to 8-bit grey, or None."""
    try:
        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None
    if arr is None or arr.size == 0:
        return None
    if arr.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(arr.shape[2])
        arr = arr[:, :, 0] if code is None else cv2.cvtColor(arr, code)
    return _to_uint8(arr)


def _to_uint8(arr: np.ndarray) -> np.ndarray:
    """8-bit grey from any depth: 16-bit / 257, float and wider ints stretched min..max."""
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind == "u" and arr.dtype.itemsize == 2:
        return np.round(arr.astype(np.float32) / 257.0).astype(np.uint8)
    a = np.nan_to_num(arr.astype(np.float64))
    if arr.dtype.kind in "iu" and a.size and a.min() >= 0 and a.max() <= 65535:
        return np.round(a / 257.0).astype(np.uint8)
    lo, hi = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)
    scale = 255.0 / (hi - lo) if hi > lo else 0.0
    return np.round((a - lo) * scale).astype(np.uint8)


def _pil_gray(im: Image.Image) -> Image.Image:
    """Decode to an 8-bit 'L' image or a 16/32-bit single-channel image (numpy converts)."""
    if im.format == "JPEG" and im.mode in ("RGB", "YCbCr"):
        im.draft("L", im.size)  # decode only the luma channel: less memory, same grey values
    if im.mode in _SIXTEEN_BIT_MODES or im.mode in ("I", "F", "L"):
        im.load()
        return im
    return im.convert("L")  # RGB(A), LA, P, PA, 1, CMYK, ...: luma, alpha dropped


def probe_image(path: Path) -> ImageInfo:
    """Upright size and EXIF facts of an image file, reading only its header when possible."""
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise BadImageError("empty file")
        with _no_pixel_limit(), Image.open(path) as im:
            return _info_from_pil(im)
    except UnidentifiedImageError:
        gray = _cv2_gray(path.read_bytes())
        if gray is None:
            raise BadImageError("not an image Pillow or OpenCV can read") from None
        return ImageInfo(int(gray.shape[1]), int(gray.shape[0]))
    except (OSError, ValueError, SyntaxError, EOFError) as exc:
        raise BadImageError(f"cannot read: {exc}") from None


def read_gray(data: bytes) -> tuple[np.ndarray, ImageInfo]:
    """Decode an image file's bytes to an upright (EXIF orientation applied) uint8 grey image."""
    gray, info = _decode(data, _pil_gray, _cv2_gray)
    if gray.ndim != 2 or gray.shape != (info.height, info.width):
        raise BadImageError(f"unexpected decoded shape {gray.shape}")
    return gray, info


def read_rgb(data: bytes) -> np.ndarray:
    """Decode an image file's bytes to an upright uint8 RGB image (H, W, 3), the same pixels
    :func:`read_gray` gives in grey: alpha dropped, palettes expanded, grey images repeated in
    the three channels, 16-bit and float images scaled as :func:`read_gray` scales them."""
    rgb, info = _decode(data, _pil_rgb, _cv2_rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    if rgb.shape != (info.height, info.width, 3):
        raise BadImageError(f"unexpected decoded shape {rgb.shape}")
    return rgb


def _decode(data: bytes, from_pil, from_cv2) -> tuple[np.ndarray, ImageInfo]:
    """``from_pil(image)`` upright as uint8, or ``from_cv2(data)`` for files Pillow cannot identify."""
    if not data:
        raise BadImageError("empty file")
    with _no_pixel_limit():
        try:
            im = Image.open(BytesIO(data))
        except UnidentifiedImageError:
            arr = from_cv2(data)
            if arr is None:
                raise BadImageError("not an image Pillow or OpenCV can read") from None
            return arr, ImageInfo(int(arr.shape[1]), int(arr.shape[0]))
        except (OSError, ValueError, SyntaxError, EOFError) as exc:
            raise BadImageError(f"cannot read: {exc}") from None
        try:
            info = _info_from_pil(im)
            decoded = from_pil(im)
            # some Pillow readers (TIFF) rotate on load and then drop the tag: rotate only once
            still_tagged = exif_number(exif_tags(im).get(ORIENTATION)) == info.orientation
            if info.orientation in _UPRIGHT and still_tagged:
                decoded = decoded.transpose(_UPRIGHT[info.orientation])
            arr = _to_uint8(np.asarray(decoded))
        except (OSError, ValueError, SyntaxError, EOFError) as exc:  # truncated, corrupt
            raise BadImageError(f"cannot decode: {exc}") from None
        finally:
            im.close()
    return arr, info


def _pil_rgb(im: Image.Image) -> Image.Image:
    """Decode to 'RGB', or to what :func:`_pil_gray` gives for single-channel 16/32-bit and
    float images (their grey levels are scaled to 8 bits first, then repeated)."""
    if im.mode in _SIXTEEN_BIT_MODES or im.mode in ("I", "F"):
        return _pil_gray(im)
    return im.convert("RGB")


def _cv2_rgb(data: bytes) -> np.ndarray | None:
    """Decode with OpenCV (files Pillow cannot identify) to 8-bit RGB, or None."""
    try:
        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    except cv2.error:
        return None
    if arr is None or arr.size == 0:
        return None
    return _to_uint8(cv2.cvtColor(arr, cv2.COLOR_BGR2RGB))


def mask_path(masks: Path, name: str) -> Path:
    """Where COLMAP looks for the mask of image ``name``: ``masks/<name>.png``."""
    return Path(masks) / f"{name}.png"


def read_mask(data: bytes, info: ImageInfo) -> np.ndarray:
    """The mask file's bytes as a boolean array of the upright image's shape (H, W): True
    where features may be, False where the mask is zero (every channel, alpha ignored)."""
    with _no_pixel_limit():
        try:
            with Image.open(BytesIO(data)) as im:
                arr = np.asarray(im.convert("RGB") if im.mode in ("P", "PA", "LA", "RGBA", "CMYK", "YCbCr") else im)
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError) as exc:
            raise BadImageError(f"cannot read its mask: {exc}") from None
    keep = arr.reshape(arr.shape[0], arr.shape[1], -1).any(axis=2)
    if keep.shape == (info.width, info.height) and info.orientation in (5, 6, 7, 8) and info.width != info.height:
        keep = np.asarray(Image.fromarray(keep).transpose(_UPRIGHT[info.orientation]))
    if keep.shape != (info.height, info.width):
        raise BadImageError(
            f"its mask is {keep.shape[1]}x{keep.shape[0]} but the image is {info.width}x{info.height} (upright)")
    return keep


def downscale(gray: np.ndarray, max_image_size: int) -> tuple[np.ndarray, float, float]:
    """``(small, sx, sy)``: ``gray`` shrunk (INTER_AREA) so its longer side is at most
    ``max_image_size``; full-resolution pixels are ``x = (x_small + 0.5) * sx - 0.5`` (OpenCV's
    pixel-centre convention), likewise y with ``sy``. ``sx == sy == 1`` when no shrink is needed.
    """
    height, width = gray.shape[:2]
    scale = max(width, height) / float(max_image_size)
    if scale <= 1.0:
        return gray, 1.0, 1.0
    new_w, new_h = max(1, round(width / scale)), max(1, round(height / scale))
    small = cv2.resize(gray, (new_w, new_h), interpolation=cv2.INTER_AREA)
    return small, width / new_w, height / new_h
