"""The extract stage: SIFT + RootSIFT, downscaling, EXIF, image formats, cameras, resume."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from sfm import features
from sfm.database import Database
from sfm.errors import InputError
from sfm.features import ExtractOptions, extract_features, quantize_descriptors, run_extract
from sfm.images import find_images, focal_prior_from_exif, read_gray
from sfm.options import add_options, options_from_args

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FAST = {"num_workers": 1, "max_num_features": 1000}


def textured(height: int, width: int, seed: int) -> np.ndarray:
    """A BGR image of random filled shapes with mild noise: plenty of SIFT corners and blobs."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width, 3), 128, np.uint8)
    for _ in range(80):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        if rng.random() < 0.5:
            w, h = int(rng.integers(5, width // 6)), int(rng.integers(5, height // 6))
            cv2.rectangle(img, (x, y), (x + w, y + h), color, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, min(width, height) // 10)), color, -1)
    noise = rng.normal(0.0, 3.0, img.shape)
    return cv2.GaussianBlur(np.clip(img + noise, 0, 255).astype(np.uint8), (3, 3), 0)


def write(path: Path, bgr: np.ndarray, exif: Image.Exif | None = None, **kw) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    im.save(path, exif=exif, **kw) if exif is not None else im.save(path, **kw)
    return path


def read_db(workspace: Path) -> tuple[dict, dict, dict, dict]:
    """(cameras, images by name, keypoints by name, descriptors by name)."""
    with Database(workspace / "database.db", readonly=True) as db:
        cams = db.read_cameras()
        images = {r.name: r for r in db.read_images().values()}
        kps = {n: db.read_keypoints(r.image_id) for n, r in images.items()}
        descs = {n: db.read_descriptors(r.image_id) for n, r in images.items()}
    return cams, images, kps, descs


def close_sets(a: np.ndarray, b: np.ndarray, tol: float) -> float:
    """Share of points of ``a`` with a point of ``b`` within ``tol`` pixels."""
    d = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=2)
    return float(np.mean(d.min(axis=1) <= tol))


# ------------------------------------------------------------------------- SIFT and RootSIFT
def test_extract_counts_layout_and_rootsift(tmp_path):
    for i in range(3):
        write(tmp_path / "img" / f"im{i}.png", textured(480, 640, i))
    opts = ExtractOptions(num_workers=1, max_num_features=500)
    result = run_extract(tmp_path / "img", tmp_path / "ws", opts)
    assert (result.num_images, result.num_extracted, result.bad_files) == (3, 3, [])
    _, images, kps, descs = read_db(tmp_path / "ws")
    for name in images:
        kp, desc = kps[name], descs[name]
        assert 0 < len(kp) <= 500 and kp.shape[1] == 4 and kp.dtype == np.float32
        assert desc.shape == (len(kp), 128) and desc.dtype == np.uint8
        assert np.all(
            (kp[:, 0] >= -0.5) & (kp[:, 0] <= 639.5) & (kp[:, 1] >= -0.5) & (kp[:, 1] <= 479.5)
        )
        assert np.all(kp[:, 2] > 0.5) and np.all((kp[:, 3] >= 0) & (kp[:, 3] < 2 * np.pi))
        # RootSIFT: sqrt of an L1-normalised vector has unit L2 norm; bytes are 512 * value
        norms = np.linalg.norm(desc.astype(np.float64) / 512.0, axis=1)
        assert np.median(np.abs(norms - 1.0)) < 0.005
        assert np.all((norms > 0.95) & (norms < 1.01))
    assert result.mean_keypoints == pytest.approx(np.mean([len(k) for k in kps.values()]))


def test_quantize_descriptors_matches_colmap():
    d = np.zeros((2, 128))
    d[0, :4] = [1.0, 1.0, 1.0, 1.0]  # L1 -> 0.25 each, sqrt 0.5, * 512 = 256 -> clipped to 255
    d[1, :16] = 3.0  # L1 -> 1/16 each, sqrt 0.25 -> 128
    q = quantize_descriptors(d, root_sift=True)
    assert q.dtype == np.uint8
    assert list(q[0, :5]) == [255, 255, 255, 255, 0] and list(q[1, :17]) == [128] * 16 + [0]
    l2 = quantize_descriptors(d, root_sift=False)  # L2: 0.5 each -> 256 -> 255; 0.25 -> 128
    assert list(l2[0, :4]) == [255] * 4 and list(l2[1, :16]) == [128] * 16


def test_keypoints_keep_scale_and_orientation_conventions():
    """Rotating the image by 90 degrees rotates the keypoint orientations by 90 degrees
    (image axes, y down: a clockwise turn adds pi/2) and leaves their scale unchanged."""
    img = cv2.cvtColor(textured(400, 400, 7), cv2.COLOR_BGR2GRAY)
    opts = ExtractOptions(max_num_features=300)
    kp, _ = extract_features(img, opts)
    kp_rot, _ = extract_features(np.ascontiguousarray(np.rot90(img, -1)), opts)  # clockwise
    # clockwise turn of a 400x400 image: (x, y) -> (399 - y, x)
    moved = np.column_stack([399 - kp[:, 1], kp[:, 0]])
    d = np.linalg.norm(moved[:, None] - kp_rot[None, :, :2], axis=2)
    i, j = np.nonzero(d < 0.3)
    assert len(i) > 0.5 * len(kp)
    same_scale = np.abs(kp_rot[j, 2] / kp[i, 2] - 1.0) < 0.05
    dtheta = np.angle(np.exp(1j * (kp_rot[j, 3] - kp[i, 3] - np.pi / 2)))
    assert np.mean(same_scale & (np.abs(dtheta) < 0.1)) > 0.6


# ------------------------------------------------------------------------- downscaling
def test_downscaled_keypoints_map_to_full_resolution(tmp_path):
    """A 2x pixel-replicated image shrunk back by INTER_AREA is the original exactly, so its
    keypoints must be the original ones under x_full = (x_small + 0.5) * 2 - 0.5."""
    small = textured(240, 320, 3)
    big = cv2.resize(small, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    opts = ExtractOptions(max_image_size=320, max_num_features=400)
    kp_small, desc_small = extract_features(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), opts)
    kp_big, desc_big = extract_features(cv2.cvtColor(big, cv2.COLOR_BGR2GRAY), opts)
    assert len(kp_big) == len(kp_small) > 100
    expected = (kp_small[:, :2] + 0.5) * 2.0 - 0.5
    np.testing.assert_allclose(kp_big[:, :2], expected, atol=1e-3)
    np.testing.assert_allclose(kp_big[:, 2], 2.0 * kp_small[:, 2], rtol=1e-5)
    np.testing.assert_array_equal(desc_big, desc_small)

    # the same through the stage and the database; a cubic 2x upscale agrees within 1.5 px
    write(tmp_path / "img" / "small.png", small)
    write(tmp_path / "img" / "big.png", big)
    write(
        tmp_path / "img" / "cubic.png",
        cv2.resize(small, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC),
    )
    run_extract(
        tmp_path / "img",
        tmp_path / "ws",
        ExtractOptions(num_workers=1, max_image_size=320, max_num_features=400),
    )
    cams, images, kps, _ = read_db(tmp_path / "ws")
    assert (cams[images["big.png"].camera_id].width, cams[images["big.png"].camera_id].height) == (
        640,
        480,
    )
    expected = (kps["small.png"][:, :2] + 0.5) * 2.0 - 0.5
    np.testing.assert_allclose(kps["big.png"][:, :2], expected, atol=1e-3)
    assert close_sets(kps["cubic.png"], expected, 1.5) > 0.8


def test_sift_sees_only_the_downscaled_image(tmp_path, monkeypatch):
    seen = []
    real = features.detect_sift
    monkeypatch.setattr(features, "detect_sift", lambda g, o: seen.append(g.shape) or real(g, o))
    big = cv2.resize(textured(300, 400, 5), (4000, 3000), interpolation=cv2.INTER_LINEAR)
    write(tmp_path / "img" / "big.jpg", big, quality=90)
    run_extract(
        tmp_path / "img", tmp_path / "ws", ExtractOptions(num_workers=1, max_image_size=800)
    )
    assert seen == [(600, 800)]
    cams, images, kps, _ = read_db(tmp_path / "ws")
    cam = cams[images["big.jpg"].camera_id]
    assert (cam.width, cam.height) == (4000, 3000)
    assert kps["big.jpg"][:, 0].max() > 3000 and kps["big.jpg"][:, 1].max() > 2000


@pytest.mark.slow
def test_very_large_image(tmp_path):
    """12000 x 9000: decoded in full (luma only), shrunk to 3200 px before SIFT."""
    big = np.tile(textured(480, 640, 9), (19, 19, 1))[:9000, :12000]
    write(tmp_path / "img" / "huge.jpg", big, quality=85)
    del big
    result = run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(num_workers=2))
    assert result.num_extracted == 1 and result.mean_keypoints > 2000
    _, _, kps, _ = read_db(tmp_path / "ws")
    assert kps["huge.jpg"][:, 0].max() > 11000 and kps["huge.jpg"][:, 1].max() > 8000


# ------------------------------------------------------------------------- EXIF
def test_exif_orientation_gives_the_upright_image(tmp_path):
    stored = textured(480, 640, 11)  # what the sensor wrote: 640 wide, 480 high
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
    write(tmp_path / "img" / "tagged.png", stored, exif)
    write(tmp_path / "img" / "rotated.png", np.ascontiguousarray(np.rot90(stored, -1)))
    write(tmp_path / "img" / "tagged.jpg", stored, exif, quality=95)
    write(tmp_path / "img" / "tagged.tif", stored, tiffinfo={0x0112: 6})  # Pillow rotates TIFFs
    run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(num_workers=1))
    cams, images, kps, descs = read_db(tmp_path / "ws")
    for name in images:
        cam = cams[images[name].camera_id]
        assert (cam.width, cam.height) == (480, 640), name
    np.testing.assert_array_equal(kps["tagged.png"], kps["rotated.png"])
    np.testing.assert_array_equal(descs["tagged.png"], descs["rotated.png"])
    np.testing.assert_array_equal(kps["tagged.tif"], kps["rotated.png"])
    assert close_sets(kps["tagged.jpg"][:300], kps["rotated.png"], 1.5) > 0.8


def test_exif_focal_priors(tmp_path):
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 50  # FocalLengthIn35mmFilm
    exif[0x010F], exif[0x0110] = "Canon", "EOS"
    write(tmp_path / "img" / "f35.jpg", textured(480, 640, 1), exif)
    write(tmp_path / "img" / "plain.png", textured(480, 640, 2))
    run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST))
    cams, images, _, _ = read_db(tmp_path / "ws")
    f35 = cams[images["f35.jpg"].camera_id]
    assert f35.model == "SIMPLE_RADIAL" and f35.prior_focal_length
    np.testing.assert_allclose(f35.params, [50 / 36 * 640, 319.5, 239.5, 0.0])
    plain = cams[images["plain.png"].camera_id]
    assert not plain.prior_focal_length
    np.testing.assert_allclose(plain.params, [1.2 * 640, 319.5, 239.5, 0.0])


def test_focal_prior_rules():
    assert focal_prior_from_exif({0xA405: 28}, 4000, 3000) == (
        pytest.approx(28 / 36 * 4000),
        "exif-35mm",
    )
    # 35 mm lens on a 23.5 mm wide sensor with 6000 px: 255.3 px/mm, in mm units (4) and inches (2)
    px_per_mm = 6000 / 23.5
    tags = {0x920A: 35.0, 0xA20E: px_per_mm, 0xA210: 4}
    assert focal_prior_from_exif(tags, 6000, 4000) == (
        pytest.approx(35 * px_per_mm),
        "exif-focal-plane",
    )
    tags = {0x920A: 35.0, 0xA20E: px_per_mm * 25.4, 0xA210: 2}
    assert focal_prior_from_exif(tags, 4000, 6000)[0] == pytest.approx(35 * px_per_mm)
    # the file was resized to 1500 px after the camera wrote 6000 x 4000
    tags.update({0xA002: 6000, 0xA003: 4000})
    assert focal_prior_from_exif(tags, 1500, 1000)[0] == pytest.approx(35 * px_per_mm / 4)
    assert focal_prior_from_exif({0x920A: 35.0}, 6000, 4000) == (None, "none")  # no sensor size
    assert focal_prior_from_exif({0xA405: 0}, 6000, 4000) == (None, "none")
    assert focal_prior_from_exif({0xA405: 10000}, 6000, 4000) == (None, "none")  # bogus value


# ------------------------------------------------------------------------- formats, bad files
def test_image_formats(tmp_path):
    rgb = cv2.cvtColor(textured(240, 320, 4), cv2.COLOR_BGR2RGB)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    d = tmp_path / "img"
    d.mkdir()
    Image.fromarray(gray).save(d / "gray.png")
    Image.fromarray(np.dstack([rgb, np.full(gray.shape, 7, np.uint8)])).save(d / "rgba.png")
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=64).save(
        d / "palette.png"
    )
    cv2.imwrite(str(d / "gray16.png"), gray.astype(np.uint16) * 257)
    cv2.imwrite(str(d / "gray16.TIF"), gray.astype(np.uint16) * 257)
    cv2.imwrite(str(d / "rgb16.tiff"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(np.uint16) * 257)
    Image.fromarray(rgb).save(d / "color.bmp")
    Image.fromarray(rgb).save(d / "color.webp", lossless=True)
    (d / "notes.txt").write_text("not an image")
    assert find_images(d) == sorted(
        [
            "color.bmp",
            "color.webp",
            "gray.png",
            "gray16.TIF",
            "gray16.png",
            "palette.png",
            "rgb16.tiff",
            "rgba.png",
        ]
    )
    result = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))
    assert result.num_extracted == 8 and result.bad_files == []
    _, _, kps, _ = read_db(tmp_path / "ws")
    assert all(len(k) > 100 for k in kps.values())
    # 16-bit = 8-bit * 257 and alpha dropped: exactly the grey image's keypoints
    for name in ["gray16.png", "gray16.TIF"]:
        np.testing.assert_array_equal(kps[name], kps["gray.png"])
    assert (
        read_gray((d / "rgba.png").read_bytes())[0].tolist()
        == read_gray((d / "color.bmp").read_bytes())[0].tolist()
    )


def test_bad_files_are_skipped_with_one_warning_each(tmp_path, caplog):
    d = tmp_path / "img"
    write(d / "a.jpg", textured(240, 320, 1))
    write(d / "sub" / "b.png", textured(240, 320, 2))
    (d / "empty.jpg").write_bytes(b"")
    (d / "text.jpg").write_text("hello, I am not a JPEG\n")
    good = write(tmp_path / "full.jpg", textured(240, 320, 3)).read_bytes()
    (d / "truncated.jpg").write_bytes(good[: len(good) // 2])
    with caplog.at_level(logging.WARNING):
        result = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))
    assert result.num_extracted == 2
    assert sorted(n for n, _ in result.bad_files) == ["empty.jpg", "text.jpg", "truncated.jpg"]
    assert "truncated" in dict(result.bad_files)["truncated.jpg"]
    for name in ["empty.jpg", "text.jpg", "truncated.jpg"]:
        lines = [r.getMessage() for r in caplog.records if name in r.getMessage()]
        assert len(lines) == 1 and "\n" not in lines[0], lines
    _, images, _, _ = read_db(tmp_path / "ws")
    assert sorted(images) == ["a.jpg", "sub/b.png"]


def test_no_usable_images_is_an_input_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images found in"):
        run_extract(tmp_path / "empty", tmp_path / "ws", ExtractOptions(**FAST))
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "x.jpg").write_bytes(b"")
    (tmp_path / "bad" / "y.png").write_text("text")
    with pytest.raises(InputError, match="no usable images"):
        run_extract(tmp_path / "bad", tmp_path / "ws2", ExtractOptions(**FAST))
    assert not (tmp_path / "ws2" / "database.db-wal").exists()
    with pytest.raises(InputError, match="not found"):
        run_extract(tmp_path / "missing", tmp_path / "ws3", ExtractOptions(**FAST))


def test_duplicate_files_are_kept_with_a_warning(tmp_path, caplog):
    img = textured(240, 320, 5)
    write(tmp_path / "img" / "a.png", img)
    write(tmp_path / "img" / "b.png", img)
    with caplog.at_level(logging.WARNING):
        result = run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST))
    assert result.num_extracted == 2
    assert any("b.png is an exact copy of a.png" in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------------- cameras
def _two_sizes(d: Path) -> None:
    write(d / "a.png", textured(240, 320, 1))
    write(d / "b.png", textured(240, 320, 2))
    write(d / "c.png", textured(320, 240, 3))


def test_camera_modes(tmp_path):
    _two_sizes(tmp_path / "img")
    result = run_extract(tmp_path / "img", tmp_path / "auto", ExtractOptions(**FAST))
    assert result.num_cameras == 2
    _, images, _, _ = read_db(tmp_path / "auto")
    assert images["a.png"].camera_id == images["b.png"].camera_id != images["c.png"].camera_id

    with pytest.raises(InputError, match="c.png is 240x320"):
        run_extract(
            tmp_path / "img", tmp_path / "single", ExtractOptions(camera_mode="single", **FAST)
        )
    assert not (tmp_path / "single" / "database.db-wal").exists()

    result = run_extract(
        tmp_path / "img", tmp_path / "per_image", ExtractOptions(camera_mode="per-image", **FAST)
    )
    assert result.num_cameras == 3

    d = tmp_path / "folders"
    for folder, seed in [("x", 1), ("x", 2), ("y", 3)]:
        write(d / folder / f"{seed}.png", textured(240, 320, seed))
    write(d / "top.png", textured(240, 320, 4))
    result = run_extract(
        d, tmp_path / "per_folder", ExtractOptions(camera_mode="per-folder", **FAST)
    )
    assert result.num_cameras == 3
    _, images, _, _ = read_db(tmp_path / "per_folder")
    assert images["x/1.png"].camera_id == images["x/2.png"].camera_id
    assert len({images[n].camera_id for n in ["x/1.png", "y/3.png", "top.png"]}) == 3
    result = run_extract(d, tmp_path / "single_ok", ExtractOptions(camera_mode="single", **FAST))
    assert result.num_cameras == 1


def test_intrinsics_file(tmp_path, caplog):
    _two_sizes(tmp_path / "img")
    table = tmp_path / "K.txt"
    table.write_text(
        "# IMAGE_NAME W H FX FY CX CY  (extra columns are ignored)\n\n"
        "c.png 240 320 300.5 301.5 119.25 160.75 1 0 0 0 0 0 0\n"
        "*     320 240 400 410 160 120\n"
    )
    opts = ExtractOptions(intrinsics=table, **FAST)
    assert run_extract(tmp_path / "img", tmp_path / "ws", opts).num_cameras == 2
    cams, images, _, _ = read_db(tmp_path / "ws")
    assert images["a.png"].camera_id == images["b.png"].camera_id
    star, c = cams[images["a.png"].camera_id], cams[images["c.png"].camera_id]
    assert (star.model, star.width, star.height, star.prior_focal_length) == (
        "PINHOLE",
        320,
        240,
        True,
    )
    np.testing.assert_array_equal(star.params, [400, 410, 160, 120])
    assert (c.model, c.width, c.height) == ("PINHOLE", 240, 320)
    np.testing.assert_array_equal(c.params, [300.5, 301.5, 119.25, 160.75])

    # images the file does not cover keep their default camera, with a warning
    table.write_text("a.png 320 240 400 410 160 120\n")
    with caplog.at_level(logging.WARNING):
        run_extract(tmp_path / "img", tmp_path / "ws2", opts)
    cams, images, _, _ = read_db(tmp_path / "ws2")
    assert cams[images["a.png"].camera_id].model == "PINHOLE"
    assert cams[images["b.png"].camera_id].model == "SIMPLE_RADIAL"
    assert any("not in intrinsics file" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    "text, match",
    [
        ("a.png 320 240 400 410 160 120\n# ok\nb.png 320 240 400\n", r"K.txt:3: expected"),
        ("a.png 320 240 400 four 160 120\n", r"K.txt:1: .*must be numbers"),
        ("\n\na.png 320.5 240 400 400 160 120\n", r"K.txt:3: WIDTH and HEIGHT"),
        ("a.png 320 240 -400 400 160 120\n", r"K.txt:1: FX and FY must be positive"),
        ("# nothing\n", r"no intrinsics lines"),
        ("c.png 320 240 400 400 160 120\n", r"K.txt:1: .*c.png is 240x320"),
    ],
)
def test_bad_intrinsics_file(tmp_path, text, match):
    _two_sizes(tmp_path / "img")
    (tmp_path / "K.txt").write_text(text)
    with pytest.raises(InputError, match=match):
        run_extract(
            tmp_path / "img", tmp_path / "ws", ExtractOptions(intrinsics=tmp_path / "K.txt", **FAST)
        )


# ------------------------------------------------------------------------- resume, database
def test_resume_and_new_images(tmp_path, caplog):
    d = tmp_path / "img"
    for i in range(3):
        write(d / f"im{i}.png", textured(240, 320, i))
    first = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))
    assert (first.num_extracted, first.num_skipped_existing) == (3, 0)
    assert not (tmp_path / "ws" / "database.db-wal").exists()
    _, images_before, kps_before, _ = read_db(tmp_path / "ws")

    again = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))
    assert (again.num_extracted, again.num_skipped_existing, again.num_cameras) == (0, 3, 1)

    write(d / "later.png", textured(240, 320, 9))
    with caplog.at_level(logging.WARNING):
        third = run_extract(d, tmp_path / "ws", ExtractOptions(num_workers=1, max_num_features=800))
    assert (third.num_extracted, third.num_skipped_existing, third.num_cameras) == (1, 3, 1)
    assert any("max_num_features=1000" in r.getMessage() for r in caplog.records)
    _, images, kps, _ = read_db(tmp_path / "ws")
    assert {n: r.image_id for n, r in images.items() if n in images_before} == {
        n: r.image_id for n, r in images_before.items()
    }
    assert images["later.png"].camera_id == images["im0.png"].camera_id
    assert len(kps["later.png"]) <= 800
    np.testing.assert_array_equal(kps["im1.png"], kps_before["im1.png"])
    assert not (tmp_path / "ws" / "database.db-wal").exists()


def test_resume_keeps_rows_and_checks_shared_camera_sizes(tmp_path):
    d = tmp_path / "img"
    write(d / "a.png", textured(240, 320, 1))
    write(d / "b.png", textured(240, 320, 2))
    (tmp_path / "ws").mkdir()
    with Database(tmp_path / "ws" / "database.db") as db:  # a row without keypoints (COLMAP-made)
        cam = db.add_camera("PINHOLE", 320, 240, [300.0, 300.0, 159.5, 119.5], True)
        image_id = db.add_image("b.png", cam)
    result = run_extract(d, tmp_path / "ws", ExtractOptions(camera_mode="single", **FAST))
    assert (result.num_extracted, result.num_cameras) == (2, 2)
    cams, images, kps, _ = read_db(tmp_path / "ws")
    assert (images["b.png"].image_id, images["b.png"].camera_id) == (image_id, cam)
    assert len(kps["b.png"]) > 100 and cams[images["a.png"].camera_id].model == "SIMPLE_RADIAL"

    write(d / "c.png", textured(320, 240, 3))  # one camera cannot have two sizes
    with pytest.raises(InputError, match=r"c.png is 240x320 but camera \d+, made for its group"):
        run_extract(d, tmp_path / "ws", ExtractOptions(camera_mode="single", **FAST))
    assert not (tmp_path / "ws" / "database.db-wal").exists()
    result = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))  # auto: its own camera
    assert (result.num_extracted, result.num_cameras) == (1, 3)


def test_interrupted_run_keeps_finished_images(tmp_path, monkeypatch):
    for i in range(4):
        write(tmp_path / "img" / f"im{i}.png", textured(240, 320, i))
    real, calls = features._extract_job, []

    def interrupted_at_third(job):
        calls.append(job.name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(features, "_extract_job", interrupted_at_third)
    with pytest.raises(KeyboardInterrupt):
        run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST))
    assert not (tmp_path / "ws" / "database.db-wal").exists()
    _, images, kps, _ = read_db(tmp_path / "ws")
    assert sorted(images) == ["im0.png", "im1.png"] and all(len(k) for k in kps.values())
    monkeypatch.undo()
    result = run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST))
    assert (result.num_extracted, result.num_skipped_existing, result.num_cameras) == (2, 2, 1)


def test_worker_pool_gives_the_same_features(tmp_path):
    for i in range(3):
        write(tmp_path / "img" / f"im{i}.jpg", textured(240, 320, i))
    run_extract(
        tmp_path / "img", tmp_path / "one", ExtractOptions(num_workers=1, max_num_features=300)
    )
    result = run_extract(
        tmp_path / "img", tmp_path / "two", ExtractOptions(num_workers=2, max_num_features=300)
    )
    assert result.num_extracted == 3
    _, images1, kps1, descs1 = read_db(tmp_path / "one")
    _, images2, kps2, descs2 = read_db(tmp_path / "two")
    assert {n: r.image_id for n, r in images1.items()} == {
        n: r.image_id for n, r in images2.items()
    }
    for name in images1:
        np.testing.assert_array_equal(kps1[name], kps2[name])
        np.testing.assert_array_equal(descs1[name], descs2[name])


def test_options_make_cli_flags(tmp_path):
    parser = argparse.ArgumentParser()
    add_options(parser, ExtractOptions)
    args = parser.parse_args(
        ["--max-num-features", "100", "--no-root-sift", "--intrinsics", str(tmp_path / "K.txt")]
    )
    opts = options_from_args(ExtractOptions, args)
    assert opts == ExtractOptions(
        max_num_features=100, root_sift=False, intrinsics=tmp_path / "K.txt"
    )
    assert all(a.help for a in parser._actions if a.dest in ExtractOptions.__dataclass_fields__)
    for mode in ["auto", "single", "per-folder", "per-image"]:
        args = parser.parse_args(["--camera-mode", mode])
        assert options_from_args(ExtractOptions, args).camera_mode == mode
    with pytest.raises(ValueError, match="camera_mode"):
        ExtractOptions(camera_mode="per-camera")


# ------------------------------------------------------------------------- real data
def test_lund_door_with_gt_intrinsics(tmp_path):
    data = SHARED_DATA / "lund_door"
    if not (data / "images").is_dir():
        pytest.skip(f"lund_door not found at {data} (../shared/data beside the checkout)")
    opts = ExtractOptions(
        num_workers=2, max_image_size=1000, intrinsics=data / "gt" / "cameras_gt_opencv.txt"
    )
    result = run_extract(data / "images", tmp_path / "ws", opts)
    assert (result.num_images, result.num_extracted, result.num_cameras, result.bad_files) == (
        12,
        12,
        1,
        [],
    )
    cams, _, kps, _ = read_db(tmp_path / "ws")
    (cam,) = cams.values()
    assert (cam.model, cam.width, cam.height) == ("PINHOLE", 1296, 1936)
    np.testing.assert_allclose(cam.params, [2435.38, 2435.38, 648.0, 968.0])
    assert all(len(k) > 2000 for k in kps.values())
    assert max(k[:, 1].max() for k in kps.values()) > 1800  # full-resolution pixels
