"""Tests of sfm.io.database: round trips, pair ids, transactions, crash safety, the COLMAP 3 descriptor
table. Interop with pycolmap is in test_database_pycolmap.py; ``db_path`` is in conftest.py."""

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
from _helpers_database import _quat_wxyz, _raw
from scipy.spatial.transform import Rotation

from sfm.io.database import Database
from sfm.io.database_schema import CAMERA_MODEL_IDS, CAMERA_MODEL_NAMES, MAX_IMAGE_ID, TwoViewConfig, TwoViewGeometry, image_ids_from_pair_id, pair_id

REPO = Path(__file__).resolve().parents[1]


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
        # only the pairs of two of the given images (a cluster's payload)
        assert sorted(db.read_two_view_geometries(image_ids=[4, 2, 1])) == [(1, 2), (1, 4), (2, 4)]
        assert sorted(db.read_two_view_geometries(image_ids=[3, 1])) == [(1, 3)]
        assert sorted(db.read_two_view_geometries(min_config=0, image_ids=[5, 4, 3])) == [(4, 5)]
        assert db.read_two_view_geometries(image_ids=[]) == {}

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
    from sfm.io.database import Database
    from sfm.io.database_schema import TwoViewGeometry
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

