"""Tests of sfm.database: round trips, pair ids, transactions, crash safety, COLMAP interop."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sfm.database import (
    CAMERA_MODEL_IDS,
    CAMERA_MODEL_NAMES,
    MAX_IMAGE_ID,
    Database,
    TwoViewConfig,
    TwoViewGeometry,
    image_ids_from_pair_id,
    pair_id,
)

REPO = Path(__file__).resolve().parents[1]


def _pycolmap():
    """pycolmap, or skip. zlib (and cv2) are loaded first: loading them after pycolmap 4.2.1 makes
    any later deflate call abort the process (free(): invalid pointer)."""
    import zlib  # noqa: F401

    try:
        import cv2  # noqa: F401
    except ImportError:
        pass
    return pytest.importorskip("pycolmap")


def _raw(path: Path, sql: str, params: tuple = ()) -> list[tuple]:
    con = sqlite3.connect(path)
    try:
        return con.execute(sql, params).fetchall()
    finally:
        con.close()


def _quat_wxyz(rotation: Rotation) -> np.ndarray:
    x, y, z, w = rotation.as_quat()
    return np.array([w, x, y, z])


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    return tmp_path / "database.db"


def test_pair_id_order_and_inverse() -> None:
    assert MAX_IMAGE_ID == 2147483647
    assert pair_id(1, 2) == 2147483649
    assert pair_id(2, 1) == 2147483649
    assert pair_id(3, 7) == 3 * 2147483647 + 7
    assert image_ids_from_pair_id(2147483649) == (1, 2)
    assert image_ids_from_pair_id(pair_id(2147483646, 5)) == (5, 2147483646)
    assert image_ids_from_pair_id(pair_id(100000, 99999)) == (99999, 100000)


def test_codes() -> None:
    assert [int(c) for c in TwoViewConfig] == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
    assert TwoViewConfig.CALIBRATED == 2 and TwoViewConfig.UNCALIBRATED == 3
    assert TwoViewConfig.PLANAR_OR_PANORAMIC == 6 and TwoViewConfig.CALIBRATED_RIG == 9
    names = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL")
    assert [CAMERA_MODEL_IDS[m] for m in names] == [0, 1, 2]
    assert CAMERA_MODEL_IDS["OPENCV"] == 4 and CAMERA_MODEL_IDS["FULL_OPENCV"] == 6
    assert CAMERA_MODEL_NAMES[5] == "OPENCV_FISHEYE"


def test_cameras_images_rigs_frames(db_path: Path) -> None:
    with Database(db_path) as db:
        c1 = db.add_camera("SIMPLE_RADIAL", 640, 480, [700.0, 320.0, 240.0, 0.01], True)
        c2 = db.add_camera("PINHOLE", 800, 600, np.array([500, 510, 400, 300]), camera_id=7)
        db.update_camera(c1, [710.5, 321.0, 241.0, -0.02])
        i1 = db.add_image("a/one.jpg", c1)
        i2 = db.add_image("two.jpg", c2, image_id=42)
        i3 = db.add_image("three.jpg", c1)
        assert (c1, c2, i1, i2, i3) == (1, 7, 1, 42, 43)
        cams = db.read_cameras()
        assert sorted(cams) == [1, 7]
        assert (cams[1].model, cams[1].width, cams[1].height, cams[1].prior_focal_length) == (
            "SIMPLE_RADIAL", 640, 480, True)  # fmt: skip
        np.testing.assert_array_equal(cams[1].params, [710.5, 321.0, 241.0, -0.02])
        assert cams[1].params.dtype == np.float64
        assert (cams[7].model, cams[7].prior_focal_length) == ("PINHOLE", False)
        np.testing.assert_array_equal(cams[7].params, [500.0, 510.0, 400.0, 300.0])
        images = db.read_images()
        assert {k: (v.name, v.camera_id) for k, v in images.items()} == {
            1: ("a/one.jpg", 1), 42: ("two.jpg", 7), 43: ("three.jpg", 1)}  # fmt: skip
        assert db.image_id_by_name() == {"a/one.jpg": 1, "two.jpg": 42, "three.jpg": 1 + 42}
        assert (db.num_cameras(), db.num_images()) == (2, 3)
        with pytest.raises(sqlite3.IntegrityError):
            db.add_image("two.jpg", c1)  # names are unique
        assert db.num_images() == 3
    # one rig per camera, one frame per image, as pycolmap.extract_features writes them
    assert _raw(db_path, "SELECT * FROM rigs ORDER BY rig_id") == [(1, 1, 0), (2, 7, 0)]
    assert _raw(db_path, "SELECT * FROM rig_sensors") == []
    assert _raw(db_path, "SELECT * FROM frames ORDER BY frame_id") == [(1, 1), (2, 2), (3, 1)]
    assert _raw(db_path, "SELECT * FROM frame_data ORDER BY frame_id") == [
        (1, 1, 1, 0), (2, 42, 7, 0), (3, 43, 1, 0)]  # fmt: skip


def test_keypoints_descriptors_roundtrip(db_path: Path) -> None:
    kp2 = np.array([[0.0, 0.0], [10.25, 20.5], [639.0, 479.0]], np.float32)
    kp6 = np.array([[1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11, 12]], np.float64)
    desc = (np.arange(3 * 128) % 256).astype(np.uint8).reshape(3, 128)
    with Database(db_path) as db:
        cam = db.add_camera("PINHOLE", 640, 480, [500, 500, 320, 240])
        a, b, c = (db.add_image(n, cam) for n in ("a", "b", "c"))
        db.write_keypoints(a, kp2)
        db.write_keypoints(b, kp6)
        db.write_descriptors(a, desc)
        with pytest.raises(ValueError):
            db.write_keypoints(c, np.zeros((4, 3)))
        np.testing.assert_array_equal(db.read_keypoints(a), kp2)
        out6 = db.read_keypoints(b)
        assert out6.dtype == np.float32 and out6.shape == (2, 6)
        np.testing.assert_array_equal(out6, kp6.astype(np.float32))
        assert db.read_keypoints(c).shape == (0, 2)
        everything = db.read_all_keypoints()
        assert sorted(everything) == [a, b]
        subset = db.read_all_keypoints([b, c])
        assert list(subset) == [b]
        np.testing.assert_array_equal(subset[b], kp6.astype(np.float32))
        np.testing.assert_array_equal(db.read_descriptors(a), desc)
        assert db.read_descriptors(b).shape == (0, 128) and db.read_descriptors(b).dtype == np.uint8
        assert db.images_with_keypoints() == {a, b}
        assert db.num_keypoints() == 5
    # the file holds COLMAP's convention: x, y shifted by +0.5, the shape columns untouched
    sql = "SELECT rows, cols, data FROM keypoints WHERE image_id=?"
    rows, cols, blob = _raw(db_path, sql, (a,))[0]
    assert (rows, cols) == (3, 2)
    np.testing.assert_array_equal(
        np.frombuffer(blob, np.float32).reshape(3, 2), [[0.5, 0.5], [10.75, 21.0], [639.5, 479.5]]
    )
    blob6 = _raw(db_path, "SELECT data FROM keypoints WHERE image_id=?", (b,))[0][0]
    np.testing.assert_array_equal(
        np.frombuffer(blob6, np.float32).reshape(2, 6),
        [[1.5, 2.5, 3, 4, 5, 6], [7.5, 8.5, 9, 10, 11, 12]],
    )
    assert _raw(db_path, "SELECT image_id, type, rows, cols FROM descriptors") == [(a, 0, 3, 128)]


def test_matches_order_and_swapped_columns(db_path: Path) -> None:
    m = np.array([[0, 5], [1, 6], [2, 9]])
    with Database(db_path) as db:
        db.write_matches(5, 2, m)  # caller's order: image 5 first
        np.testing.assert_array_equal(db.read_matches(5, 2), m)
        np.testing.assert_array_equal(db.read_matches(2, 5), m[:, ::-1])
        assert db.read_matches(5, 2).dtype == np.uint32
        assert db.read_matches(1, 2).shape == (0, 2)
        db.write_matches(3, 4, [])
        assert db.read_matches(4, 3).shape == (0, 2)
        assert db.pairs_with_matches() == {(2, 5), (3, 4)}
        with pytest.raises(ValueError):
            db.write_matches(1, 2, [[0, -1]])
    [(pid, rows, cols, blob)] = _raw(db_path, "SELECT * FROM matches WHERE rows > 0")
    assert (pid, rows, cols) == (2 * 2147483647 + 5, 3, 2)
    stored = np.frombuffer(blob, np.uint32).reshape(3, 2)
    np.testing.assert_array_equal(stored, [[5, 0], [6, 1], [9, 2]])


def test_two_view_geometry_roundtrip_and_inversion(db_path: Path) -> None:
    rot = Rotation.from_rotvec([0.1, -0.2, 0.3])
    qvec, tvec = _quat_wxyz(rot), np.array([1.0, -2.0, 0.5])
    F = np.arange(1.0, 10.0).reshape(3, 3)
    E = F * 2 + 1
    H = np.array([[2.0, 0.1, 3.0], [0.0, 1.5, -1.0], [0.001, 0.0, 1.0]])
    inliers = np.array([[10, 20], [11, 21], [12, 22]])
    g = TwoViewGeometry(TwoViewConfig.CALIBRATED, inliers, F=F, E=E, H=H, qvec=qvec, tvec=tvec)
    with Database(db_path) as db:
        db.write_two_view_geometry(8, 3, g)  # stored as pair (3, 8): inverted
        back = db.read_two_view_geometry(8, 3)
        assert back.config == 2 and back.num_inliers == 3
        np.testing.assert_array_equal(back.inlier_matches, inliers)
        for got, want in ((back.F, F), (back.E, E), (back.H, H), (back.tvec, tvec)):
            np.testing.assert_allclose(got, want, atol=1e-12)
        assert abs(abs(np.dot(back.qvec, qvec)) - 1.0) < 1e-12
        inv = db.read_two_view_geometry(3, 8)
        np.testing.assert_array_equal(inv.inlier_matches, inliers[:, ::-1])
        np.testing.assert_allclose(inv.F, F.T, atol=1e-12)
        np.testing.assert_allclose(inv.E, E.T, atol=1e-12)
        np.testing.assert_allclose(inv.H @ H, np.eye(3), atol=1e-12)
        r_inv = Rotation.from_quat([*inv.qvec[1:], inv.qvec[0]]).as_matrix()
        np.testing.assert_allclose(r_inv, rot.as_matrix().T, atol=1e-12)
        np.testing.assert_allclose(inv.tvec, -rot.as_matrix().T @ tvec, atol=1e-12)
        assert db.read_two_view_geometry(1, 2) is None
    row = _raw(db_path, "SELECT pair_id, rows, cols, config, F, qvec FROM two_view_geometries")[0]
    assert row[:4] == (3 * 2147483647 + 8, 3, 2, 2)
    np.testing.assert_allclose(np.frombuffer(row[4]).reshape(3, 3), F.T, atol=1e-12)  # row-major
    assert len(row[5]) == 32


def test_geometry_filters_verified_pairs_and_bulk(db_path: Path) -> None:
    def geom(config: int, n: int) -> TwoViewGeometry:
        return TwoViewGeometry(config, np.stack([np.arange(n), np.arange(n) + 1], 1))

    with Database(db_path) as db:
        db.write_two_view_geometries_many([
            (1, 2, geom(2, 20)), (3, 1, geom(3, 15)), (2, 3, geom(1, 50)),
            (4, 1, geom(4, 14)), (4, 5, geom(0, 0)), (2, 4, geom(6, 30)),
        ])  # fmt: skip
        assert db.pairs_with_geometry() == {(1, 2), (1, 3), (2, 3), (1, 4), (4, 5), (2, 4)}
        i1, i2, n = db.verified_pairs()
        assert (i1.tolist(), i2.tolist(), n.tolist()) == ([1, 1, 2], [2, 3, 4], [20, 15, 30])
        assert db.verified_pairs(min_inliers=0)[2].tolist() == [20, 15, 14, 30]
        assert db.num_verified_pairs() == 3
        assert sorted(db.read_two_view_geometries()) == [(1, 2), (1, 3), (1, 4), (2, 4)]
        assert sorted(db.read_two_view_geometries(min_inliers=16)) == [(1, 2), (2, 4)]
        everything = db.read_two_view_geometries(min_config=0)
        assert len(everything) == 6 and everything[(4, 5)].inlier_matches.shape == (0, 2)
        # (3, 1) was given reversed: stored (1, 3) with swapped columns
        np.testing.assert_array_equal(everything[(1, 3)].inlier_matches[:2], [[1, 0], [2, 1]])
        assert everything[(1, 3)].F is None
        assert everything[(2, 3)].config == TwoViewConfig.DEGENERATE

        # bulk: 20,000 pairs of 30 matches each
        rng = np.random.default_rng(1)
        pairs = [(i, j) for i in range(1, 201) for j in range(i + 1, i + 101)]
        ms = {p: rng.integers(0, 5000, (30, 2)) for p in pairs}
        t0 = time.perf_counter()
        db.write_matches_many((j, i, ms[i, j]) for i, j in pairs)
        db.write_two_view_geometries_many((i, j, TwoViewGeometry(2, ms[i, j])) for i, j in pairs)
        elapsed = time.perf_counter() - t0
        assert len(db.pairs_with_matches()) == 20000
        np.testing.assert_array_equal(db.read_matches(57, 7), ms[7, 57])  # written as (j, i)
        np.testing.assert_array_equal(db.read_matches(7, 57), ms[7, 57][:, ::-1])
        g300 = db.read_two_view_geometry(300, 200)
        np.testing.assert_array_equal(g300.inlier_matches, ms[200, 300][:, ::-1])
        assert len(db.verified_pairs()[0]) == 20000  # the bulk pairs overwrote the six above
        assert len(db.pairs_with_geometry()) == 20000
    assert elapsed < 5.0, f"bulk writes of 2 x 20,000 pairs took {elapsed:.2f} s"


def test_transaction_rollback_and_nesting(db_path: Path) -> None:
    with Database(db_path) as db:
        cam = db.add_camera("PINHOLE", 10, 10, [1, 1, 5, 5])
        with pytest.raises(RuntimeError):
            with db.transaction():
                db.add_camera("PINHOLE", 20, 20, [2, 2, 10, 10])
                img = db.add_image("x.jpg", cam)
                db.write_keypoints(img, [[1.0, 2.0]])
                db.write_matches(1, 2, [[0, 0]])
                raise RuntimeError("boom")
        assert (db.num_cameras(), db.num_images(), db.images_with_keypoints()) == (1, 0, set())
        assert db.pairs_with_matches() == set()
        assert _raw(db_path, "SELECT COUNT(*) FROM frames")[0][0] == 0
        assert _raw(db_path, "SELECT COUNT(*) FROM rigs")[0][0] == 1
        with db.transaction():
            db.add_image("y.jpg", cam)
            with db.transaction():  # inner level: no commit of its own
                db.write_matches(1, 2, [[3, 4]])
            assert _raw(db_path, "SELECT COUNT(*) FROM matches")[0][0] == 0  # not yet visible
        assert _raw(db_path, "SELECT COUNT(*) FROM matches")[0][0] == 1
        with pytest.raises(KeyError):
            with db.transaction():
                db.add_image("z.jpg", cam)
                with db.transaction():
                    raise KeyError("inner failure rolls back the outer level too")
        assert db.image_id_by_name() == {"y.jpg": 1}


_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from sfm.database import Database, TwoViewGeometry
    db = Database(sys.argv[1])
    cam = db.add_camera("SIMPLE_RADIAL", 100, 80, [90.0, 50.0, 40.0, 0.0])
    a, b = db.add_image("a.jpg", cam), db.add_image("b.jpg", cam)
    db.write_keypoints(a, [[1.0, 2.0], [3.0, 4.0]])
    db.write_matches(a, b, [[0, 1]])
    with db.transaction():
        c = db.add_image("c.jpg", cam)
        db.write_keypoints(b, np.ones((1000, 2)))
        db.write_matches_many((i, i + 1, np.ones((50, 2))) for i in range(3, 3000))
        db.write_two_view_geometry(a, b, TwoViewGeometry(2, np.ones((20, 2))))
        print("ready", flush=True)
        time.sleep(120)
    """
)


def test_sigkill_inside_transaction_keeps_committed_data(db_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(db_path)], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert child.stdout.readline().strip() == "ready"
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL
    with Database(db_path) as db:
        assert db._conn.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        assert db.image_id_by_name() == {"a.jpg": 1, "b.jpg": 2}
        assert db.images_with_keypoints() == {1}
        np.testing.assert_array_equal(db.read_keypoints(1), [[1.0, 2.0], [3.0, 4.0]])
        assert db.pairs_with_matches() == {(1, 2)}
        assert db.pairs_with_geometry() == set()
        assert _raw(db_path, "SELECT * FROM frame_data") == [(1, 1, 1, 0), (2, 2, 1, 0)]


def test_close_leaves_a_self_contained_file(db_path: Path) -> None:
    db = Database(db_path)
    assert db._conn.execute("PRAGMA journal_mode").fetchone() == ("wal",)
    cam = db.add_camera("PINHOLE", 64, 48, [50, 50, 32, 24])
    img = db.add_image("only.png", cam)
    db.write_keypoints(img, [[5.0, 6.0]])
    assert Path(str(db_path) + "-wal").exists()
    db.close()
    db.close()  # idempotent
    assert not Path(str(db_path) + "-wal").exists()
    con = sqlite3.connect(db_path)
    assert con.execute("PRAGMA journal_mode").fetchone() == ("delete",)
    assert con.execute("SELECT name, camera_id FROM images").fetchall() == [("only.png", 1)]
    blob = con.execute("SELECT data FROM keypoints").fetchone()[0]
    np.testing.assert_array_equal(np.frombuffer(blob, np.float32), [5.5, 6.5])
    con.close()
    with Database(db_path, readonly=True) as ro:
        assert ro.image_id_by_name() == {"only.png": 1}
        with pytest.raises(sqlite3.OperationalError):
            ro.add_camera("PINHOLE", 1, 1, [1, 1, 0, 0])


def test_colmap3_descriptor_table_without_type(db_path: Path) -> None:
    con = sqlite3.connect(db_path)
    con.execute(
        "CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, "
        "cols INTEGER NOT NULL, data BLOB)"
    )
    con.close()
    with Database(db_path) as db:
        db.write_descriptors(4, np.full((2, 128), 9, np.uint8))
        np.testing.assert_array_equal(db.read_descriptors(4), np.full((2, 128), 9, np.uint8))


# ---------------------------------------------------------------------------- pycolmap


def test_codes_match_pycolmap() -> None:
    pycolmap = _pycolmap()
    configs = {k: int(v) for k, v in pycolmap.TwoViewGeometryConfiguration.__members__.items()}
    assert configs == {c.name: int(c) for c in TwoViewConfig}
    models = {k: int(v) for k, v in pycolmap.CameraModelId.__members__.items() if int(v) >= 0}
    assert models == CAMERA_MODEL_IDS


def test_schema_matches_pycolmap(tmp_path: Path) -> None:
    pycolmap = _pycolmap()
    pycolmap.Database.open(tmp_path / "theirs.db").close()
    Database(tmp_path / "ours.db").close()

    def columns(path: Path) -> dict[str, list[tuple]]:
        tables = [r[0] for r in _raw(path, "SELECT name FROM sqlite_master WHERE type='table'")]
        return {t: _raw(path, f"PRAGMA table_info({t})") for t in tables}

    def indexes(path: Path) -> set[tuple]:
        rows = _raw(path, "SELECT name, tbl_name FROM sqlite_master WHERE type='index'")
        return {(n, t, tuple(r[2] for r in _raw(path, f"PRAGMA index_info({n})"))) for n, t in rows}

    assert columns(tmp_path / "ours.db") == columns(tmp_path / "theirs.db")
    assert indexes(tmp_path / "ours.db") == indexes(tmp_path / "theirs.db")


def _synthetic_scene(db: Database, n_images: int = 6, n_points: int = 300) -> None:
    """A PINHOLE camera translating in front of random points; every pair fully matched."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (n_points, 3)) + [0.0, 0.0, 6.0]
    cam = db.add_camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0], prior_focal_length=True)
    index_of_point = []
    for i in range(n_images):
        x_cam = points - [0.4 * i - 1.0, 0.1 * i, 0.0]
        uv = 500.0 * x_cam[:, :2] / x_cam[:, 2:] + [319.5, 239.5]  # OpenCV: centre 0.5 less
        perm = rng.permutation(n_points)
        image_id = db.add_image(f"im{i}.jpg", cam)
        db.write_keypoints(image_id, uv[perm] + rng.normal(0, 0.3, uv.shape))
        index_of_point.append(np.argsort(perm))
    items = []
    for a in range(n_images):
        for b in range(a + 1, n_images):
            items.append((b + 1, a + 1, np.stack([index_of_point[b], index_of_point[a]], 1)))
    db.write_matches_many(items)
    db.write_two_view_geometries_many([(i, j, TwoViewGeometry(2, m)) for i, j, m in items])


def test_pycolmap_reads_our_database(db_path: Path, tmp_path: Path) -> None:
    pycolmap = _pycolmap()
    rot = Rotation.from_rotvec([0.0, 0.3, 0.0])
    F = np.arange(1.0, 10.0).reshape(3, 3)
    kp = np.array([[0.0, 0.0, 2.0, 0.0, 0.0, 2.0], [99.0, 79.0, 1.0, 0.5, -0.5, 1.0]])
    with Database(db_path) as db:
        c1 = db.add_camera("SIMPLE_RADIAL", 100, 80, [90.0, 50.0, 40.0, 0.01])
        c2 = db.add_camera("OPENCV", 200, 100, [1, 2, 3, 4, 5, 6, 7, 8], True)
        a, b = db.add_image("a.jpg", c1), db.add_image("b.jpg", c2)
        db.write_keypoints(a, kp)
        db.write_keypoints(b, kp[:, :2])
        db.write_descriptors(a, np.full((2, 128), 3, np.uint8))
        db.write_matches(b, a, [[0, 1], [1, 0], [1, 1]])
        g = TwoViewGeometry(TwoViewConfig.UNCALIBRATED, np.array([[1, 0]]), F=F,
                            qvec=_quat_wxyz(rot), tvec=np.array([1.0, 0.0, 0.0]))  # fmt: skip
        db.write_two_view_geometry(b, a, g)
    with pycolmap.Database.open(db_path) as theirs:
        cams = {c.camera_id: c for c in theirs.read_all_cameras()}
        assert (cams[1].model.name, cams[1].width, cams[1].height) == ("SIMPLE_RADIAL", 100, 80)
        # COLMAP's principal point is ours + 0.5 (image corner at 0,0).
        np.testing.assert_array_equal(cams[1].params, [90.0, 50.5, 40.5, 0.01])
        np.testing.assert_array_equal(cams[2].params, [1, 2, 3.5, 4.5, 5, 6, 7, 8])
        assert (cams[2].model.name, bool(cams[2].has_prior_focal_length)) == ("OPENCV", True)
        assert {i.image_id: (i.name, i.camera_id) for i in theirs.read_all_images()} == {
            1: ("a.jpg", 1), 2: ("b.jpg", 2)}  # fmt: skip
        assert [(r.rig_id, r.ref_sensor_id.id) for r in theirs.read_all_rigs()] == [(1, 1), (2, 2)]
        assert [f.rig_id for f in theirs.read_all_frames()] == [1, 2]
        expected = kp.astype(np.float32)
        expected[:, :2] += 0.5
        np.testing.assert_array_equal(theirs.read_keypoints(1), expected)
        np.testing.assert_array_equal(theirs.read_keypoints(2), expected[:, :2])
        np.testing.assert_array_equal(theirs.read_descriptors(1).data, np.full((2, 128), 3))
        np.testing.assert_array_equal(theirs.read_matches(2, 1), [[0, 1], [1, 0], [1, 1]])
        np.testing.assert_array_equal(theirs.read_matches(1, 2), [[1, 0], [0, 1], [1, 1]])
        tv = theirs.read_two_view_geometry(2, 1)
        assert int(tv.config) == 3
        np.testing.assert_array_equal(tv.inlier_matches, [[1, 0]])
        np.testing.assert_allclose(tv.F, F, atol=1e-12)
        np.testing.assert_allclose(tv.cam2_from_cam1.rotation.matrix(), rot.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(tv.cam2_from_cam1.translation, [1.0, 0.0, 0.0], atol=1e-12)
        tv12 = theirs.read_two_view_geometry(1, 2)
        np.testing.assert_array_equal(tv12.inlier_matches, [[0, 1]])
        np.testing.assert_allclose(tv12.F, F.T, atol=1e-12)
        assert theirs.num_verified_image_pairs() == 1


def test_pycolmap_maps_our_database(db_path: Path, tmp_path: Path) -> None:
    pycolmap = _pycolmap()
    with Database(db_path) as db:
        _synthetic_scene(db)
        ours = db.read_all_keypoints()
    (tmp_path / "images").mkdir()
    (tmp_path / "sparse").mkdir()
    recs = pycolmap.incremental_mapping(db_path, tmp_path / "images", tmp_path / "sparse")
    assert len(recs) == 1
    rec = recs[0]
    assert (rec.num_reg_images(), rec.num_points3D()) == (6, 300)
    for image in rec.images.values():
        xy = np.array([p.xy for p in image.points2D])
        np.testing.assert_allclose(xy, ours[image.image_id][:, :2] + 0.5, atol=1e-4)
    np.testing.assert_allclose(rec.cameras[1].params, [500.0, 500.0, 320.0, 240.0], atol=5.0)


def test_we_read_a_pycolmap_database(db_path: Path) -> None:
    pycolmap = _pycolmap()
    H = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 10.0]])
    F = np.array([[0.0, -1e-4, 0.02], [1e-4, 0.0, -0.03], [-0.02, 0.03, 1.0]])
    rot = Rotation.from_rotvec([0.05, 0.1, -0.2])
    with pycolmap.Database.open(db_path) as theirs:
        cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 800.0, 1024, 768)
        cam.params = [800.0, 512.0, 384.0, -0.05]
        cam_id = theirs.write_camera(cam)
        names = ("p/1.jpg", "p/2.jpg", "p/3.jpg")
        ids = [theirs.write_image(pycolmap.Image(name=n, camera_id=cam_id)) for n in names]
        kp6 = np.array([[10.5, 20.5, 1, 0, 0, 1], [0.5, 0.5, 2, 0, 0, 2]], np.float32)
        theirs.write_keypoints(ids[0], kp6)
        theirs.write_keypoints(ids[1], np.array([[3.0, 4.0]], np.float32))
        sift = pycolmap.FeatureExtractorType.SIFT
        desc = pycolmap.FeatureDescriptors(sift, np.full((2, 128), 7, np.uint8))
        theirs.write_descriptors(ids[0], desc)
        theirs.write_matches(ids[1], ids[0], np.array([[0, 1]], np.uint32))
        tv = pycolmap.TwoViewGeometry()
        tv.config = pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC
        tv.inlier_matches = np.array([[1, 0]], np.uint32)
        tv.H = H
        theirs.write_two_view_geometry(ids[0], ids[1], tv)
        tv = pycolmap.TwoViewGeometry()
        tv.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        tv.inlier_matches = np.array([[0, 0], [1, 0]], np.uint32)
        tv.F = F
        xyzw = rot.as_quat()
        tv.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(xyzw), np.array([0.0, 1.0, 0.0]))
        theirs.write_two_view_geometry(ids[2], ids[0], tv)
    with Database(db_path, readonly=True) as db:
        [rec] = db.read_cameras().values()
        assert (rec.camera_id, rec.model, rec.width, rec.height) == (1, "SIMPLE_RADIAL", 1024, 768)
        np.testing.assert_array_equal(rec.params, [800.0, 511.5, 383.5, -0.05])  # corner -> centre
        assert db.image_id_by_name() == {"p/1.jpg": 1, "p/2.jpg": 2, "p/3.jpg": 3}
        expected = kp6.copy()
        expected[:, :2] -= 0.5
        np.testing.assert_array_equal(db.read_keypoints(1), expected)
        np.testing.assert_array_equal(db.read_keypoints(2), [[2.5, 3.5]])
        np.testing.assert_array_equal(db.read_descriptors(1), np.full((2, 128), 7))
        assert db.read_descriptors(2).shape == (0, 128)
        np.testing.assert_array_equal(db.read_matches(2, 1), [[0, 1]])
        np.testing.assert_array_equal(db.read_matches(1, 2), [[1, 0]])
        planar = db.read_two_view_geometry(1, 2)
        assert planar.config == TwoViewConfig.PLANAR_OR_PANORAMIC
        assert planar.F is None and planar.E is None and planar.qvec is None
        np.testing.assert_array_equal(planar.inlier_matches, [[1, 0]])
        np.testing.assert_allclose(planar.H, H, atol=1e-12)
        calibrated = db.read_two_view_geometry(3, 1)
        assert calibrated.config == TwoViewConfig.CALIBRATED
        np.testing.assert_array_equal(calibrated.inlier_matches, [[0, 0], [1, 0]])
        np.testing.assert_allclose(calibrated.F, F, atol=1e-12)
        assert abs(abs(np.dot(calibrated.qvec, _quat_wxyz(rot))) - 1.0) < 1e-12
        np.testing.assert_allclose(calibrated.tvec, [0.0, 1.0, 0.0], atol=1e-12)
        i1, i2, n = db.verified_pairs(min_inliers=0)
        assert (i1.tolist(), i2.tolist(), n.tolist()) == ([1, 1], [2, 3], [1, 2])
