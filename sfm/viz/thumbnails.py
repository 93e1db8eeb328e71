"""The images of the recording: JPEG thumbnails of bounded size, and where they come from.

The extract stage makes each image's thumbnail in its worker, from the colour image it decodes
for the keypoint colours anyway (:func:`make_thumbnail`), and hands it to the recorder, which
keeps it (a few tens of kB) for the later stages' views: the matches between two images, the
camera frustums.  A stage run on its own, or a resumed run whose images were extracted before,
reads the image file again (:func:`thumbnail_from_file`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

JPEG_QUALITY = 85


@dataclass(frozen=True)
class Thumbnail:
    """A JPEG of an image shrunk so its longer side is at most the recording's thumbnail size:
    ``width x height`` pixels of an image of ``full_width x full_height``; a full-resolution
    pixel ``x`` (OpenCV's pixel centres) is at ``(x + 0.5) * scale_x - 0.5`` in it."""

    jpeg: bytes
    width: int
    height: int
    full_width: int
    full_height: int

    @property
    def scale_x(self) -> float:
        return self.width / self.full_width

    @property
    def scale_y(self) -> float:
        return self.height / self.full_height

    def to_thumbnail(self, xy: np.ndarray) -> np.ndarray:
        """Full-resolution pixel positions ``(N, 2)`` in the thumbnail's pixels."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return (xy + 0.5) * [self.scale_x, self.scale_y] - 0.5

    def pixels(self) -> np.ndarray:
        """The thumbnail decoded to RGB (H, W, 3)."""
        bgr = cv2.imdecode(np.frombuffer(self.jpeg, np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def make_thumbnail(rgb: np.ndarray, size: int) -> Thumbnail:
    """``rgb`` (H, W, 3) shrunk (area averaging) so its longer side is at most ``size``, as JPEG."""
    height, width = rgb.shape[:2]
    scale = min(1.0, size / max(width, height))
    tw, th = max(1, round(width * scale)), max(1, round(height * scale))
    small = cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA) if scale < 1.0 else rgb
    return encode_thumbnail(small, width, height)


def encode_thumbnail(rgb: np.ndarray, full_width: int, full_height: int) -> Thumbnail:
    """RGB pixels (H, W, 3) as a :class:`Thumbnail` of an image of ``full_width x full_height``."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return Thumbnail(buf.tobytes(), int(rgb.shape[1]), int(rgb.shape[0]), int(full_width), int(full_height))


def thumbnail_from_file(path: Path, size: int) -> Thumbnail | None:
    """The thumbnail of an image file, or None when it cannot be read (a view is not worth
    failing a run for)."""
    from sfm.io.image_files import BadImageError, read_rgb

    try:
        return make_thumbnail(read_rgb(Path(path).read_bytes()), size)
    except (OSError, BadImageError, cv2.error) as exc:
        log.debug("no thumbnail for %s: %s", path, exc)
        return None
