"""``--masks``: COLMAP's mask convention (``MASKS/<image name>.png``, zero = ignore)."""

from __future__ import annotations

import numpy as np
import pytest
from _helpers_features import FAST, read_db, textured, write
from PIL import Image

from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.features.options import ExtractOptions
from sfm.stages.extract import run_extract


def _mask(path, height, width, zero_box):
    """A mask of 255 with a zero rectangle (x0, y0, x1, y1)."""
    m = np.full((height, width), 255, np.uint8)
    x0, y0, x1, y1 = zero_box
    m[y0:y1, x0:x1] = 0
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(m).save(path)
    return m


@pytest.mark.parametrize("max_image_size", [1000, 200])  # SIFT at full size, and on a shrunk image
def test_no_keypoint_in_a_masked_area(tmp_path, max_image_size):
    write(tmp_path / "img" / "a.jpg", textured(240, 320, 1))
    write(tmp_path / "img" / "sub" / "b.png", textured(240, 320, 2))
    write(tmp_path / "img" / "c.png", textured(240, 320, 3))
    masks = tmp_path / "masks"
    ma = _mask(masks / "a.jpg.png", 240, 320, (0, 0, 160, 240))  # left half ignored
    mb = _mask(masks / "sub" / "b.png.png", 240, 320, (100, 60, 220, 180))  # a central box ignored
    opts = dict(FAST, max_image_size=max_image_size)
    run_extract(tmp_path / "img", tmp_path / "plain", ExtractOptions(**opts))
    run_extract(tmp_path / "img", tmp_path / "masked", ExtractOptions(masks=masks, **opts))
    _, _, plain, _ = read_db(tmp_path / "plain")
    _, _, masked, descs = read_db(tmp_path / "masked")
    for name, m in (("a.jpg", ma), ("sub/b.png", mb)):
        kp = masked[name]
        cols, rows = np.rint(kp[:, 0]).astype(int), np.rint(kp[:, 1]).astype(int)
        assert len(kp) > 50 and len(descs[name]) == len(kp)
        assert np.all(m[rows, cols] != 0), name
        # what the plain run found outside the masked area is still found
        pc, pr = np.rint(plain[name][:, 0]).astype(int), np.rint(plain[name][:, 1]).astype(int)
        assert np.sum(m[pr, pc] == 0) > 20  # there was something to drop
    # c.png has no mask: used whole, the same keypoints as without masks
    np.testing.assert_array_equal(masked["c.png"], plain["c.png"])


def test_masks_travel_to_remote_workers(tmp_path):
    """Workers on other machines get the mask's bytes with the image's: same keypoints."""
    write(tmp_path / "img" / "a.png", textured(240, 320, 1))
    _mask(tmp_path / "masks" / "a.png.png", 240, 320, (0, 0, 160, 240))
    opts = ExtractOptions(masks=tmp_path / "masks", **FAST)

    class Remote(LocalExecutor):
        remote = True

    run_extract(tmp_path / "img", tmp_path / "local", opts, LocalExecutor(1))
    run_extract(tmp_path / "img", tmp_path / "remote", opts, Remote(1))
    np.testing.assert_array_equal(read_db(tmp_path / "local")[2]["a.png"], read_db(tmp_path / "remote")[2]["a.png"])


def test_mask_of_another_size_skips_its_image(tmp_path, caplog):
    write(tmp_path / "img" / "a.png", textured(240, 320, 1))
    write(tmp_path / "img" / "b.png", textured(240, 320, 2))
    _mask(tmp_path / "masks" / "a.png.png", 100, 100, (0, 0, 10, 10))
    result = run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(masks=tmp_path / "masks", **FAST))
    assert [name for name, _ in result.bad_files] == ["a.png"]
    assert "mask is 100x100 but the image is 320x240" in result.bad_files[0][1]


def test_missing_mask_folder_is_an_input_error(tmp_path):
    write(tmp_path / "img" / "a.png", textured(240, 320, 1))
    with pytest.raises(InputError, match="mask folder not found"):
        run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(masks=tmp_path / "nope", **FAST))
