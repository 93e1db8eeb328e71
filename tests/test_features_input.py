"""The extract stage's input: EXIF orientation and focal priors, image formats, bad and
duplicate files."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from _helpers_features import FAST, close_sets, read_db, textured, write
from PIL import Image

from sfm.execution.local import LocalExecutor
from sfm.errors import InputError
from sfm.features.options import ExtractOptions
from sfm.stages.extract import run_extract
from sfm.io.exif import focal_prior_from_exif
from sfm.io.image_files import find_images, read_gray


# ------------------------------------------------------------------------- EXIF
def test_exif_orientation_gives_the_upright_image(tmp_path):
    stored = textured(480, 640, 11)  # what the sensor wrote: 640 wide, 480 high
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
    write(tmp_path / "img" / "tagged.png", stored, exif)
    write(tmp_path / "img" / "rotated.png", np.ascontiguousarray(np.rot90(stored, -1)))
    write(tmp_path / "img" / "tagged.jpg", stored, exif, quality=95)
    write(tmp_path / "img" / "tagged.tif", stored, tiffinfo={0x0112: 6})  # Pillow rotates TIFFs
    run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(), LocalExecutor(1))
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

