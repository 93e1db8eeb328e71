"""Ground-truth camera poses for evaluation: the GT table format and GT taken from a model.

A GT pose (:class:`GTPose`) is one image's size, pinhole ``K`` and ``cam_from_world`` pose
(``x_cam = R @ X + t``, COLMAP's images.txt convention; the centre is ``C = -R.T @ t``).
Intrinsics use OpenCV's pixel convention (pixel centres at integers).  Poses are keyed by image
name, the file name relative to the image folder, which is how :func:`sfm.evaluation.metrics.evaluate`
matches them to a reconstruction.

Two sources:

* :func:`read_gt_table`: a text table, one image a line,
  ``IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ`` (:data:`GT_TABLE_COLUMNS`).
* :func:`gt_from_reconstruction`: the registered images of a reconstruction (e.g. a COLMAP
  model used as reference).
* :func:`read_projection_matrices`: one 3x4 projection matrix ``P = K [R | t]`` per image, as
  photogrammetry and multi-view datasets ship their cameras (Oxford VGG, Strecha, Olsson's
  Lund sets), split into ``K``, ``R`` and ``t`` by the RQ decomposition.

The library does no printing; it logs through ``logging.getLogger(__name__)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from backend.geometry import quaternion_to_rotation
from sfm.core.model import Reconstruction

logger = logging.getLogger(__name__)

GT_TABLE_COLUMNS = "IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ"


@dataclass(frozen=True, eq=False)
class GTPose:
    """Ground truth of one image: size, pinhole ``K`` (OpenCV pixels) and ``cam_from_world``.

    ``rotation`` (3x3) and ``translation`` (3,) map world points into the camera:
    ``x_cam = rotation @ X + translation``.  Arrays are stored read-only.
    """

    name: str
    width: int
    height: int
    K: np.ndarray  # noqa: N815 - the usual name
    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        for attr, shape in (("K", (3, 3)), ("rotation", (3, 3)), ("translation", (3,))):
            value = np.array(getattr(self, attr), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(
                    f"GTPose {self.name}: {attr} must have shape {shape}, got {value.shape}"
                )
            value.setflags(write=False)
            object.__setattr__(self, attr, value)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R.T @ t``."""
        return -self.rotation.T @ self.translation


def read_gt_table(path: str | Path) -> dict[str, GTPose]:
    """Read a GT table of lines ``IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ``.

    The pose is ``cam_from_world`` (``x_cam = R X + t``) with the quaternion ``(QW, QX, QY, QZ)``
    w-first as in COLMAP (normalised here); ``CX, CY`` use OpenCV's pixel convention.  Lines
    starting with ``#`` and blank lines are skipped.  Names may contain ``/`` but no whitespace.
    A malformed line (wrong column count, non-numeric or non-finite values, non-positive size or
    focal length, zero quaternion) or a repeated name raises ``ValueError`` naming file and line.
    """
    path = Path(path)
    poses: dict[str, GTPose] = {}
    with open(path, encoding="utf-8") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            where = f"{path}:{lineno}"
            tokens = line.split()
            if len(tokens) != 14:
                raise ValueError(
                    f"{where}: expected 14 columns ({GT_TABLE_COLUMNS}), got {len(tokens)}"
                )
            name = tokens[0]
            try:
                values = np.array([float(v) for v in tokens[1:]])
            except ValueError as exc:
                raise ValueError(
                    f"{where}: non-numeric value ({exc}); columns are {GT_TABLE_COLUMNS}"
                ) from None
            if not np.all(np.isfinite(values)):
                raise ValueError(f"{where}: non-finite value in {line!r}")
            width, height, fx, fy, cx, cy = values[:6]
            qvec, tvec = values[6:10], values[10:13]
            if width != int(width) or height != int(height) or width <= 0 or height <= 0:
                raise ValueError(
                    f"{where}: WIDTH and HEIGHT must be positive integers, "
                    f"got {tokens[1]} {tokens[2]}"
                )
            if fx <= 0 or fy <= 0:
                raise ValueError(
                    f"{where}: FX and FY must be positive, got {tokens[3]} {tokens[4]}"
                )
            if np.linalg.norm(qvec) < 1e-12:
                raise ValueError(f"{where}: zero quaternion")
            if name in poses:
                raise ValueError(f"{where}: image {name!r} appears twice")
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])  # noqa: N806
            rotation = quaternion_to_rotation(qvec)
            poses[name] = GTPose(name, int(width), int(height), K, rotation, tvec)
    logger.debug("read %d GT poses from %s", len(poses), path)
    return poses


def gt_from_reconstruction(recon: Reconstruction) -> dict[str, GTPose]:
    """The registered images of a reconstruction (e.g. a COLMAP model) as GT poses by name.

    ``K`` is the camera's pinhole matrix (distortion ignored).  Raises ``ValueError`` when two
    registered images share a name.
    """
    poses: dict[str, GTPose] = {}
    for image_id in recon.registered_image_ids:
        image = recon.images[image_id]
        if image.name in poses:
            raise ValueError(f"two registered images are named {image.name!r}")
        camera = recon.cameras[image.camera_id]
        poses[image.name] = GTPose(
            image.name, camera.width, camera.height, camera.K,
            image.cam_from_world_rotation, image.cam_from_world_translation,
        )
    return poses


def read_projection_matrices(path: str | Path, sizes: dict[str, tuple[int, int]]) -> dict[str, GTPose]:
    """Read GT poses from projection matrices: blocks of a line with the image name, then the 3
    rows of its ``P`` (4 numbers each), in pixels, ``x ~ P X``; ``#`` lines and blank lines are
    skipped.  ``sizes``: each image's (width, height), which ``P`` does not hold; images without
    a size are left out.  ``P = s K [R | t]`` is split by the RQ decomposition of its left 3x3
    block, with ``K``'s diagonal made positive and ``R`` a rotation (the sign of ``s`` taken
    out), and ``K`` scaled to ``K[2, 2] = 1``."""
    from scipy.linalg import rq

    path = Path(path)
    tokens = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#")]
    poses: dict[str, GTPose] = {}
    for k in range(0, len(tokens), 4):
        block = tokens[k:k + 4]
        if len(block) != 4 or len(block[0]) != 1 or any(len(row) != 4 for row in block[1:]):
            raise ValueError(f"{path}: expected an image name and 3 rows of 4 numbers at block {k // 4 + 1}")
        name = block[0][0]
        P = np.array([[float(v) for v in row] for row in block[1:]])  # noqa: N806
        K, R = rq(P[:, :3])  # noqa: N806
        signs = np.diag(np.sign(np.diag(K)))
        K, R = K @ signs, signs @ R  # noqa: N806 - signs is its own inverse
        t = np.linalg.solve(K, P[:, 3])
        if np.linalg.det(R) < 0:  # P was given up to a negative scale
            R, t = -R, -t  # noqa: N806
        if name in sizes:
            width, height = sizes[name]
            poses[name] = GTPose(name, width, height, K / K[2, 2], R, t)
    logger.debug("read %d GT poses from %s", len(poses), path)
    return poses
