"""SQLite database with COLMAP 4's schema: COLMAP and pycolmap open our files, we read theirs.

Conventions (COLMAP's, so files are interchangeable):

- Tables as COLMAP 4.2 creates them (schema, id codes and row records: ``sfm.io.database_schema``).
  Every camera gets a trivial rig (the camera is its reference sensor,
  sensor type 0 = CAMERA, no ``rig_sensors`` row) and every image a one-image frame of that rig,
  ``frame_data = (frame_id, data_id=image_id, sensor_id=camera_id, sensor_type=0)``: the rows
  ``pycolmap.extract_features`` writes.
- Pair id ``image_id1 * 2147483647 + image_id2`` with ``image_id1 < image_id2``. Callers pass ids
  in any order: matches are stored with swapped columns when ``id1 > id2`` and swapped back when
  read; a two-view geometry is inverted (F, E transposed, H inverted, pose inverted) like COLMAP.
- Blobs: ``cameras.params`` float64 (principal point shifted like keypoints, below, for the
  models graphsfm supports; other models' params pass through unchanged); keypoints float32 rows x 2|4|6 (x, y first);
  descriptors uint8 rows x 128; matches and inlier matches uint32 rows x 2; F, E, H float64 3 x 3
  row-major; ``qvec`` (w, x, y, z) and ``tvec`` float64 of ``cam2_from_cam1``.
- PIXELS: graphsfm keypoints use OpenCV's convention (pixel centres at integers); the database
  holds COLMAP's (image corner at (0, 0)). :meth:`Database.write_keypoints` adds 0.5 to x and y,
  :meth:`Database.read_keypoints` subtracts it; camera principal points likewise
  (``sfm.io.pixel_convention.params_to_colmap``): no other code needs to know.
- One table of graphsfm's own, ``graphsfm_keypoint_colors`` (image id, rows, uint8 RGB rows x 3:
  the colour of each keypoint, written with the keypoints by the extract stage), made only when
  colours are written; COLMAP and pycolmap open the file and ignore it.
- ``two_view_geometries.config`` holds :class:`~sfm.io.database_schema.TwoViewConfig` codes; a verified pair has
  config >= 2 (CALIBRATED) and enough inliers.

While open the file is in WAL mode (synchronous=NORMAL: a killed process never corrupts it and
loses only its uncommitted transaction); :meth:`Database.close` checkpoints and returns to a
rollback journal, so ``database.db`` is then complete on its own.
"""

from __future__ import annotations

import json
import logging
import sqlite3
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from backend.camera_models import CAMERA_MODELS
from sfm.errors import DamagedFileError
from sfm.io.pixel_convention import params_from_colmap, params_to_colmap
from sfm.io.database_schema import (
    CAMERA_MODEL_IDS,
    CAMERA_MODEL_NAMES,
    COORDINATES_WGS84,
    DESCRIPTOR_TYPE_SIFT,
    GEOMETRY_COLUMNS,
    KEYPOINT_COLORS,
    KEYPOINT_COLORS_SCHEMA,
    MAX_IMAGE_ID,
    SCHEMA,
    SENSOR_TYPE_CAMERA,
    CameraRecord,
    ImageRecord,
    PosePrior,
    TwoViewGeometry,
    image_ids_from_pair_id,
    pair_id,
)

logger = logging.getLogger(__name__)


def _params_to_db(model: str, params: Any) -> np.ndarray:
    """Camera params in COLMAP's pixel convention for the models graphsfm knows."""
    p = np.asarray(params, dtype=np.float64)
    if model in CAMERA_MODELS and len(p) == CAMERA_MODELS[model].num_params:
        return params_to_colmap(model, p)
    return p


def _blob(array: Any, dtype: type) -> bytes | None:
    return None if array is None else np.ascontiguousarray(array, dtype=dtype).tobytes()


def _array(blob: bytes | None, dtype: type, shape: tuple[int, ...]) -> np.ndarray | None:
    """A writable array from a blob; None for NULL or empty blobs."""
    if not blob:
        return None
    return np.frombuffer(blob, dtype=dtype).reshape(shape).copy()


def _matches_array(matches: Any) -> np.ndarray:
    m = np.asarray(matches)
    if m.size == 0:
        return np.zeros((0, 2), np.uint32)
    if m.ndim != 2 or m.shape[1] != 2 or m.min() < 0:
        raise ValueError(f"matches must be (N, 2) non-negative indices, got shape {m.shape}")
    return np.ascontiguousarray(m, dtype=np.uint32)


def _decode_matches(rows: int, blob: bytes | None) -> np.ndarray:
    m = _array(blob, np.uint32, (rows, 2)) if rows else None
    return np.zeros((0, 2), np.uint32) if m is None else m


def _decode_keypoints(rows: int, cols: int, blob: bytes | None) -> np.ndarray:
    kp = _array(blob, np.float32, (rows, cols)) if rows else None
    if kp is None:
        return np.zeros((0, 2), np.float32)
    kp[:, :2] -= 0.5  # COLMAP -> OpenCV pixel convention
    return kp


def _decode_geometry(row: tuple) -> TwoViewGeometry:
    _, rows, data, config, F, E, H, qvec, tvec = row
    mat = lambda blob: _array(blob, np.float64, (3, 3))  # noqa: E731
    return TwoViewGeometry(
        int(config), _decode_matches(rows, data), F=mat(F), E=mat(E), H=mat(H),
        qvec=_array(qvec, np.float64, (4,)), tvec=_array(tvec, np.float64, (3,)),
    )  # fmt: skip


def _match_row(image_id1: int, image_id2: int, matches: Any) -> tuple:
    m = _matches_array(matches)
    if image_id1 > image_id2:
        m = np.ascontiguousarray(m[:, ::-1])
    return pair_id(image_id1, image_id2), m.shape[0], 2, m.tobytes()


def _geometry_row(image_id1: int, image_id2: int, geometry: TwoViewGeometry) -> tuple:
    g = geometry.inverted() if image_id1 > image_id2 else geometry
    f64 = np.float64
    return (
        *_match_row(min(image_id1, image_id2), max(image_id1, image_id2), g.inlier_matches),
        int(g.config), _blob(g.F, f64), _blob(g.E, f64), _blob(g.H, f64), _blob(g.qvec, f64),
        _blob(g.tvec, f64),
    )  # fmt: skip


def damaged_database(path: Path, exc: Exception) -> DamagedFileError:
    """The one-line error of a database file SQLite cannot read (``database disk image is
    malformed``, ``file is not a database``)."""
    return DamagedFileError(path, str(exc), f"delete it (and {Path(path).name}-wal, -shm if there) and rerun "
                            "with --images: the features are extracted and matched again")


class Database:
    """A COLMAP-4-compatible database file; a context manager (``close`` on exit)."""

    def __init__(self, path: str | Path, readonly: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        self._depth = 0
        self._conn = None  # type: ignore[assignment]
        try:
            if readonly:
                uri = f"{self.path.resolve().as_uri()}?mode=ro"
                self._conn = sqlite3.connect(uri, uri=True, isolation_level=None, timeout=60.0)
            else:
                self._conn = sqlite3.connect(self.path, isolation_level=None, timeout=60.0)
                self._conn.execute("PRAGMA journal_mode=WAL")
                self._conn.execute("PRAGMA synchronous=NORMAL")
                self._conn.executescript(SCHEMA)
            columns = {r[1] for r in self._conn.execute("PRAGMA table_info(descriptors)")}
        except sqlite3.DatabaseError as exc:
            if self._conn is not None:
                self._conn.close()
            if type(exc) is sqlite3.DatabaseError:  # not locked, not a constraint: the file is damaged
                raise damaged_database(self.path, exc) from exc
            raise
        self._descriptors_have_type = "type" in columns  # False in COLMAP 3.x databases

    def close(self) -> None:
        """Commit, checkpoint the WAL, switch to journal_mode DELETE and close (idempotent)."""
        if self._conn is None:
            return
        try:
            if self._conn.in_transaction:
                self._conn.execute("COMMIT")
            if not self.readonly:
                self._conn.execute("PRAGMA busy_timeout=5000")  # not the 60 s of writes
                self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                self._conn.execute("PRAGMA journal_mode=DELETE")
        except sqlite3.OperationalError as exc:  # another connection still uses the file
            logger.warning("database %s left in WAL mode: %s", self.path, exc)
        finally:
            self._conn.close()
            self._conn = None  # type: ignore[assignment]

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @contextmanager
    def transaction(self) -> Iterator[Database]:
        """``BEGIN IMMEDIATE`` ... ``COMMIT``, ``ROLLBACK`` on exception; nested: no-op level."""
        if self._depth > 0:
            self._depth += 1
            try:
                yield self
            finally:
                self._depth -= 1
            return
        self._conn.execute("BEGIN IMMEDIATE")
        self._depth = 1
        try:
            yield self
        except BaseException:
            self._conn.execute("ROLLBACK")
            raise
        else:
            self._conn.execute("COMMIT")
        finally:
            self._depth = 0

    def _one(self, sql: str, params: tuple = ()) -> tuple | None:
        return self._conn.execute(sql, params).fetchone()

    # ------------------------------------------------------------------ writing
    def add_camera(
        self, model: str, width: int, height: int, params: Any,
        prior_focal_length: bool = False, camera_id: int | None = None,
    ) -> int:  # fmt: skip
        """Insert a camera (params in graphsfm's pixel convention) and its trivial rig; returns
        its id."""
        model_id = CAMERA_MODEL_IDS[model] if isinstance(model, str) else int(model)
        params = _params_to_db(CAMERA_MODEL_NAMES[model_id], params)
        row = (camera_id, model_id, int(width), int(height), _blob(params, np.float64),
               int(bool(prior_focal_length)))  # fmt: skip
        with self.transaction():
            cur = self._conn.execute("INSERT INTO cameras VALUES (?, ?, ?, ?, ?, ?)", row)
            new_id = int(cur.lastrowid if camera_id is None else camera_id)
            self._rig_of_camera(new_id)
        return new_id

    def _rig_of_camera(self, camera_id: int) -> int:
        key = (int(camera_id), SENSOR_TYPE_CAMERA)
        row = self._one("SELECT rig_id FROM rigs WHERE ref_sensor_id=? AND ref_sensor_type=?", key)
        if row is not None:
            return int(row[0])
        sql = "INSERT INTO rigs (ref_sensor_id, ref_sensor_type) VALUES (?, ?)"
        return int(self._conn.execute(sql, key).lastrowid)

    def update_camera(self, camera_id: int, params: Any) -> None:
        """Replace the parameters of an existing camera."""
        row = self._one("SELECT model FROM cameras WHERE camera_id = ?", (int(camera_id),))
        if row is None:
            raise KeyError(f"camera {camera_id} not in the database")
        params = _params_to_db(CAMERA_MODEL_NAMES[int(row[0])], params)
        with self.transaction():
            sql = "UPDATE cameras SET params = ? WHERE camera_id = ?"
            self._conn.execute(sql, (_blob(params, np.float64), int(camera_id)))

    def add_image(self, name: str, camera_id: int, image_id: int | None = None) -> int:
        """Insert an image and its one-image frame; returns the image id."""
        with self.transaction():
            sql = "INSERT INTO images VALUES (?, ?, ?)"
            cur = self._conn.execute(sql, (image_id, str(name), int(camera_id)))
            new_id = int(cur.lastrowid if image_id is None else image_id)
            rig_id = self._rig_of_camera(camera_id)
            cur = self._conn.execute("INSERT INTO frames (rig_id) VALUES (?)", (rig_id,))
            frame = (cur.lastrowid, new_id, int(camera_id), SENSOR_TYPE_CAMERA)
            self._conn.execute("INSERT INTO frame_data VALUES (?, ?, ?, ?)", frame)
        return new_id

    def write_pose_prior(self, image_id: int, camera_id: int, position: Any, covariance: Any = None,
                         coordinate_system: int = COORDINATES_WGS84) -> None:
        """The position prior of an image (COLMAP 4's ``pose_priors`` row, as pycolmap writes
        it: the image's data id, its camera as the sensor, gravity unknown); replaces one there
        was.  ``covariance`` (3, 3) or None (unknown: NaN)."""
        cov = np.full(9, np.nan) if covariance is None else np.asarray(covariance, np.float64).reshape(9)
        row = (int(image_id), int(camera_id), SENSOR_TYPE_CAMERA, _blob(np.asarray(position, np.float64).reshape(3), np.float64),
               _blob(cov, np.float64), _blob(np.full(3, np.nan), np.float64), int(coordinate_system))
        with self.transaction():
            old = self._one("SELECT pose_prior_id FROM pose_priors WHERE corr_data_id=? AND corr_sensor_type=?",
                            (int(image_id), SENSOR_TYPE_CAMERA))
            self._conn.execute("INSERT OR REPLACE INTO pose_priors VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (None if old is None else old[0], *row))

    def read_pose_priors(self) -> dict[int, PosePrior]:
        """Image id -> its position prior (camera sensors only)."""
        out = {}
        sql = ("SELECT corr_data_id, corr_sensor_id, position, position_covariance, coordinate_system "
               "FROM pose_priors WHERE corr_sensor_type = ?")
        for image_id, camera_id, position, cov, system in self._conn.execute(sql, (SENSOR_TYPE_CAMERA,)):
            pos = _array(position, np.float64, (3,))
            cov = _array(cov, np.float64, (3, 3))
            out[int(image_id)] = PosePrior(int(image_id), int(camera_id), np.full(3, np.nan) if pos is None else pos,
                                           np.full((3, 3), np.nan) if cov is None else cov, int(system))
        return out

    def write_keypoints(self, image_id: int, keypoints: Any) -> None:
        """Store (N, 2|4|6) keypoints given in OpenCV's pixel convention (adds 0.5 to x, y)."""
        kp = np.array(keypoints, dtype=np.float32, ndmin=2)
        kp = np.zeros((0, 2), np.float32) if kp.size == 0 else kp
        if kp.ndim != 2 or kp.shape[1] not in (2, 4, 6):
            raise ValueError(f"keypoints must be (N, 2|4|6), got shape {kp.shape}")
        kp[:, :2] += 0.5
        with self.transaction():
            sql = "INSERT OR REPLACE INTO keypoints VALUES (?, ?, ?, ?)"
            self._conn.execute(sql, (int(image_id), *kp.shape, kp.tobytes()))

    def write_descriptors(self, image_id: int, descriptors: Any) -> None:
        """Store (N, 128) uint8 descriptors (type SIFT)."""
        desc = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, 128)
        row: tuple = (int(image_id), *desc.shape, desc.tobytes())
        if self._descriptors_have_type:
            row = (row[0], DESCRIPTOR_TYPE_SIFT, *row[1:])
        with self.transaction():
            sql = f"INSERT OR REPLACE INTO descriptors VALUES ({', '.join('?' * len(row))})"
            self._conn.execute(sql, row)

    def write_keypoint_colors(self, image_id: int, colors: Any) -> None:
        """Store the (N, 3) uint8 RGB colour of each keypoint of an image, row k for keypoint k,
        in graphsfm's own table (:data:`~sfm.io.database_schema.KEYPOINT_COLORS_SCHEMA`, made
        by the first write): COLMAP and pycolmap ignore it."""
        rgb = np.ascontiguousarray(colors, dtype=np.uint8).reshape(-1, 3)
        with self.transaction():
            self._conn.execute(KEYPOINT_COLORS_SCHEMA)
            sql = f"INSERT OR REPLACE INTO {KEYPOINT_COLORS} VALUES (?, ?, ?)"
            self._conn.execute(sql, (int(image_id), len(rgb), rgb.tobytes()))

    def write_matches(self, image_id1: int, image_id2: int, matches: Any) -> None:
        """Store raw matches: (N, 2) feature indices into image 1 and image 2."""
        self.write_matches_many([(image_id1, image_id2, matches)])

    def write_matches_many(self, items: Iterable[tuple[int, int, Any]]) -> None:
        """:meth:`write_matches` for many pairs in one transaction and one executemany."""
        rows = [_match_row(i1, i2, m) for i1, i2, m in items]
        with self.transaction():
            self._conn.executemany("INSERT OR REPLACE INTO matches VALUES (?, ?, ?, ?)", rows)

    def write_two_view_geometry(
        self, image_id1: int, image_id2: int, geometry: TwoViewGeometry
    ) -> None:
        """Store a two-view geometry given from image 1 to image 2."""
        self.write_two_view_geometries_many([(image_id1, image_id2, geometry)])

    def write_two_view_geometries_many(
        self, items: Iterable[tuple[int, int, TwoViewGeometry]]
    ) -> None:
        """:meth:`write_two_view_geometry` for many pairs in one transaction and executemany."""
        rows = [_geometry_row(i1, i2, g) for i1, i2, g in items]
        columns = GEOMETRY_COLUMNS.replace("data", "cols, data")
        marks = ", ".join("?" * 10)
        sql = f"INSERT OR REPLACE INTO two_view_geometries ({columns}) VALUES ({marks})"
        with self.transaction():
            self._conn.executemany(sql, rows)

    # ------------------------------------------------------------------ reading
    def read_cameras(self) -> dict[int, CameraRecord]:
        out = {}
        for cid, model, w, h, params, prior in self._conn.execute("SELECT * FROM cameras"):
            p = _array(params, np.float64, (-1,))
            name = CAMERA_MODEL_NAMES.get(int(model), f"UNKNOWN_{model}")
            p = np.zeros(0) if p is None else p
            if name in CAMERA_MODELS and len(p) == CAMERA_MODELS[name].num_params:
                p = params_from_colmap(name, p)
            out[int(cid)] = CameraRecord(int(cid), name, int(w), int(h), p, bool(prior))
        return out

    def read_images(self) -> dict[int, ImageRecord]:
        rows = self._conn.execute("SELECT image_id, name, camera_id FROM images")
        return {int(i): ImageRecord(int(i), str(n), int(c)) for i, n, c in rows}

    def image_id_by_name(self) -> dict[str, int]:
        return {str(n): int(i) for i, n in self._conn.execute("SELECT image_id, name FROM images")}

    def read_keypoints(self, image_id: int) -> np.ndarray:
        """Keypoints (N, 2|4|6) float32 in OpenCV's pixel convention; (0, 2) when absent."""
        row = self._one("SELECT rows, cols, data FROM keypoints WHERE image_id=?", (int(image_id),))
        return np.zeros((0, 2), np.float32) if row is None else _decode_keypoints(*row)

    def read_all_keypoints(self, image_ids: Iterable[int] | None = None) -> dict[int, np.ndarray]:
        """:meth:`read_keypoints` of the given images (default: all) in one query."""
        sql, params = "SELECT image_id, rows, cols, data FROM keypoints", ()
        if image_ids is not None:
            sql += " WHERE image_id IN (SELECT value FROM json_each(?))"
            params = (json.dumps([int(i) for i in image_ids]),)  # type: ignore[assignment]
        rows = self._conn.execute(sql, params)
        return {int(i): _decode_keypoints(r, c, d) for i, r, c, d in rows}

    def read_keypoint_colors(self, image_ids: Iterable[int] | None = None) -> dict[int, np.ndarray]:
        """The (N, 3) uint8 keypoint colours of the given images (default: all) that have them
        and as many as keypoints; a database graphsfm did not extract has none."""
        exists = "SELECT 1 FROM sqlite_master WHERE type='table' AND name=?"
        if self._one(exists, (KEYPOINT_COLORS,)) is None:
            return {}
        sql = (f"SELECT c.image_id, c.rows, c.data FROM {KEYPOINT_COLORS} c "
               "JOIN keypoints k ON k.image_id = c.image_id AND k.rows = c.rows")
        params: tuple = ()
        if image_ids is not None:
            sql += " WHERE c.image_id IN (SELECT value FROM json_each(?))"
            params = (json.dumps([int(i) for i in image_ids]),)
        rows = self._conn.execute(sql, params)
        return {int(i): np.frombuffer(d or b"", np.uint8).reshape(int(r), 3) for i, r, d in rows}

    def read_descriptors(self, image_id: int) -> np.ndarray:
        """Descriptors (N, D) uint8; (0, 128) when absent."""
        sql = "SELECT rows, cols, data FROM descriptors WHERE image_id=?"
        row = self._one(sql, (int(image_id),))
        desc = _array(row[2], np.uint8, row[:2]) if row is not None and row[0] else None
        return np.zeros((0, 128), np.uint8) if desc is None else desc

    def read_matches(self, image_id1: int, image_id2: int) -> np.ndarray:
        """Raw matches (N, 2) uint32, columns in the caller's image order; (0, 2) when absent."""
        sql = "SELECT rows, data FROM matches WHERE pair_id=?"
        row = self._one(sql, (pair_id(image_id1, image_id2),))
        m = np.zeros((0, 2), np.uint32) if row is None else _decode_matches(*row)
        return np.ascontiguousarray(m[:, ::-1]) if image_id1 > image_id2 else m

    def read_two_view_geometry(self, image_id1: int, image_id2: int) -> TwoViewGeometry | None:
        """The geometry from image 1 to image 2 (in the caller's order), or None."""
        sql = f"SELECT {GEOMETRY_COLUMNS} FROM two_view_geometries WHERE pair_id=?"
        row = self._one(sql, (pair_id(image_id1, image_id2),))
        if row is None:
            return None
        g = _decode_geometry(row)
        return g.inverted() if image_id1 > image_id2 else g

    def read_two_view_geometries(
        self, min_config: int = 2, min_inliers: int = 0, image_ids: Iterable[int] | None = None,
        touching: bool = False,
    ) -> dict[tuple[int, int], TwoViewGeometry]:
        """Geometries with config >= min_config and >= min_inliers, keyed (id1, id2), id1 < id2;
        with ``image_ids``, only the pairs of two of those images (``touching``: of at least one)."""
        sql = f"SELECT {GEOMETRY_COLUMNS} FROM two_view_geometries WHERE config>=? AND rows>=?"
        params: tuple = (int(min_config), int(min_inliers))
        if image_ids is not None:
            ids = json.dumps(sorted(int(i) for i in image_ids))
            sql += (f" AND (pair_id / {MAX_IMAGE_ID} IN (SELECT value FROM json_each(?))"
                    f" {'OR' if touching else 'AND'} pair_id % {MAX_IMAGE_ID} IN (SELECT value FROM json_each(?)))")
            params += (ids, ids)
        rows = self._conn.execute(sql, params)
        return {image_ids_from_pair_id(r[0]): _decode_geometry(r) for r in rows}

    def verified_pairs(self, min_inliers: int = 15) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image_id1, image_id2, num_inliers) int64 arrays of pairs with config >= 2, id1 < id2."""
        sql = "SELECT pair_id, rows FROM two_view_geometries WHERE config>=2 AND rows>=?"
        rows = self._conn.execute(sql + " ORDER BY pair_id", (int(min_inliers),)).fetchall()
        arr = np.array(rows, np.int64).reshape(-1, 2)
        id2 = arr[:, 0] % MAX_IMAGE_ID
        return (arr[:, 0] - id2) // MAX_IMAGE_ID, id2, arr[:, 1].copy()

    def clear_matches(self) -> None:
        """Delete every raw match and two-view geometry (stale after the match options changed)."""
        with self.transaction():
            self._conn.execute("DELETE FROM matches")
            self._conn.execute("DELETE FROM two_view_geometries")

    # ------------------------------------------------------------------ resuming, counts
    def images_with_keypoints(self) -> set[int]:
        return {int(r[0]) for r in self._conn.execute("SELECT image_id FROM keypoints")}

    def pairs_with_matches(self) -> set[tuple[int, int]]:
        rows = self._conn.execute("SELECT pair_id FROM matches")
        return {image_ids_from_pair_id(r[0]) for r in rows}

    def pairs_with_geometry(self) -> set[tuple[int, int]]:
        rows = self._conn.execute("SELECT pair_id FROM two_view_geometries")
        return {image_ids_from_pair_id(r[0]) for r in rows}

    def _scalar(self, sql: str, params: tuple = ()) -> int:
        return int(self._conn.execute(sql, params).fetchone()[0] or 0)

    def num_cameras(self) -> int:
        return self._scalar("SELECT COUNT(*) FROM cameras")

    def num_images(self) -> int:
        return self._scalar("SELECT COUNT(*) FROM images")

    def keypoint_counts(self) -> dict[int, int]:
        """The number of keypoints of each image that has keypoints."""
        return {int(i): int(n) for i, n in self._conn.execute("SELECT image_id, rows FROM keypoints")}

    def num_keypoints(self) -> int:
        """Total number of keypoints over all images."""
        return self._scalar("SELECT SUM(rows) FROM keypoints")

    def num_two_view_geometries(self) -> int:
        """Pairs that went through verification (a row each, verified or not)."""
        return self._scalar("SELECT COUNT(*) FROM two_view_geometries")

    def num_verified_pairs(self, min_inliers: int = 15) -> int:
        sql = "SELECT COUNT(*) FROM two_view_geometries WHERE config>=2 AND rows>=?"
        return self._scalar(sql, (int(min_inliers),))
