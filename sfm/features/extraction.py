"""SIFT keypoints and RootSIFT descriptors of one decoded image (arrays in, arrays out, no I/O).

The ``extract`` stage (``sfm.stages.extract``) runs :func:`extract_features` on every image.

Conventions:

- Detector: OpenCV SIFT (``cv2.SIFT_create``); contrastThreshold 0.02 is COLMAP's default peak
  threshold (0.02 / 3 per octave layer on a [0, 1] image; OpenCV's own default is 0.04) and
  edgeThreshold 10 COLMAP's too; both are options. ``enable_precise_upscale=True``: OpenCV's
  default doubling of the image for the first octave maps upsampled pixel i to i / 2 instead
  of i / 2 - 0.25, which biases every keypoint by +0.25 px in x and y; the precise upscale has
  no such bias, so keypoints are in OpenCV's pixel-centre convention (``tests/test_features.py``
  checks it on an image rotated by 90 degrees, where every keypoint's place is known).
- Images whose longer side exceeds ``max_image_size`` are shrunk with ``cv2.INTER_AREA`` before
  SIFT (SIFT never sees the full image); keypoints are mapped back to full-resolution pixels with
  OpenCV's pixel-centre convention ``x = (x_small + 0.5) * sx - 0.5`` (likewise y) and their
  scale multiplied by the mean of ``sx, sy``.
- At most ``max_num_features`` keypoint *locations* per image, each with at most
  ``MAX_ORIENTATIONS`` (2) orientations: COLMAP's meaning of the option (it caps the
  detections, then gives each up to ``max_num_orientations = 2`` descriptors), so a busy image
  holds somewhat more than ``max_num_features`` keypoints (Lowe 2004: about 15% of locations
  get a second orientation).  OpenCV's own ``nfeatures`` counts each orientation as a keypoint,
  so the same number would keep fewer locations than COLMAP does, and fewer matches on hard
  (oblique) pairs.  Which locations: by default the largest-scale ones, COLMAP's documented
  rule ("maximum number of features to detect, keeping larger-scale features"); coarse blobs
  recur across viewpoint and resolution changes where the finest ones are texture and noise;
  ``keep_features="strongest"`` keeps the highest SIFT response instead (OpenCV's rule).  SIFT detects every keypoint; the kept ones get the descriptors
  ``detectAndCompute`` gives them (computed for the kept ones alone on large images, from the
  same doubled-image pyramid: :data:`DESCRIBE_ALL_PIXELS`).  Stored in the order kept.
- Keypoints are float32 rows ``(x, y, scale, orientation)``: the 4-column layout COLMAP reads.
  ``scale = KeyPoint.size / 2`` (OpenCV's size is the diameter ``2 sigma`` of the keypoint's
  Gaussian scale; COLMAP's and VLFeat's scale is ``sigma``), ``orientation =
  radians(KeyPoint.angle)`` in [0, 2 pi): OpenCV's angle is the dominant gradient direction in
  image axes (x right, y down), which is COLMAP's convention too. x, y use OpenCV's pixel centres
  in memory; ``Database.write_keypoints`` shifts them to COLMAP's (+0.5).
- Descriptors: RootSIFT (Arandjelovic & Zisserman 2012; COLMAP's default ``L1_ROOT``): each
  128-vector is L1-normalised and square-rooted (which gives unit L2 norm), then quantised as
  COLMAP does: ``uint8(min(round(512 * d), 255))``. Dividing the stored bytes by 512 gives the
  unit vector back (up to rounding and the rare clipping). With ``root_sift=False`` the vector
  is L2-normalised instead, then quantised the same way.
- Masks (``--masks DIR``, COLMAP's convention ``DIR/<image name>.png``, zero = ignore; an image
  without one is used whole): SIFT detects only where the mask, shrunk with SIFT's image
  (nearest pixel), is non-zero, and a keypoint whose full-resolution pixel (rounded) is masked
  is dropped, so none is kept in a masked area.
- Images, EXIF and grey levels: ``sfm.io.image_files``; cameras and ``--intrinsics``:
  ``sfm.features.cameras``; bad files and duplicates: the ``extract`` stage
  (``sfm.stages.extract``), which decodes the images and calls :func:`extract_features`.
"""

from __future__ import annotations

import cv2
import numpy as np

from sfm.features.options import ExtractOptions
from sfm.features.sift import detect_and_select
from sfm.io.image_files import downscale


def detect_sift(gray: np.ndarray, options: ExtractOptions, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on an 8-bit grey image as given: ``(keypoints (N, 4) float32 x, y, scale,
    orientation; descriptors (N, 128) uint8)``: at most ``max_num_features`` locations, each
    with at most ``MAX_ORIENTATIONS`` orientations, chosen by ``keep_features`` (module
    docstring; :func:`sfm.features.sift.detect_and_select`), in the order kept."""
    return detect_and_select(gray, options.contrast_threshold, options.edge_threshold,
                             options.max_num_features, options.keep_features, options.root_sift, mask)


def extract_features(gray: np.ndarray, options: ExtractOptions,
                     mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`detect_sift` on ``gray`` shrunk to ``max_image_size``, keypoints in ``gray``'s
    pixels (OpenCV convention: ``x = (x_small + 0.5) * sx - 0.5``, scale times mean(sx, sy)).
    ``mask`` (bool, ``gray``'s shape): no keypoint is kept where it is False."""
    small, sx, sy = downscale(gray, options.max_image_size)
    small_mask = None
    if mask is not None:
        small_mask = mask.astype(np.uint8) * 255
        if small.shape != gray.shape:
            small_mask = cv2.resize(small_mask, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST)
    keypoints, descriptors = detect_sift(small, options, small_mask)
    if (sx, sy) != (1.0, 1.0):
        keypoints[:, 0] = (keypoints[:, 0] + 0.5) * sx - 0.5
        keypoints[:, 1] = (keypoints[:, 1] + 0.5) * sy - 0.5
        keypoints[:, 2] *= (sx + sy) / 2.0
    if mask is not None and len(keypoints):
        col = np.clip(np.rint(keypoints[:, 0]).astype(np.int64), 0, mask.shape[1] - 1)
        row = np.clip(np.rint(keypoints[:, 1]).astype(np.int64), 0, mask.shape[0] - 1)
        keep = mask[row, col]
        keypoints, descriptors = keypoints[keep], descriptors[keep]
    return keypoints, descriptors
