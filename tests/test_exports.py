"""Exports a user can train on, each checked against its reader: undistorted images and a PINHOLE
model (pycolmap), nerfstudio's transforms.json (read back), the PLY (colours and normals); and
``graphsfm info`` / ``graphsfm align`` on the same model."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

import sfm.cli as cli
from backend.camera_models import project, unproject
from sfm.core.model import Camera
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.io.colmap_model import read_model, read_ply, write_model
from sfm.io.nerfstudio import APPLIED_TRANSFORM, read_nerfstudio, write_nerfstudio
from sfm.io.undistort import read_upright, undistorted_camera
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import make_scene, with_lens

LENS = [-0.2, 0.05, 0.003, -0.002]  # k1, k2, p1, p2 of a wide-angle phone lens


def _pattern(normalised: np.ndarray) -> np.ndarray:
    """A smooth grey pattern on the normalised image plane (what an ideal pinhole camera sees)."""
    x, y = normalised[..., 0], normalised[..., 1]
    return 127.5 + 100.0 * np.sin(9.0 * x + 1.0) * np.cos(7.0 * y - 0.5)


@pytest.fixture(scope="module")
def lens_model(tmp_path_factory):
    """A mapped synthetic scene seen through an OPENCV lens, and images of a known pattern
    taken through the refined camera (so pixels and model agree exactly)."""
    root = tmp_path_factory.mktemp("lens")
    opts = SynthOptions(scene="orbit", num_images=10, observations_per_image=1500, seed=3, width=320, height=240,
                        focal=280.0)
    scene = make_scene(opts)
    f, cx, cy = scene.focal, (scene.width - 1) / 2, (scene.height - 1) / 2
    write_database(with_lens(scene, "OPENCV", [f, f, cx, cy, *LENS]), simulate_matching(scene, opts),
                   root / "database.db", camera_model="OPENCV")
    run_map(root, MapperOptions(georegister=False), executor=LocalExecutor(1))
    model = root / "sparse" / "0"
    recon = read_model(model)
    [cam] = recon.cameras.values()
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    grey = _pattern(unproject(cam.model, cam.params, np.column_stack([u.ravel(), v.ravel()])).reshape(u.shape + (2,)))
    images = root / "images"
    images.mkdir()
    for image in recon.images.values():
        Image.fromarray(np.round(grey).astype(np.uint8)).save(images / image.name.replace(".jpg", ".png"))
    for image in recon.images.values():  # the model names its images .png
        image.name = image.name.replace(".jpg", ".png")
    write_model(recon, model)
    return model, images, read_model(model)


def _bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return cv2.remap(img.astype(np.float32), xy[:, :1].astype(np.float32), xy[:, 1:].astype(np.float32),
                     cv2.INTER_LINEAR).ravel()


def test_undistorted_export_is_what_pycolmap_reads_and_agrees_with_the_original(lens_model, tmp_path):
    model, images, recon = lens_model
    out = tmp_path / "und"
    assert cli.main(["export", str(model), str(out), "--to", "undistorted", "--images", str(images)]) == 0
    pycolmap = pytest.importorskip("pycolmap")
    theirs = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert len(theirs.images) == len(recon.images)
    for image in theirs.images.values():
        cam = theirs.cameras[image.camera_id]
        assert cam.model.name == "PINHOLE"
        with Image.open(out / "images" / image.name) as picture:
            assert picture.size == (cam.width, cam.height)
    undistorted = read_model(out / "sparse" / "0")
    [orig_cam], [pin] = recon.cameras.values(), undistorted.cameras.values()
    # Every pixel of the undistorted image shows the pattern where the pinhole camera looks.
    grey = read_upright(out / "images" / next(iter(undistorted.images.values())).name).astype(float)
    u, v = np.meshgrid(np.arange(pin.width, dtype=float), np.arange(pin.height, dtype=float))
    fx, fy, cx, cy = pin.params
    expected = _pattern(np.stack([(u - cx) / fx, (v - cy) / fy], axis=-1))
    assert np.abs(grey - expected)[2:-2, 2:-2].max() < 4.0  # rounding and bilinear resampling
    # Each point projects into the undistorted image and, with the distortion, into the original
    # at the same place of the scene: the two pixels map onto each other to a fraction of a pixel.
    for image_id, image in recon.images.items():
        und_image = undistorted.images[image_id]
        seen = np.flatnonzero(image.point3D_ids >= 0)
        xyz = np.array([recon.points3D[p].xyz for p in image.point3D_ids[seen]])
        cam_xyz = xyz @ image.cam_from_world_rotation.T + image.cam_from_world_translation
        in_original = project(orig_cam.model, orig_cam.params, cam_xyz)
        in_undistorted = project("PINHOLE", pin.params, cam_xyz)
        rays = np.column_stack([(in_undistorted - [cx, cy]) / [fx, fy], np.ones(len(seen))])
        np.testing.assert_allclose(project(orig_cam.model, orig_cam.params, rays), in_original, atol=1e-6)
        # the model's keypoints moved with the pixels: the same reprojection errors
        err_orig = np.linalg.norm(in_original - image.keypoints[seen], axis=1)
        err_und = np.linalg.norm(in_undistorted - und_image.keypoints[seen], axis=1)
        assert abs(err_orig.mean() - err_und.mean()) < 0.05
        # and the pixels themselves agree
        original = read_upright(images / image.name).astype(float)
        undist = read_upright(out / "images" / image.name).astype(float)
        inside = np.all((in_undistorted > 2) & (in_undistorted < [pin.width - 3, pin.height - 3]), axis=1)
        diff = _bilinear(original, in_original[inside]) - _bilinear(undist, in_undistorted[inside])
        assert np.abs(diff).max() < 4.0


def test_undistorted_camera_has_no_blank_pixels():
    cam = Camera(1, "OPENCV", 640, 480, np.array([500.0, 500.0, 319.5, 239.5, *LENS]))
    pin = undistorted_camera(cam)
    fx, fy, cx, cy = pin.params
    border = np.concatenate([np.column_stack([np.arange(pin.width), np.zeros(pin.width)]),
                             np.column_stack([np.arange(pin.width), np.full(pin.width, pin.height - 1)]),
                             np.column_stack([np.zeros(pin.height), np.arange(pin.height)]),
                             np.column_stack([np.full(pin.height, pin.width - 1), np.arange(pin.height)])])
    src = project(cam.model, cam.params, np.column_stack([(border - [cx, cy]) / [fx, fy], np.ones(len(border))]))
    assert np.all((src >= -0.5) & (src <= [639.5, 479.5]))
    assert pin.width > 0.9 * 640 and pin.height > 0.9 * 480  # ... and is the largest such rectangle, nearly
    assert undistorted_camera(Camera(1, "SIMPLE_PINHOLE", 64, 48, np.array([50.0, 31.5, 23.5]))).width == 64


def test_a_lens_that_folds_inside_the_image_cannot_be_undistorted_and_says_so():
    """k2 = -0.6 turns the radial map back before the image's corners: no ray reaches them."""
    folding = Camera(3, "OPENCV", 320, 240, np.array([268.0, 269.0, 159.5, 119.5, -0.09, -0.6, 0.0, 0.0]))
    with pytest.raises(InputError, match="camera 3 .*folds back inside the image"):
        undistorted_camera(folding)


def test_nerfstudio_round_trip(lens_model, tmp_path):
    model, images, recon = lens_model
    out = tmp_path / "ns"
    assert cli.main(["export", str(model), str(out / "transforms.json"), "--images", str(images)]) == 0  # from .json
    data = json.loads((out / "transforms.json").read_text())
    [cam] = recon.cameras.values()
    assert data["camera_model"] == "OPENCV" and (data["w"], data["h"]) == (cam.width, cam.height)
    np.testing.assert_allclose([data["fl_x"], data["fl_y"], data["cx"], data["cy"]],
                               [cam.params[0], cam.params[1], cam.params[2] + 0.5, cam.params[3] + 0.5])
    np.testing.assert_allclose([data[k] for k in ("k1", "k2", "p1", "p2")], cam.params[4:])
    frames = read_nerfstudio(out / "transforms.json")
    by_name = {im.name: im for im in recon.images.values()}
    assert len(frames) == len(by_name)
    for file_path, (rotation, translation, intrinsics) in frames.items():
        assert (out / file_path).resolve() == (images / Path(file_path).name).resolve()
        image = by_name[Path(file_path).name]
        np.testing.assert_allclose(-rotation.T @ translation, image.center, atol=1e-9)  # same centre
        np.testing.assert_allclose(rotation[2], image.cam_from_world_rotation[2], atol=1e-12)  # same viewing direction
        np.testing.assert_allclose(rotation, image.cam_from_world_rotation, atol=1e-12)
    # OpenGL axes: the camera looks down its -z, in nerfstudio's world (applied_transform)
    frame = data["frames"][0]
    image = recon.images[frame["colmap_im_id"]]
    c2w = np.array(frame["transform_matrix"])
    np.testing.assert_allclose(-c2w[:3, 2], APPLIED_TRANSFORM[:, :3] @ image.cam_from_world_rotation[2], atol=1e-12)
    xyz, rgb, normals = read_ply(out / data["ply_file_path"], normals=True)
    ours = np.array([recon.points3D[p].xyz for p in sorted(recon.points3D)])
    np.testing.assert_allclose(xyz, ours @ APPLIED_TRANSFORM[:, :3].T, atol=1e-9)


def test_nerfstudio_per_frame_intrinsics_when_cameras_differ(lens_model, tmp_path):
    _, _, recon = lens_model
    recon = recon.copy()
    [cam] = recon.cameras.values()
    other = Camera(2, "PINHOLE", cam.width, cam.height, np.array([300.0, 301.0, 160.0, 120.0]))
    recon.cameras[2] = other
    ids = sorted(recon.images)
    for i in ids[::2]:
        recon.images[i].camera_id = 2
    write_nerfstudio(recon, tmp_path / "transforms.json")
    data = json.loads((tmp_path / "transforms.json").read_text())
    assert "fl_x" not in data and data["camera_model"] == "OPENCV"
    for frame in data["frames"]:
        expected = other if recon.images[frame["colmap_im_id"]].camera_id == 2 else cam
        assert frame["fl_x"] == expected.params[0] and frame["w"] == expected.width
        assert frame["file_path"] == f"images/{recon.images[frame['colmap_im_id']].name}"
    assert [frame["k1"] for frame in data["frames"] if frame["fl_x"] == 300.0] == [0.0] * len(ids[::2])


def test_ply_keeps_colours_and_normals_face_the_cameras(lens_model, tmp_path):
    model, _, recon = lens_model
    assert cli.main(["export", str(model), str(tmp_path / "points.ply")]) == 0  # format from .ply
    xyz, rgb, normals = read_ply(tmp_path / "points.ply", normals=True)
    ids = sorted(recon.points3D)
    np.testing.assert_array_equal(rgb, np.array([recon.points3D[p].color for p in ids]))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    for row in range(0, len(ids), 50):
        for image_id, _ in recon.points3D[ids[row]].track:
            assert normals[row] @ (recon.images[image_id].center - xyz[row]) > 0


def test_existing_output_is_an_error_that_says_so(lens_model, tmp_path, capsys):
    model, _, _ = lens_model
    out = tmp_path / "model"
    assert cli.main(["export", str(model), str(out)]) == 0  # no extension: a binary COLMAP model
    assert (out / "cameras.bin").is_file()
    assert cli.main(["export", str(model), str(out)]) == 2
    assert "exists; choose another output or pass --overwrite" in capsys.readouterr().err
    assert cli.main(["export", str(model), str(out), "--to", "txt", "--overwrite"]) == 0
    assert (out / "cameras.txt").is_file()
    assert cli.main(["export", str(tmp_path / "nowhere"), str(tmp_path / "x")]) == 2
    assert "model not found" in capsys.readouterr().err


def test_info_summarises_the_model(lens_model, capsys):
    model, _, recon = lens_model
    capsys.readouterr()
    assert cli.main(["info", str(model)]) == 0
    info = json.loads(capsys.readouterr().out)
    [cam] = info["cameras"]
    assert cam["model"] == "OPENCV" and set(cam["params"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"}
    assert cam["params"]["cx"] == pytest.approx(recon.cameras[cam["camera_id"]].params[2] + 0.5)
    assert info["registered_images"] == len(recon.registered_image_ids) == 10
    assert info["points"] == len(recon.points3D)
    assert info["observations"] == recon.num_observations
    assert info["mean_track_length"] == pytest.approx(recon.mean_track_length, rel=1e-9)
    assert info["mean_reprojection_error"] == pytest.approx(recon.mean_reprojection_error(), rel=1e-9)
    assert info["georegistered"] is False


def test_align_to_a_reference_table(lens_model, tmp_path, capsys):
    model, _, recon = lens_model
    angle = np.radians(30.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    table = tmp_path / "ref.txt"
    truth = {im.name: 2.5 * rotation @ im.center + [100.0, -20.0, 3.0] for im in recon.images.values()}
    table.write_text("# name x y z\n" + "".join(f"{n} {float(x)!r} {float(y)!r} {float(z)!r}\n" for n, (x, y, z) in truth.items()))
    assert cli.main(["align", str(model), "--ref", str(table), str(tmp_path / "aligned"), "--max-error", "0.5"]) == 0
    aligned = read_model(tmp_path / "aligned")
    for image in aligned.images.values():
        np.testing.assert_allclose(image.center, truth[image.name], atol=1e-6)
    assert json.loads(capsys.readouterr().out)["scale"] == pytest.approx(2.5)
    assert not (tmp_path / "aligned" / "georegistration.json").exists()
    assert cli.main(["align", str(model), "--gps", str(tmp_path), str(tmp_path / "gps")]) == 2  # no GPS there
    assert "cannot align" in capsys.readouterr().err


def test_python_api(lens_model, tmp_path):
    import sfm
    from sfm.errors import InputError

    model, images, recon = lens_model
    assert sfm.export(model, tmp_path / "m", to="txt")["images"] == 10
    assert (tmp_path / "m" / "images.txt").is_file()
    assert sfm.info(tmp_path / "m")["points"] == len(recon.points3D)
    with pytest.raises(ValueError, match="unknown option 'too'"):
        sfm.export(model, tmp_path / "x.ply", too="ply")
    with pytest.raises(InputError, match="one of --gps SOURCE or --ref TABLE"):
        sfm.align(model, tmp_path / "a")
