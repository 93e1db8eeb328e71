"""Data model, geometry helpers and camera models against exact answers."""

from __future__ import annotations

import numpy as np
import pytest

from backend.camera_models import has_bogus_params, project, unproject
from backend.geometry import (
    look_at,
    quaternion_to_rotation,
    rotation_about_axis,
    rotation_angle_deg,
    rotation_from_rotvec,
    rotation_to_quaternion,
)
from backend.sim3 import Sim3, umeyama
from sfm.core.model import INVALID_POINT3D, Camera, Image, Reconstruction
from sfm.io.pixel_convention import params_from_colmap, params_to_colmap


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return rotation_about_axis(rng.normal(size=3), rng.uniform(0, 180))


def test_quaternion_round_trip_all_angles():
    rng = np.random.default_rng(0)
    for angle in [0.0, 1e-7, 30.0, 90.0, 179.9, 180.0]:
        r = rotation_about_axis(rng.normal(size=3), angle)
        q = rotation_to_quaternion(r)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quaternion_to_rotation(q), r, atol=1e-12)
        assert abs(rotation_angle_deg(r) - angle) < 1e-5


def test_rotation_from_rotvec_matches_scipy_and_is_first_order_near_zero():
    from scipy.spatial.transform import Rotation

    for w in np.random.default_rng(6).normal(size=(20, 3)):
        assert np.allclose(rotation_from_rotvec(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    tiny = np.array([1e-14, -2e-14, 3e-14])
    assert np.allclose(rotation_from_rotvec(tiny), Rotation.from_rotvec(tiny).as_matrix(), atol=1e-20)


def test_look_at_opencv_axes():
    r, t = look_at(np.array([0.0, 10.0, 0.0]), np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    # The target is straight ahead (+z), world up appears as image up (-y), world -x is right.
    np.testing.assert_allclose(r @ np.zeros(3) + t, [0, 0, 10], atol=1e-12)
    np.testing.assert_allclose(r @ np.array([0, 0, 1.0]), [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(r @ np.array([-1.0, 0, 0]), [1, 0, 0], atol=1e-12)
    assert abs(np.linalg.det(r) - 1) < 1e-12


def test_sim3_inverse_compose_and_umeyama():
    rng = np.random.default_rng(1)
    sim = Sim3(2.5, random_rotation(rng), rng.normal(size=3))
    pts = rng.normal(size=(20, 3))
    np.testing.assert_allclose(sim.inverse().apply(sim.apply(pts)), pts, atol=1e-12)
    other = Sim3(0.3, random_rotation(rng), rng.normal(size=3))
    np.testing.assert_allclose(sim.compose(other).apply(pts), sim.apply(other.apply(pts)), atol=1e-12)
    est = umeyama(pts, sim.apply(pts))
    assert abs(est.scale - 2.5) < 1e-12
    np.testing.assert_allclose(est.rotation, sim.rotation, atol=1e-12)
    np.testing.assert_allclose(est.translation, sim.translation, atol=1e-12)


@pytest.mark.parametrize(
    "model,params",
    [
        ("SIMPLE_PINHOLE", [500.0, 320.0, 240.0]),
        ("PINHOLE", [500.0, 520.0, 319.5, 239.5]),
        ("SIMPLE_RADIAL", [500.0, 320.0, 240.0, -0.05]),
        ("RADIAL", [500.0, 320.0, 240.0, -0.05, 0.01]),
        ("OPENCV", [500.0, 510.0, 320.0, 240.0, -0.05, 0.01, 0.001, -0.002]),
    ],
)
def test_project_unproject_inverse(model, params):
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 5, 50)])
    px = project(model, np.array(params), pts)
    normalised = unproject(model, np.array(params), px)
    np.testing.assert_allclose(normalised, pts[:, :2] / pts[:, 2:], atol=1e-9)
    shifted = params_to_colmap(model, np.array(params))
    assert np.count_nonzero(shifted - np.array(params)) == 2
    np.testing.assert_allclose(params_from_colmap(model, shifted), params)


def test_project_behind_camera_is_nan():
    px = project("PINHOLE", np.array([100.0, 100, 50, 50]), np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert np.isnan(px[0]).all() and np.allclose(px[1], [50, 50])


def make_small_reconstruction(rng: np.random.Generator) -> tuple[Reconstruction, np.ndarray]:
    recon = Reconstruction()
    recon.add_camera(Camera(1, "PINHOLE", 640, 480, [500.0, 500.0, 319.5, 239.5]))
    points = rng.uniform(-1, 1, (30, 3))
    cam = recon.cameras[1]
    for i in range(4):
        r, t = look_at(np.array([6 * np.cos(i), 6 * np.sin(i), 1.0]), np.zeros(3), np.array([0, 0, 1.0]))
        kps = project(cam.model, cam.params, points @ r.T + t)
        recon.add_image(Image(i + 1, f"im{i}.png", 1, r, t, kps))
    for p, xyz in enumerate(points):
        recon.add_point3D(xyz, [(i + 1, p) for i in range(4)])
    return recon, points


def test_reconstruction_consistency_and_errors():
    rng = np.random.default_rng(3)
    recon, _ = make_small_reconstruction(rng)
    assert len(recon.points3D) == 30 and recon.num_observations == 120
    assert recon.mean_track_length == 4.0
    assert recon.mean_reprojection_error() < 1e-9
    pid = next(iter(recon.points3D))
    recon.points3D[pid].xyz = recon.points3D[pid].xyz + np.array([0.0, 0.0, 0.0])
    image = recon.images[1]
    image.keypoints[0] += np.array([3.0, 4.0])  # this observation is now 5 px off
    mean = recon.update_point_errors()
    pid0 = int(image.point3D_ids[0])
    assert abs(recon.points3D[pid0].error - 5.0 / 4) < 1e-9
    assert abs(mean - 5.0 / 120) < 1e-9
    # Removing observations keeps both tables consistent and drops short tracks.
    recon.remove_observation(1, 0)
    recon.remove_observation(2, 0)
    recon.remove_observation(3, 0)
    assert pid0 not in recon.points3D
    assert all(im.point3D_ids[0] == INVALID_POINT3D for im in recon.images.values())
    recon.remove_image(4)
    assert 4 not in recon.images
    assert all(len(p.track) == 3 for p in recon.points3D.values())
    pids, iids, kps = recon.observations()
    for pid, iid, kp in zip(pids, iids, kps):
        assert (int(iid), int(kp)) in recon.points3D[int(pid)].track


def test_reprojection_errors_name_a_point_missing_from_the_model():
    rng = np.random.default_rng(5)
    recon, _ = make_small_reconstruction(rng)
    pids, err = recon.reprojection_errors()
    assert len(pids) == recon.num_observations and np.all(err < 1e-9)
    image = recon.images[2]
    image.point3D_ids[np.flatnonzero(image.point3D_ids != INVALID_POINT3D)[0]] = 10_000  # no such point
    with pytest.raises(KeyError, match="observes point 10000"):
        recon.reprojection_errors()


def test_add_observation_conflict_raises():
    rng = np.random.default_rng(4)
    recon, _ = make_small_reconstruction(rng)
    with pytest.raises(ValueError, match="already observes"):
        recon.add_observation(next(iter(recon.points3D)) + 1, 1, 0)


def test_transform_keeps_reprojection_and_moves_centres():
    rng = np.random.default_rng(5)
    recon, _ = make_small_reconstruction(rng)
    centres = np.array([recon.images[i].center for i in sorted(recon.images)])
    sim = Sim3(3.0, random_rotation(rng), rng.normal(size=3))
    recon.transform(sim)
    assert recon.mean_reprojection_error() < 1e-9
    moved = np.array([recon.images[i].center for i in sorted(recon.images)])
    np.testing.assert_allclose(moved, sim.apply(centres), atol=1e-9)


def test_subset_keeps_ids_and_filters_tracks():
    rng = np.random.default_rng(6)
    recon, _ = make_small_reconstruction(rng)
    sub = recon.subset([1, 2])
    assert sorted(sub.images) == [1, 2] and len(sub.points3D) == 30
    assert set(sub.points3D) == set(recon.points3D)
    assert all(len(p.track) == 2 for p in sub.points3D.values())
    assert len(recon.points3D[next(iter(recon.points3D))].track) == 4  # original untouched
    assert len(recon.subset([3]).points3D) == 0


def test_camera_param_count_checked():
    with pytest.raises(ValueError, match="takes 4 params"):
        Camera(1, "SIMPLE_RADIAL", 10, 10, [1.0, 2.0])
    with pytest.raises(ValueError, match="camera model .FISHEYE_X. is not supported"):
        Camera(1, "FISHEYE_X", 10, 10, [1.0])


def test_bogus_intrinsics_are_recognised():
    """COLMAP's limits: focal in [0.1, 10] x the longer side, principal point in the image,
    distortion parameters within +-1, everything finite."""
    assert not has_bogus_params("SIMPLE_RADIAL", [1200.0, 639.5, 479.5, -0.2], 1280, 960)
    assert has_bogus_params("SIMPLE_RADIAL", [1200.0, 639.5, 479.5, -1.01], 1280, 960)
    assert has_bogus_params("SIMPLE_RADIAL", [100.0, 639.5, 479.5, 0.0], 1280, 960)  # f/1280 < 0.1
    assert has_bogus_params("PINHOLE", [1200.0, 13000.0, 639.5, 479.5], 1280, 960)  # fy/1280 > 10
    assert has_bogus_params("PINHOLE", [1200.0, 1200.0, 1300.0, 479.5], 1280, 960)  # cx outside
    assert has_bogus_params("OPENCV", [1200.0, 1200.0, 639.5, 479.5, 0.0, 0.0, 1.5, 0.0], 1280, 960)
    assert has_bogus_params("SIMPLE_RADIAL", [np.nan, 639.5, 479.5, 0.0], 1280, 960)
