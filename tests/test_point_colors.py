"""Point colours: every keypoint's colour is read at extraction and kept in the database; a 3D
point's colour is the mean over its track.  On the rendered facade, whose textures are known,
reconstructed points carry the colour of the surface they lie on, in the COLMAP files and the PLY."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import sfm
from backend.sim3 import umeyama
from sfm.evaluation.ground_truth import read_gt_table
from sfm.features.colors import keypoint_colors
from sfm.io.colmap_model import read_model, read_ply, write_model, write_ply
from sfm.io.database import Database
from sfm.io.image_files import read_gray, read_rgb
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import facade_planes, write_rendered_scene

SEED, NUM_IMAGES = 1, 8


def test_keypoint_colors_are_bilinear_at_opencv_pixel_centres():
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[:, :, 0] = np.arange(6) * 40
    rgb[:, :, 1] = (np.arange(4) * 50)[:, None]
    rgb[:, :, 2] = 7
    kp = np.array([[0, 0, 1, 0], [2.5, 1.5, 1, 0], [5, 3, 1, 0], [-3, 10, 1, 0]], np.float32)
    np.testing.assert_array_equal(keypoint_colors(rgb, kp), [[0, 0, 7], [100, 75, 7], [200, 150, 7], [0, 150, 7]])
    assert keypoint_colors(rgb, np.zeros((0, 4))).shape == (0, 3)


def test_rgb_is_upright_like_grey(tmp_path):
    """An EXIF-rotated JPEG decodes to the same upright shape in colour and grey, and a grey PNG
    gives three equal channels."""
    from PIL import Image

    rng = np.random.default_rng(0)
    pixels = (rng.random((40, 60, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = 6  # rotated 90 degrees: the upright image is 40 wide, 60 high
    Image.fromarray(pixels).save(tmp_path / "r.jpg", exif=exif.tobytes(), quality=95)
    data = (tmp_path / "r.jpg").read_bytes()
    gray, info = read_gray(data)
    rgb = read_rgb(data)
    assert gray.shape == (60, 40) and rgb.shape == (60, 40, 3) and (info.width, info.height) == (40, 60)
    luma = rgb.astype(float) @ [0.299, 0.587, 0.114]
    assert np.abs(luma - gray).mean() < 2.0  # the same pixels, in colour
    Image.fromarray(pixels[:, :, 0]).save(tmp_path / "g.png")
    g = read_rgb((tmp_path / "g.png").read_bytes())
    np.testing.assert_array_equal(g[:, :, 0], pixels[:, :, 0])
    np.testing.assert_array_equal(g[:, :, 0], g[:, :, 2])


def test_database_keeps_colours_beside_colmaps_tables(tmp_path):
    with Database(tmp_path / "database.db") as db:
        assert db.read_keypoint_colors() == {}  # no table: a database graphsfm did not extract
        cam = db.add_camera("SIMPLE_RADIAL", 64, 48, [50.0, 32.0, 24.0, 0.0])
        a, b = db.add_image("a.png", cam), db.add_image("b.png", cam)
        db.write_keypoints(a, np.zeros((3, 4), np.float32))
        db.write_keypoints(b, np.zeros((2, 4), np.float32))
        colors = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]], np.uint8)
        db.write_keypoint_colors(a, colors)
        db.write_keypoint_colors(b, colors)  # 3 colours for 2 keypoints: stale, not returned
    with Database(tmp_path / "database.db", readonly=True) as db:
        got = db.read_keypoint_colors()
        assert list(got) == [a]
        np.testing.assert_array_equal(got[a], colors)
        assert db.read_keypoint_colors([b]) == {}
    pycolmap = pytest.importorskip("pycolmap")
    db = pycolmap.Database.open(str(tmp_path / "database.db"))  # COLMAP ignores the extra table
    assert db.num_images() == 2 and db.num_keypoints() == 5
    db.close()


@pytest.fixture(scope="module")
def reconstruction(tmp_path_factory):
    root = tmp_path_factory.mktemp("colors")
    scene = write_rendered_scene(root / "scene", RenderOptions(num_images=NUM_IMAGES, seed=SEED))
    models, _ = sfm.reconstruct(scene["image_dir"], root / "ws", recording=False, workers=2, seed=0)
    return root, models[0], read_gt_table(Path(scene["gt_table"]))


def surface_colors(model, gt, seed: int, texture_size: int):
    """For each point of ``model`` that lies on one of the facade's planes (within 2 cm, not at
    a plane's border): its colour and the RGB of the plane's texture where it lies."""
    names = sorted(im.name for im in model.images.values())
    by_name = {im.name: im for im in model.images.values()}
    sim = umeyama(np.array([by_name[n].center for n in names]), np.array([gt[n].center for n in names]))
    planes = facade_planes(np.random.default_rng(seed), texture_size)  # write_rendered_scene's first draws
    ids = sorted(model.points3D)
    world = sim.apply(np.array([model.points3D[i].xyz for i in ids]))
    plane = np.full(len(ids), -1)
    where = np.zeros((len(ids), 2))
    distance = np.full(len(ids), np.inf)
    for k, p in enumerate(planes):
        normal = np.cross(p.u, p.v) / np.linalg.norm(np.cross(p.u, p.v))
        c = np.linalg.solve(np.column_stack([p.u, p.v, normal]), (world - p.origin).T).T
        on = (c[:, :2] > 0.01).all(1) & (c[:, :2] < 0.99).all(1) & (np.abs(c[:, 2]) < 0.02) & (np.abs(c[:, 2]) < distance)
        plane[on], where[on], distance[on] = k, c[on, :2], np.abs(c[on, 2])
    on = np.flatnonzero(plane >= 0)
    s = texture_size - 1
    truth = np.array([planes[plane[i]].texture[round(where[i, 1] * s), round(where[i, 0] * s)][::-1] for i in on])
    colors = np.array([model.points3D[ids[i]].color for i in on])
    return colors.astype(float), truth.astype(float)


def test_points_carry_the_colour_of_the_surface_they_lie_on(reconstruction):
    _, model, gt = reconstruction
    colors, truth = surface_colors(model, gt, SEED, RenderOptions().texture_size)
    assert len(colors) > 0.6 * len(model.points3D)
    error = np.abs(colors - truth).max(axis=1)  # worst channel
    swapped = np.abs(colors[:, ::-1] - truth).max(axis=1)
    shuffled = np.abs(colors[np.random.default_rng(0).permutation(len(colors))] - truth).max(axis=1)
    grey = np.abs(128 - truth).max(axis=1)
    # SIFT keypoints sit on edges and blobs, where colour changes within a pixel: the median is
    # what the test bounds, well below what shuffled, channel-swapped or grey colours give.
    assert np.median(error) < 30
    assert np.median(swapped) > 50 and np.median(shuffled) > 80 and np.median(grey) > 50


def test_colmap_files_and_ply_carry_the_colours(reconstruction, tmp_path):
    root, model, _ = reconstruction
    ids = sorted(model.points3D)
    rgb = np.array([model.points3D[i].color for i in ids])
    assert len(np.unique(rgb, axis=0)) > 0.5 * len(ids)  # not one grey
    binary = read_model(root / "ws" / "sparse" / "0")
    np.testing.assert_array_equal(np.array([binary.points3D[i].color for i in ids]), rgb)
    write_model(binary, tmp_path / "txt", fmt="txt")
    text = read_model(tmp_path / "txt")
    np.testing.assert_array_equal(np.array([text.points3D[i].color for i in ids]), rgb)
    write_ply(binary, tmp_path / "model.ply")
    xyz, ply_rgb = read_ply(tmp_path / "model.ply")
    np.testing.assert_array_equal(ply_rgb, rgb)
    np.testing.assert_allclose(xyz, [binary.points3D[i].xyz for i in ids])


def test_mean_colour_of_a_track_is_exact():
    from dataclasses import dataclass

    from sfm.mapper.output import mean_colors

    @dataclass
    class Payload:
        colors: list

    @dataclass
    class State:
        payload: Payload
        obs_image: np.ndarray
        obs_kp: np.ndarray

    colors = [np.array([[0, 0, 0], [255, 255, 255]], np.uint8), np.array([[10, 20, 31]], np.uint8), np.zeros((0, 3), np.uint8)]
    state = State(Payload(colors), np.array([0, 1, 0, 2, 1]), np.array([0, 0, 1, 0, 0]))
    rows, starts = np.arange(5), np.array([0, 2, 4, 5])
    # (0 + 10) / 2 = 5, (0 + 20) / 2 = 10, (0 + 31) / 2 = 15.5 -> 16; 255 and an unknown; one row
    np.testing.assert_array_equal(mean_colors(state, rows, starts), [[5, 10, 16], [255, 255, 255], [10, 20, 31]])
