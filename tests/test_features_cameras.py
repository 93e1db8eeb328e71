"""The extract stage's cameras: camera modes (auto, single, per-folder, per-image) and
intrinsics files."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from _helpers_features import FAST, read_db, textured, write

from sfm.errors import InputError
from sfm.features.options import ExtractOptions
from sfm.stages.extract import run_extract


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

