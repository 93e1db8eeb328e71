"""The colour of each keypoint, read from the colour image the extract stage decodes anyway.

A 3D point's colour is the mean over its track of the colours of the keypoints that observe it
(``sfm.mapper.output.to_reconstruction``), as COLMAP colours its points (it reads each registered
image at the end and interpolates bilinearly at the keypoints).  Here the colours are read once,
at extraction, from the same decoded pixels as the keypoints, and kept in the database next to
them (``Database.write_keypoint_colors``): no image is read twice and the map and merge stages
need no image files.
"""

from __future__ import annotations

import cv2
import numpy as np


def keypoint_colors(rgb: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """``(K, 3)`` uint8 RGB of ``rgb`` (H, W, 3) at each keypoint's ``x, y`` (OpenCV's pixel
    centres), bilinearly interpolated; positions outside the image take the nearest border pixel."""
    if len(keypoints) == 0:
        return np.zeros((0, 3), np.uint8)
    xy = np.asarray(keypoints, dtype=np.float32)[:, :2]
    map_x, map_y = np.ascontiguousarray(xy[:, :1]), np.ascontiguousarray(xy[:, 1:])
    sampled = cv2.remap(np.ascontiguousarray(rgb), map_x, map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(sampled.reshape(-1, 3), dtype=np.uint8)
