"""Tests of sfm.io.database against pycolmap: codes, schema, pycolmap reading and mapping our
database, and us reading a database pycolmap wrote. ``db_path`` is in conftest.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _helpers_database import _quat_wxyz, _raw
from scipy.spatial.transform import Rotation

from sfm.io.database import Database
from sfm.io.database_schema import CAMERA_MODEL_IDS, TwoViewConfig, TwoViewGeometry


def _pycolmap():
    """pycolmap, or skip. zlib (and cv2) are loaded first: loading them after pycolmap 4.2.1 makes
    any later deflate call abort the process (free(): invalid pointer)."""
    import zlib  # noqa: F401

    try:
        import cv2  # noqa: F401
    except ImportError:
        pass
    return pytest.importorskip("pycolmap")


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
