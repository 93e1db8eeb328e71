"""GPS: EXIF positions read at extraction into COLMAP 4's pose_priors, spatial pairs, and the
georegistration of final models into a local east-north-up frame in metres."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _helpers_features import FAST, textured, write
from PIL import Image

from backend.geometry import rotation_angle_deg
from sfm.core.geodesy import WGS84_A, WGS84_E2, enu_from_wgs84, wgs84_from_enu
from sfm.execution.local import LocalExecutor
from sfm.features.options import ExtractOptions
from sfm.io.colmap_model import read_model
from sfm.io.database import Database
from sfm.io.image_files import probe_image
from sfm.matching.pairs import select_pairs, spatial_pairs
from sfm.mapper.options import MapperOptions
from sfm.stages.extract import run_extract
from sfm.stages.map import run_map
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import make_scene

ORIGIN = np.array([47.3769, 8.5417, 408.0])  # where the synthetic scenes are put on Earth


def test_enu_round_trip_and_the_length_of_a_degree():
    lat = 55.7
    points = np.array([[lat, 13.19, 35.0], [lat + 1e-3, 13.19, 35.0], [lat, 13.191, 35.0], [lat, 13.19, 135.0]])
    enu = enu_from_wgs84(points, points[0])
    # a meridian's radius of curvature M and the parallel's radius N cos(lat) (WGS84)
    s2 = np.sin(np.radians(lat)) ** 2
    m = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * s2)
    np.testing.assert_allclose(enu[1], [0, np.radians(1e-3) * m, 0], atol=2e-3)
    np.testing.assert_allclose(enu[2], [np.radians(1e-3) * (n + 35) * np.cos(np.radians(lat)), 0, 0], atol=2e-3)
    np.testing.assert_allclose(enu[3], [0, 0, 100], atol=1e-6)
    np.testing.assert_allclose(wgs84_from_enu(enu, points[0]), points, rtol=0, atol=1e-9)


def _gps_exif(lat: float, lon: float, alt: float) -> Image.Exif:
    def dms(x):
        d = int(x)
        m = int((x - d) * 60)
        return (float(d), float(m), round((x - d - m / 60) * 3600, 4))

    exif = Image.Exif()
    exif[0x8825] = {1: "N" if lat >= 0 else "S", 2: dms(abs(lat)), 3: "E" if lon >= 0 else "W", 4: dms(abs(lon)),
                    5: b"\x01" if alt < 0 else b"\x00", 6: abs(alt)}
    return exif


def test_exif_gps_becomes_a_pose_prior_pycolmap_reads(tmp_path):
    write(tmp_path / "img" / "a.jpg", textured(240, 320, 1), exif=_gps_exif(55.698166, 13.195388, 37.0))
    write(tmp_path / "img" / "b.jpg", textured(240, 320, 2), exif=_gps_exif(-33.8568, -151.2153, -4.5))
    write(tmp_path / "img" / "c.jpg", textured(240, 320, 3))
    assert probe_image(tmp_path / "img" / "c.jpg").gps is None
    lat, lon, alt = probe_image(tmp_path / "img" / "b.jpg").gps
    assert (lat, lon, alt) == pytest.approx((-33.8568, -151.2153, -4.5), abs=1e-6)
    run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST))
    with Database(tmp_path / "ws" / "database.db", readonly=True) as db:
        names = {i: r.name for i, r in db.read_images().items()}
        priors = {names[i]: p for i, p in db.read_pose_priors().items()}
    assert sorted(priors) == ["a.jpg", "b.jpg"]
    np.testing.assert_allclose(priors["a.jpg"].position, [55.698166, 13.195388, 37.0], atol=1e-6)
    pycolmap = pytest.importorskip("pycolmap")
    theirs = pycolmap.Database.open(str(tmp_path / "ws" / "database.db"))
    read = {names[p.corr_data_id.id]: p for p in theirs.read_all_pose_priors()}
    theirs.close()
    assert sorted(read) == ["a.jpg", "b.jpg"]
    assert read["b.jpg"].coordinate_system == pycolmap.PosePriorCoordinateSystem.WGS84
    np.testing.assert_allclose(read["b.jpg"].position, priors["b.jpg"].position, rtol=0, atol=0)


def test_spatial_pairs_add_gps_neighbours():
    ids = [1, 2, 3, 4, 5]
    pos = np.array([[0, 0, 0], [1, 0, 0], [50, 0, 0], [52, 0, 0], [np.nan] * 3])
    np.testing.assert_array_equal(spatial_pairs(ids, pos, 1, 100.0), [[1, 2], [3, 4]])
    np.testing.assert_array_equal(spatial_pairs(ids, pos, 3, 10.0), [[1, 2], [3, 4]])  # 10 m at most
    assert len(spatial_pairs(ids, pos, 3, 0.0)) == 6  # any distance: every pair of the four with GPS
    # spatial = retrieval (here every pair: top_k covers all) plus the neighbours
    pairs = select_pairs(ids, "spatial", top_k=10, positions=pos, spatial_neighbors=1, spatial_max_distance=100)
    assert len(pairs) == 10


def _scene_with_gps(tmp_path: Path, scene_name: str, num_images: int, metres_per_unit: float, sigma: float):
    """A synthetic scene whose database carries GPS: the true centres (times metres_per_unit,
    in the ENU frame of ORIGIN) plus Gaussian noise of ``sigma`` metres per axis."""
    opts = SynthOptions(scene=scene_name, num_images=num_images, observations_per_image=600, seed=1)
    scene = make_scene(opts)
    write_database(scene, simulate_matching(scene, opts), tmp_path / "database.db")
    true_enu = scene.centers * metres_per_unit
    noisy = true_enu + np.random.default_rng(5).normal(0, sigma, true_enu.shape)
    with Database(tmp_path / "database.db") as db:
        for i in range(num_images):
            db.write_pose_prior(i + 1, 1, wgs84_from_enu(noisy[i], ORIGIN)[0])
    return scene, wgs84_from_enu(true_enu, ORIGIN)


@pytest.mark.parametrize("scene_name, metres_per_unit, roll_from_upright", [
    ("aerial", 1.0, False),  # a drone grid: the GPS positions fix the whole similarity
    ("street", 5.0, True),  # a walk along a street: the rotation about it comes from upright cameras
])  # fmt: skip
def test_final_model_is_georegistered_within_the_gps_noise(tmp_path, scene_name, metres_per_unit, roll_from_upright):
    sigma = 3.0
    scene, true_lla = _scene_with_gps(tmp_path, scene_name, 20, metres_per_unit, sigma)
    run_map(tmp_path, MapperOptions(), executor=LocalExecutor(1))
    recon = read_model(tmp_path / "sparse" / "0")
    reg = json.loads((tmp_path / "sparse" / "0" / "georegistration.json").read_text())
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["georegistration"] == reg
    assert reg["frame"] == "ENU" and reg["num_inliers"] >= 18 and reg["roll_from_upright_cameras"] == roll_from_upright
    origin = np.array([reg["origin_lat"], reg["origin_lon"], reg["origin_alt"]])
    true_enu = enu_from_wgs84(true_lla, origin)
    est = np.array([recon.image_by_name(n).center for n in scene.names])
    err = np.linalg.norm(est - true_enu, axis=1)
    # each centre within the noise of one GPS fix (3 sigma per axis), typically well inside it
    assert err.max() < 3 * sigma and np.median(err) < sigma
    assert np.abs(est).max() < 200  # small coordinates: metres from the origin
    # orientation: the same world up and north as the truth
    rot_err = [rotation_angle_deg(recon.image_by_name(n).cam_from_world_rotation, scene.rotations[i])
               for i, n in enumerate(scene.names)]
    assert np.median(rot_err) < 3.0


def test_no_georegistration_without_enough_gps(tmp_path):
    _scene_with_gps(tmp_path, "aerial", 12, 1.0, 3.0)
    with Database(tmp_path / "database.db") as db:
        db._conn.execute("DELETE FROM pose_priors WHERE corr_data_id > 2")
        db._conn.commit()
    run_map(tmp_path, MapperOptions(), executor=LocalExecutor(1))
    assert not (tmp_path / "sparse" / "0" / "georegistration.json").exists()
    assert json.loads((tmp_path / "report.json").read_text())["georegistration"] is None


@pytest.mark.slow
def test_opensfm_lund_is_georegistered(shared_data, tmp_path):
    """29 street photos with phone GPS (integer altitudes, DOP 5-10): the model lands in ENU metres,
    its cameras upright, each inlier within the GPS noise of its fix."""
    from sfm.api import reconstruct
    from sfm.evaluation.georegistration import model_centers_and_up
    from sfm.stages.georegister import gps_by_name

    models, report = reconstruct(shared_data / "opensfm_lund" / "images", tmp_path, recording=False, pairs="spatial")
    reg = report["georegistration"]
    assert reg is not None and reg["num_gps_images"] == 29 and reg["num_inliers"] >= 25
    assert reg["rms_error"] < 6.0 and reg["roll_from_upright_cameras"]  # a walk along one street
    gps = gps_by_name(tmp_path / "database.db")
    names = sorted(gps)
    origin = np.array([reg["origin_lat"], reg["origin_lon"], reg["origin_alt"]])
    enu = enu_from_wgs84(np.array([gps[n] for n in names]), origin)
    centers, up = model_centers_and_up(models[0], names)
    err = np.linalg.norm(centers - enu, axis=1)
    assert np.median(err) < 5.0 and np.sum(err < 10.0) >= 25
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
    assert np.median(tilt) < 10.0  # people hold phones upright
