"""Which SIFT keypoints an image keeps, and how descriptors are stored (``sfm.stages.extract``).

:func:`detect_and_select` runs OpenCV's SIFT and keeps what the options ask for; the rest are
pure array functions: :func:`top_locations` applies COLMAP's meaning of
``max_num_features`` (keypoint locations, each with up to ``MAX_ORIENTATIONS`` descriptors) to
OpenCV's output, where every orientation is a keypoint of its own;
:func:`quantize_descriptors` is COLMAP's RootSIFT-to-bytes conversion; :func:`keypoint_scales`
and :func:`localization_sigma` give bundle adjustment each keypoint's positional uncertainty.
"""

from __future__ import annotations

import cv2
import numpy as np

# Orientations one keypoint location keeps (COLMAP's SiftExtraction.max_num_orientations).
MAX_ORIENTATIONS = 2
# Scale (Gaussian sigma, pixels) of SIFT's finest level when the image is doubled first (OpenCV's
# and COLMAP's default first octave -1): the base sigma 1.6 halved.
FINEST_SCALE = 0.8


def top_locations(locations: np.ndarray, score: np.ndarray, max_locations: int,
                  max_orientations: int = MAX_ORIENTATIONS) -> np.ndarray:
    """Indices of the keypoints to keep, highest score first (the SIFT response, or the scale):
    those of the ``max_locations`` best locations (rows of ``locations`` that are equal, e.g.
    x, y, size, are one location seen at several orientations), at most ``max_orientations``
    per location: the first in order of score (OpenCV gives a location's orientations the same
    response and size, so the first in OpenCV's order).  ``locations`` may hold fewer than
    ``max_locations`` distinct rows; then all of them count."""
    order = np.argsort(-np.asarray(score), kind="stable")
    if len(order) == 0:
        return order
    _, first, location = np.unique(np.asarray(locations)[order], axis=0, return_index=True, return_inverse=True)
    location = location.ravel()
    rank = np.empty(len(first), np.int64)  # locations ranked by their strongest keypoint
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    by_location = np.argsort(location, kind="stable")  # strongest first within a location
    starts = np.searchsorted(location[by_location], np.arange(len(first)))
    sizes = np.diff(np.append(starts, len(order)))
    nth = np.empty(len(order), np.int64)  # 0: a location's strongest keypoint, 1: the next...
    nth[by_location] = np.arange(len(order)) - np.repeat(starts, sizes)
    return order[(rank[location] < max_locations) & (nth < max_orientations)]


def quantize_descriptors(descriptors: np.ndarray, root_sift: bool = True) -> np.ndarray:
    """(N, 128) uint8: RootSIFT (L1-normalise, sqrt) or L2-normalised, times 512, rounded,
    clipped to 255 (COLMAP's ``FeatureDescriptorsToUnsignedByte``)."""
    d = np.maximum(np.asarray(descriptors, np.float64).reshape(-1, 128), 0.0)
    if root_sift:
        l1 = d.sum(axis=1, keepdims=True)
        d = np.sqrt(d / np.where(l1 > 0, l1, 1.0))
    else:
        l2 = np.linalg.norm(d, axis=1, keepdims=True)
        d = d / np.where(l2 > 0, l2, 1.0)
    return np.minimum(np.round(512.0 * d), 255.0).astype(np.uint8)


def keypoint_scales(keypoints: np.ndarray) -> np.ndarray | None:
    """Detection scale (Gaussian sigma, pixels) of each keypoint row: column 2 of the
    ``(x, y, scale, orientation)`` layout, ``sqrt(|det A|)`` of COLMAP's affine
    ``(x, y, a11, a12, a21, a22)`` layout; None for bare ``(x, y)`` rows."""
    kp = np.asarray(keypoints, np.float64)
    if kp.ndim != 2 or kp.shape[1] not in (4, 6):
        return None
    if kp.shape[1] == 4:
        return kp[:, 2].copy()
    return np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))


def localization_sigma(scales: np.ndarray) -> np.ndarray:
    """Standard deviation (pixels) of a keypoint's position from its detection scale:
    ``max(1, scale / FINEST_SCALE)``.  A SIFT extremum is located by a quadratic fit on a grid
    whose spacing, like the blob itself, grows with the scale, so its positional error grows in
    proportion to the scale (ORB-SLAM weighs its observations by pyramid level the same way);
    the finest level counts as 1 px.  Unknown (non-finite or non-positive) scales count as
    1 px."""
    s = np.asarray(scales, np.float64)
    ok = np.isfinite(s) & (s > 0)
    return np.where(ok, np.maximum(1.0, np.where(ok, s, 0.0) / FINEST_SCALE), 1.0)


# Up to this many pixels SIFT describes every detection and the selection takes its rows;
# above, it detects, selects, then describes the kept keypoints (a second Gaussian pyramid).
# Same output either way, only the cost differs: a small image holds fewer locations than
# max_num_features, so describing them all is cheaper than building a second pyramid, while a
# photo of several megapixels detects many times the locations kept, and describing only the
# kept ones saves more than the second pyramid costs.
DESCRIBE_ALL_PIXELS = 1_000_000


def detect_and_select(gray: np.ndarray, contrast_threshold: float, edge_threshold: float,
                      max_num_features: int, keep_features: str = "largest_scale",
                      root_sift: bool = True, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV SIFT on an 8-bit grey image: ``(keypoints (N, 4) float32 x, y, scale (sigma),
    orientation (radians); descriptors (N, 128) uint8)`` of at most ``max_num_features``
    locations with up to ``MAX_ORIENTATIONS`` orientations each, the largest-scale ones
    (``keep_features="largest_scale"``) or those of highest response ("strongest"), in the
    order kept; descriptors as ``detectAndCompute`` gives them (:data:`DESCRIBE_ALL_PIXELS`)."""
    empty = np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8)
    sift = cv2.SIFT_create(  # every detection: the selection below is ours
        nfeatures=0, contrastThreshold=contrast_threshold, edgeThreshold=edge_threshold,
        enable_precise_upscale=True,
    )  # fmt: skip
    small = gray.shape[0] * gray.shape[1] <= DESCRIBE_ALL_PIXELS
    kps, desc = sift.detectAndCompute(gray, mask) if small else (sift.detect(gray, mask), None)
    if not kps:
        return empty
    found = np.array([(k.pt[0], k.pt[1], k.size, k.response) for k in kps], np.float64)
    score = found[:, 2] if keep_features == "largest_scale" else found[:, 3]
    order = top_locations(found[:, :3], score, max_num_features, MAX_ORIENTATIONS)
    if small:
        kps, desc = [kps[i] for i in order], desc[order]
    else:
        # A keypoint of octave -1 makes compute() build the doubled first octave, as detection
        # did; without one it would start from the undoubled image and blur it differently.
        probe = cv2.KeyPoint(gray.shape[1] / 2.0, gray.shape[0] / 2.0, 1.6, 0.0, 0.0, 255 | (1 << 8))
        kept = [kps[i] for i in order]
        kps, desc = sift.compute(gray, kept + [probe])
        if desc is None or len(kps) != len(kept) + 1:  # OpenCV's SIFT keeps provided keypoints
            raise RuntimeError(f"SIFT compute returned {len(kps)} of {len(kept) + 1} keypoints")
        kps, desc = kps[:-1], desc[:-1]
    rows = np.array([(k.pt[0], k.pt[1], k.size, k.angle) for k in kps], np.float64)
    keypoints = np.column_stack(
        [rows[:, 0], rows[:, 1], rows[:, 2] / 2.0, np.deg2rad(np.mod(rows[:, 3], 360.0))]
    ).astype(np.float32)
    return keypoints, quantize_descriptors(desc, root_sift)
