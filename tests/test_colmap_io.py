"""COLMAP model I/O: bin/txt round trips, the +0.5 pixel convention, pycolmap interop, PLY."""

from __future__ import annotations

import os

import numpy as np
import pytest

from sfm.io import colmap_model as colmap_io
from backend.geometry import quaternion_to_rotation, rotation_to_quaternion
from sfm.core.model import Camera, Image, Reconstruction


def random_reconstruction(seed: int = 0, num_images: int = 10, num_points: int = 200
                          ) -> Reconstruction:
    """Two cameras (SIMPLE_RADIAL, OPENCV), random poses and keypoints, tracks of 2-5 views."""
    rng = np.random.default_rng(seed)
    recon = Reconstruction()
    recon.add_camera(Camera(3, "SIMPLE_RADIAL", 640, 480, [500.3, 319.5, 239.25, -0.012]))
    recon.add_camera(
        Camera(7, "OPENCV", 800, 600, [610.1, 605.7, 399.5, 301.2, 0.01, -0.002, 1e-4, -2e-4])
    )
    for k in range(num_images):
        image_id = 10 + 3 * k  # not contiguous
        recon.add_image(
            Image(
                image_id,
                f"dir/img_{k:03d}.jpg",
                3 if k % 2 else 7,
                quaternion_to_rotation(rng.normal(size=4)),
                rng.normal(size=3) * 5,
                rng.uniform(0, 600, size=(150 + 3 * k, 2)),
            )
        )
    image_ids = list(recon.images)
    for p in range(num_points):
        views = rng.choice(image_ids, size=rng.integers(2, 6), replace=False)
        track = []
        for image_id in views:
            free = np.flatnonzero(recon.images[int(image_id)].point3D_ids == -1)
            track.append((int(image_id), int(rng.choice(free))))
        color = rng.integers(0, 256, 3)
        pid = recon.add_point3D(rng.normal(size=3) * 10, track, color, point3D_id=1000 + 2 * p)
        recon.points3D[pid].error = float(rng.uniform(0, 2))
    return recon


def sorted_track(track: list[tuple[int, int]]) -> list[tuple[int, int]]:
    return sorted((int(i), int(k)) for i, k in track)


def close(actual, expected, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(actual, expected, rtol=0, atol=atol)


def assert_same(a: Reconstruction, b: Reconstruction, atol: float = 1e-12,
                pose_atol: float = 1e-12) -> None:
    """Same ids and data; values equal to ``atol`` (0 means bit-identical)."""
    assert sorted(a.cameras) == sorted(b.cameras)
    for cid, cam in a.cameras.items():
        other = b.cameras[cid]
        assert (cam.model, cam.width, cam.height) == (other.model, other.width, other.height)
        close(other.params, cam.params, atol)
    assert sorted(a.images) == sorted(b.images)
    for iid, im in a.images.items():
        other = b.images[iid]
        assert (im.name, im.camera_id, other.registered) == (other.name, other.camera_id, True)
        close(other.cam_from_world_rotation, im.cam_from_world_rotation, pose_atol)
        close(other.cam_from_world_translation, im.cam_from_world_translation, pose_atol)
        close(other.keypoints, im.keypoints, atol)
        np.testing.assert_array_equal(other.point3D_ids, im.point3D_ids)
    assert sorted(a.points3D) == sorted(b.points3D)
    for pid, pt in a.points3D.items():
        other = b.points3D[pid]
        np.testing.assert_array_equal(other.xyz, pt.xyz)
        np.testing.assert_array_equal(other.color, pt.color)
        assert other.color.dtype == np.uint8
        assert other.error == pt.error
        assert sorted_track(other.track) == sorted_track(pt.track)


@pytest.fixture(scope="module")
def recon() -> Reconstruction:
    return random_reconstruction()


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_round_trip(recon, tmp_path, fmt):
    colmap_io.write_model(recon, tmp_path, fmt)
    assert colmap_io.detect_format(tmp_path) == fmt
    back = colmap_io.read_model(tmp_path)
    assert_same(recon, back)
    assert back.num_observations == recon.num_observations == sum(
        im.num_points3D for im in back.images.values()
    )
    assert back._next_point_id == max(recon.points3D) + 1
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp files
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{n}.{fmt}" for n in ("cameras", "images", "points3D", "rigs", "frames")
    )


def test_bin_then_txt_is_identical(recon, tmp_path):
    colmap_io.write_model(recon, tmp_path / "a", "bin")
    first = colmap_io.read_model(tmp_path / "a")
    colmap_io.write_model(first, tmp_path / "b", "txt")
    second = colmap_io.read_model(tmp_path / "b")
    # Bit-identical except the rotations, which go through a quaternion each time.
    assert_same(first, second, atol=0.0, pose_atol=1e-14)
    for iid, im in first.images.items():
        translation = second.images[iid].cam_from_world_translation
        np.testing.assert_array_equal(translation, im.cam_from_world_translation)
    for pid, point in first.points3D.items():  # tracks come back in the same order
        assert second.points3D[pid].track == point.track
    # The same model written as txt twice gives the same bytes (deterministic output).
    colmap_io.write_model(second, tmp_path / "c", "txt")
    for name in ("cameras", "points3D"):
        b, c = (tmp_path / d / f"{name}.txt" for d in "bc")
        assert b.read_bytes() == c.read_bytes()


def test_pixel_convention_visible_in_text(tmp_path):
    recon = Reconstruction()
    recon.add_camera(Camera(1, "PINHOLE", 200, 100, [150.0, 151.0, 99.5, 49.5]))
    recon.add_image(Image(5, "a.png", 1, np.eye(3), [0.0, 0.0, 1.0], [[10.0, 20.0], [0.0, 0.0]]))
    recon.add_image(Image(6, "b.png", 1, np.eye(3), [1.0, 0.0, 1.0], [[30.0, 40.0]]))
    recon.add_point3D([0.0, 0.0, 5.0], [(5, 0), (6, 0)], np.array([1, 2, 3]), point3D_id=9)
    colmap_io.write_model(recon, tmp_path, "txt")
    camera_line = [ln for ln in (tmp_path / "cameras.txt").read_text().splitlines() if ln[0] != "#"]
    assert camera_line[0].split()[:4] == ["1", "PINHOLE", "200", "100"]
    assert [float(v) for v in camera_line[0].split()[4:]] == [150.0, 151.0, 100.0, 50.0]
    lines = [ln for ln in (tmp_path / "images.txt").read_text().splitlines() if ln[0] != "#"]
    assert lines[0].split()[-1] == "a.png"
    assert [float(v) for v in lines[1].split()] == [10.5, 20.5, 9, 0.5, 0.5, -1]
    assert [float(v) for v in lines[3].split()] == [30.5, 40.5, 9]
    point_line = [ln for ln in (tmp_path / "points3D.txt").read_text().splitlines() if ln[0] != "#"]
    assert point_line[0].split()[:7] == ["9", "0.0", "0.0", "5.0", "1", "2", "3"]
    assert point_line[0].split()[8:] == ["5", "0", "6", "0"]
    back = colmap_io.read_model(tmp_path)
    np.testing.assert_array_equal(back.images[5].keypoints, [[10.0, 20.0], [0.0, 0.0]])
    np.testing.assert_array_equal(back.cameras[1].params, [150.0, 151.0, 99.5, 49.5])


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_names_with_spaces(recon, tmp_path, fmt, caplog):
    """COLMAP's own text reader stops at the first space; ours (and COLMAP's binary) keep it."""
    model = recon.copy()
    model.images[10].name = "sub dir/IMG 0001.JPG"
    colmap_io.write_model(model, tmp_path, fmt)
    assert ("whitespace" in caplog.text) == (fmt == "txt")
    assert colmap_io.read_model(tmp_path).images[10].name == "sub dir/IMG 0001.JPG"
    if fmt == "bin":
        pycolmap = pytest.importorskip("pycolmap")
        assert pycolmap.Reconstruction(str(tmp_path)).images[10].name == "sub dir/IMG 0001.JPG"


def test_only_registered_images_are_written(recon, tmp_path):
    model = recon.copy()
    dropped = sorted(model.images)[0]
    model.images[dropped].registered = False
    lost = [pid for pid, p in model.points3D.items() if {i for i, _ in p.track} <= {dropped}]
    colmap_io.write_model(model, tmp_path, "bin")
    back = colmap_io.read_model(tmp_path)
    assert dropped not in back.images and len(back.images) == len(recon.images) - 1
    assert lost == [] or all(pid not in back.points3D for pid in lost)
    for pid, p in back.points3D.items():
        expected = [(i, k) for i, k in model.points3D[pid].track if i != dropped]
        assert sorted_track(p.track) == sorted_track(expected)
    assert back.num_observations == model.num_observations - model.images[dropped].num_points3D


def test_writing_is_atomic(recon, tmp_path, monkeypatch):
    colmap_io.write_model(recon, tmp_path, "bin")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def fail(f, t):
        f.write(b"half a file")
        raise RuntimeError("interrupted")

    other = random_reconstruction(seed=1)
    monkeypatch.setitem(colmap_io.WRITERS["bin"], "points3D", fail)
    with pytest.raises(RuntimeError, match="interrupted"):
        colmap_io.write_model(other, tmp_path, "bin")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    umask = os.umask(0o022)
    os.umask(umask)
    assert (tmp_path / "images.bin").stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_missing_and_corrupt_files(recon, tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        colmap_io.read_model(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match=str(tmp_path)):
        colmap_io.read_model(tmp_path)
    colmap_io.write_model(recon, tmp_path / "m", "bin")
    os.remove(tmp_path / "m" / "points3D.bin")
    with pytest.raises(FileNotFoundError, match="found: cameras.bin, images.bin$"):
        colmap_io.read_model(tmp_path / "m")
    with pytest.raises(FileNotFoundError, match="points3D.bin is missing"):
        colmap_io.read_model(tmp_path / "m", fmt="bin")
    colmap_io.write_model(recon, tmp_path / "m", "bin")
    data = (tmp_path / "m" / "images.bin").read_bytes()
    (tmp_path / "m" / "images.bin").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"images\.bin: corrupt or truncated"):
        colmap_io.read_model(tmp_path / "m")
    (tmp_path / "m" / "images.bin").write_bytes(data + b"\0")
    with pytest.raises(ValueError, match="trailing"):
        colmap_io.read_model(tmp_path / "m")
    colmap_io.write_model(recon, tmp_path / "t", "txt")
    text = (tmp_path / "t" / "points3D.txt").read_text().splitlines()
    (tmp_path / "t" / "points3D.txt").write_text("\n".join(text[:-1] + [text[-1] + " 7"]) + "\n")
    with pytest.raises(ValueError, match=r"points3D\.txt"):
        colmap_io.read_model(tmp_path / "t")
    # A track that disagrees with the images' point ids is caught.
    *head, image_id, _ = text[-1].split()
    free = np.flatnonzero(recon.images[int(image_id)].point3D_ids == -1)[0]
    bad_line = " ".join(head + [image_id, str(free)])
    (tmp_path / "t" / "points3D.txt").write_text("\n".join(text[:-1] + [bad_line]))
    with pytest.raises(ValueError, match="disagree"):
        colmap_io.read_model(tmp_path / "t")
    with pytest.raises(ValueError, match="format"):
        colmap_io.write_model(recon, tmp_path / "x", "json")


def test_ply(recon, tmp_path):
    colmap_io.write_ply(recon, tmp_path / "sub" / "model.ply")
    raw = (tmp_path / "sub" / "model.ply").read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 200\n")
    xyz, rgb = colmap_io.read_ply(tmp_path / "sub" / "model.ply")
    ids = sorted(recon.points3D)
    assert xyz.shape == (200, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(xyz, [recon.points3D[i].xyz for i in ids])
    np.testing.assert_array_equal(rgb, [recon.points3D[i].color for i in ids])
    (tmp_path / "bad.ply").write_bytes(raw[:-5])
    with pytest.raises(ValueError, match="bad.ply"):
        colmap_io.read_ply(tmp_path / "bad.ply")


# ------------------------------------------------------------------------------ pycolmap interop
def check_pycolmap_model(ours: Reconstruction, theirs) -> None:
    """A pycolmap.Reconstruction holds the same numbers as ours (+0.5 on pixels)."""
    assert theirs.num_cameras() == len(ours.cameras)
    assert theirs.num_reg_images() == theirs.num_images() == len(ours.registered_image_ids)
    assert theirs.num_points3D() == len(ours.points3D)
    assert theirs.compute_num_observations() == ours.num_observations
    for cid, cam in ours.cameras.items():
        their_cam = theirs.cameras[cid]
        assert their_cam.model.name == cam.model
        assert (their_cam.width, their_cam.height) == (cam.width, cam.height)
        expected = cam.params.copy()
        expected[[1, 2] if cam.model == "SIMPLE_RADIAL" else [2, 3]] += 0.5
        close(their_cam.params, expected)
    for iid in ours.registered_image_ids:
        im, their_im = ours.images[iid], theirs.images[iid]
        assert their_im.name == im.name and their_im.camera_id == im.camera_id
        matrix = their_im.cam_from_world().matrix()
        close(matrix[:, :3], im.cam_from_world_rotation)
        close(matrix[:, 3], im.cam_from_world_translation)
        xy = np.array([p.xy for p in their_im.points2D])
        close(xy, im.keypoints + 0.5)
        pids = [p.point3D_id if p.has_point3D() else -1 for p in their_im.points2D]
        np.testing.assert_array_equal(pids, im.point3D_ids)
    for pid, pt in ours.points3D.items():
        their_pt = theirs.points3D[pid]
        np.testing.assert_array_equal(their_pt.xyz, pt.xyz)
        np.testing.assert_array_equal(their_pt.color, pt.color)
        assert their_pt.error == pytest.approx(pt.error, abs=1e-15)
        their_track = [(e.image_id, e.point2D_idx) for e in their_pt.track.elements]
        assert sorted_track(their_track) == sorted_track(pt.track)


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_pycolmap_reads_our_model(recon, tmp_path, fmt):
    pycolmap = pytest.importorskip("pycolmap")
    colmap_io.write_model(recon, tmp_path, fmt)
    theirs = pycolmap.Reconstruction(str(tmp_path))
    check_pycolmap_model(recon, theirs)
    assert theirs.num_rigs() == len(recon.cameras) and theirs.num_frames() == len(recon.images)
    # Without our rigs/frames files pycolmap derives the same trivial ones (classic 3-file model).
    for name in ("rigs", "frames"):
        os.remove(tmp_path / f"{name}.{fmt}")
    check_pycolmap_model(recon, pycolmap.Reconstruction(str(tmp_path)))


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_we_read_a_pycolmap_model(tmp_path, fmt):
    pycolmap = pytest.importorskip("pycolmap")
    theirs = pycolmap.Reconstruction()
    for camera_id, model, params in [(2, "SIMPLE_RADIAL", [500.0, 320.0, 240.0, 0.01]),
                                     (4, "PINHOLE", [600.0, 610.0, 400.0, 300.0])]:
        theirs.add_camera_with_trivial_rig(
            pycolmap.Camera(model=model, width=800, height=600, params=params, camera_id=camera_id)
        )
    rng = np.random.default_rng(3)
    for image_id, camera_id in [(1, 2), (3, 2), (8, 4)]:
        image = pycolmap.Image(name=f"im{image_id}.jpg", camera_id=camera_id, image_id=image_id)
        image.points2D = [pycolmap.Point2D(xy) for xy in rng.uniform(0, 400, size=(5, 2))]
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(q[[1, 2, 3, 0]]), rng.normal(size=3))  # xyzw
        theirs.add_image_with_trivial_frame(image, pose)
    for k, elements in enumerate([[(1, 0), (3, 1)], [(1, 2), (3, 3), (8, 4)]]):
        track = pycolmap.Track()
        for image_id, idx in elements:
            track.add_element(image_id, idx)
        pid = theirs.add_point3D(rng.normal(size=3), track, np.array([10 * k, 20, 255], np.uint8))
        theirs.point3D(pid).error = 0.25 + k
    getattr(theirs, "write_binary" if fmt == "bin" else "write_text")(str(tmp_path))
    assert (tmp_path / f"frames.{fmt}").exists()  # COLMAP 4 writes rigs and frames; we ignore them
    ours = colmap_io.read_model(tmp_path)
    assert sorted(ours.cameras) == [2, 4] and sorted(ours.images) == [1, 3, 8]
    close(ours.cameras[2].params, [500.0, 319.5, 239.5, 0.01])
    close(ours.cameras[4].params, [600.0, 610.0, 399.5, 299.5])
    for image_id, image in theirs.images.items():
        matrix = image.cam_from_world().matrix()
        close(ours.images[image_id].cam_from_world_rotation, matrix[:, :3])
        close(ours.images[image_id].cam_from_world_translation, matrix[:, 3])
        close(ours.images[image_id].keypoints, np.array([p.xy for p in image.points2D]) - 0.5)
        assert ours.images[image_id].name == image.name and ours.images[image_id].registered
    assert sorted_track(ours.points3D[2].track) == [(1, 2), (3, 3), (8, 4)]
    assert ours.images[8].point3D_ids.tolist() == [-1, -1, -1, -1, 2]
    for pid, point in theirs.points3D.items():
        np.testing.assert_array_equal(ours.points3D[pid].xyz, point.xyz)
        np.testing.assert_array_equal(ours.points3D[pid].color, point.color)
        assert ours.points3D[pid].error == point.error
    check_pycolmap_model(ours, theirs)


def test_quaternion_convention(recon, tmp_path):
    """images.txt holds cam_from_world as QW QX QY QZ TX TY TZ."""
    colmap_io.write_model(recon, tmp_path, "txt")
    text = (tmp_path / "images.txt").read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    for head in lines[0::2]:
        v = head.split(maxsplit=9)
        image = recon.images[int(v[0])]
        q = np.array(v[1:5], dtype=float)
        assert q[0] >= 0 and np.isclose(np.linalg.norm(q), 1.0, atol=1e-15)
        np.testing.assert_array_equal(q, rotation_to_quaternion(image.cam_from_world_rotation))
        translation = np.array(v[5:8], dtype=float)
        np.testing.assert_array_equal(translation, image.cam_from_world_translation)
        assert int(v[8]) == image.camera_id and v[9] == image.name
