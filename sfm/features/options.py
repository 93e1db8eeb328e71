"""Options of the ``extract`` stage: SIFT, image size and which camera each image gets."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sfm.core.options import Options, option
from sfm.features.cameras import CAMERA_MODEL_NAMES, CAMERA_MODES, DEFAULT_CAMERA_MODEL


@dataclass(frozen=True)
class ExtractOptions(Options):
    """Options of the ``extract`` stage (``graphsfm extract``)."""

    max_image_size: int = option(
        3200, "Images whose longer side is larger are shrunk to it before SIFT; keypoints stay in "
        "full-resolution pixels.", min=16)
    max_num_features: int = option(
        8192, "Keypoint locations kept per image, each with up to two orientations (COLMAP's meaning).", min=1)
    keep_features: str = option(
        "largest_scale", "Which locations max_num_features keeps: the largest-scale ones (COLMAP's rule) "
        "or those of strongest SIFT response.", choices=("largest_scale", "strongest"))
    camera_mode: str = option(
        "auto", "Which images share a camera: auto (same size, EXIF make, model and focal), one for all "
        "images, one per sub-folder, or one per image.", choices=CAMERA_MODES)
    camera_model: str = option(
        DEFAULT_CAMERA_MODEL, "COLMAP camera model of cameras whose intrinsics are not given, refined by bundle "
        "adjustment: OPENCV (fx, fy, cx, cy, k1, k2, p1, p2) holds wide-angle and phone lenses.",
        choices=CAMERA_MODEL_NAMES)
    intrinsics: Path | None = option(
        None, "File of 'NAME WIDTH HEIGHT FX FY CX CY' lines ('*' for every image, OpenCV pixel centres): "
        "those images get PINHOLE cameras with these values, held fixed unless refine_given_intrinsics.")
    masks: Path | None = option(
        None, "Folder of masks in COLMAP's convention, MASKS/<image name>.png: no keypoint is kept where a mask is "
        "zero; an image without a mask is used whole.")
    root_sift: bool = option(
        True, "RootSIFT descriptors (L1-normalised, square-rooted, as COLMAP); off: L2-normalised SIFT.")
    contrast_threshold: float = option(
        0.02, "OpenCV SIFT's contrastThreshold; 0.02 is COLMAP's default peak threshold in the same units.",
        above=0)
    edge_threshold: float = option(
        10.0, "OpenCV SIFT's edgeThreshold, the limit on a peak's edge response (COLMAP's is 10 too).", above=0)
