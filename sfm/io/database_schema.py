"""COLMAP 4's database schema and its vocabulary: tables, id encodings and row records.

What ``sfm.io.database.Database`` reads and writes, independent of any connection:

- :data:`SCHEMA`: the ``CREATE`` statements of a database made by pycolmap 4.2.1, so COLMAP and
  pycolmap open our files and we read theirs.
- Id encodings: :func:`pair_id` (``image_id1 * 2147483647 + image_id2`` with
  ``image_id1 < image_id2``) and its inverse :func:`image_ids_from_pair_id`; camera model ids
  (:data:`CAMERA_MODEL_IDS`, :data:`CAMERA_MODEL_NAMES`); the sensor and descriptor type codes;
  and :class:`TwoViewConfig`, the codes of ``two_view_geometries.config`` (a verified pair has
  config >= 2, CALIBRATED).
- Records rows decode into: :class:`CameraRecord`, :class:`ImageRecord`, :class:`PosePrior` and
  :class:`TwoViewGeometry` (with :meth:`TwoViewGeometry.inverted`, the same geometry seen from
  image 2, as COLMAP inverts it when a pair is stored in the other order).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

MAX_IMAGE_ID = 2147483647
SENSOR_TYPE_CAMERA = 0
DESCRIPTOR_TYPE_SIFT = 0
CAMERA_MODEL_IDS: dict[str, int] = {
    "SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
    "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8,
    "RADIAL_FISHEYE": 9, "THIN_PRISM_FISHEYE": 10, "RAD_TAN_THIN_PRISM_FISHEYE": 11,
    "SIMPLE_DIVISION": 12, "DIVISION": 13, "SIMPLE_FISHEYE": 14, "FISHEYE": 15, "EUCM": 16,
    "EQUIRECTANGULAR": 17,
}  # fmt: skip
CAMERA_MODEL_NAMES: dict[int, str] = {v: k for k, v in CAMERA_MODEL_IDS.items()}
# ``pose_priors.coordinate_system`` (pycolmap's PosePriorCoordinateSystem)
COORDINATES_UNDEFINED, COORDINATES_WGS84, COORDINATES_CARTESIAN = -1, 0, 1


class TwoViewConfig(IntEnum):
    """COLMAP's ``TwoViewGeometry::ConfigurationType`` codes (pycolmap 4.2)."""

    UNDEFINED = 0
    DEGENERATE = 1
    CALIBRATED = 2
    UNCALIBRATED = 3
    PLANAR = 4
    PANORAMIC = 5
    PLANAR_OR_PANORAMIC = 6
    WATERMARK = 7
    MULTIPLE = 8
    CALIBRATED_RIG = 9


# The CREATE statements of a database made by pycolmap 4.2.1 (sqlite_master), reflowed.
SCHEMA = """
CREATE TABLE IF NOT EXISTS rigs (rig_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
  ref_sensor_id INTEGER NOT NULL, ref_sensor_type INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS rig_ref_sensor_assignment ON rigs(ref_sensor_id, ref_sensor_type);
CREATE TABLE IF NOT EXISTS rig_sensors (rig_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL,
  sensor_type INTEGER NOT NULL, sensor_from_rig BLOB,
  FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS rig_sensor_assignment ON rig_sensors(sensor_id, sensor_type);
CREATE TABLE IF NOT EXISTS cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
  model INTEGER NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB,
  prior_focal_length INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS frames (frame_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
  rig_id INTEGER NOT NULL, FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS frame_data (frame_id INTEGER NOT NULL, data_id INTEGER NOT NULL,
  sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL,
  FOREIGN KEY(frame_id) REFERENCES frames(frame_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS frame_sensor_assignment ON frame_data(data_id, sensor_type);
CREATE TABLE IF NOT EXISTS images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
  name TEXT NOT NULL UNIQUE, camera_id INTEGER NOT NULL,
  CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
  FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE UNIQUE INDEX IF NOT EXISTS index_name ON images(name);
CREATE TABLE IF NOT EXISTS pose_priors (pose_prior_id INTEGER PRIMARY KEY NOT NULL,
  corr_data_id INTEGER NOT NULL, corr_sensor_id INTEGER NOT NULL,
  corr_sensor_type INTEGER NOT NULL, position BLOB, position_covariance BLOB, gravity BLOB,
  coordinate_system INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS pose_prior_data_assignment
  ON pose_priors(corr_data_id, corr_sensor_id, corr_sensor_type);
CREATE TABLE IF NOT EXISTS keypoints (image_id INTEGER PRIMARY KEY NOT NULL,
  rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
  FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS descriptors (image_id INTEGER PRIMARY KEY NOT NULL,
  type INTEGER NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
  FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS matches (pair_id INTEGER PRIMARY KEY NOT NULL,
  rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB);
CREATE TABLE IF NOT EXISTS two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL,
  rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL,
  F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB, camera1 BLOB, camera2 BLOB);
"""
GEOMETRY_COLUMNS = "pair_id, rows, data, config, F, E, H, qvec, tvec"


def pair_id(image_id1: int, image_id2: int) -> int:
    """COLMAP's pair id of two images, independent of their order."""
    a, b = sorted((int(image_id1), int(image_id2)))
    return a * MAX_IMAGE_ID + b


def image_ids_from_pair_id(pair_id: int) -> tuple[int, int]:
    """Inverse of :func:`pair_id`: ``(image_id1, image_id2)`` with ``image_id1 < image_id2``."""
    image_id2 = int(pair_id) % MAX_IMAGE_ID
    return (int(pair_id) - image_id2) // MAX_IMAGE_ID, image_id2


@dataclass(frozen=True, eq=False)
class CameraRecord:
    """A ``cameras`` row; ``params`` in COLMAP's order and pixel convention."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray
    prior_focal_length: bool


@dataclass(frozen=True)
class ImageRecord:
    """An ``images`` row; ``name`` is the path relative to the image folder."""

    image_id: int
    name: str
    camera_id: int


@dataclass(frozen=True, eq=False)
class PosePrior:
    """A ``pose_priors`` row of an image: ``position`` (3,) in ``coordinate_system``
    (:data:`COORDINATES_WGS84`: latitude deg, longitude deg, altitude m, as COLMAP stores GPS),
    ``position_covariance`` (3, 3), NaN where unknown."""

    image_id: int
    camera_id: int
    position: np.ndarray
    position_covariance: np.ndarray
    coordinate_system: int = COORDINATES_WGS84


@dataclass(frozen=True, eq=False)
class TwoViewGeometry:
    """COLMAP config code, inlier matches (N, 2) uint32 and the optional models, image 1 -> 2.

    ``x2^T F x1 = 0`` (E likewise on normalised points), ``x2 ~ H x1``, and ``qvec`` (w, x, y, z)
    with ``tvec`` give ``cam2_from_cam1``.
    """

    config: int
    inlier_matches: np.ndarray
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    H: np.ndarray | None = None
    qvec: np.ndarray | None = None
    tvec: np.ndarray | None = None

    @property
    def num_inliers(self) -> int:
        return int(len(self.inlier_matches))

    def inverted(self) -> TwoViewGeometry:
        """The same geometry from image 2 to image 1."""
        qvec = tvec = None
        if self.qvec is not None and self.tvec is not None:
            w, u = float(self.qvec[0]), -np.asarray(self.qvec[1:], np.float64)  # conjugate
            t = np.asarray(self.tvec, np.float64)
            ut = np.cross(u, t)
            qvec, tvec = np.r_[w, u], -(t + 2 * w * ut + 2 * np.cross(u, ut))
        return TwoViewGeometry(
            self.config, np.ascontiguousarray(np.asarray(self.inlier_matches)[:, ::-1]),
            F=None if self.F is None else np.ascontiguousarray(np.transpose(self.F)),
            E=None if self.E is None else np.ascontiguousarray(np.transpose(self.E)),
            H=None if self.H is None else np.linalg.inv(self.H), qvec=qvec, tvec=tvec,
        )  # fmt: skip


# graphsfm's own table, beside COLMAP's: the RGB colour of every keypoint (row k of ``data`` is
# keypoint k's), written in the same transaction as the keypoints.  Made by the first write, so
# a database without colours has exactly COLMAP's tables.
KEYPOINT_COLORS = "graphsfm_keypoint_colors"
KEYPOINT_COLORS_SCHEMA = (f"CREATE TABLE IF NOT EXISTS {KEYPOINT_COLORS} (image_id INTEGER PRIMARY KEY NOT NULL, "
                          "rows INTEGER NOT NULL, data BLOB, "
                          "FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE)")
