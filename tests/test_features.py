"""The extract stage: SIFT + RootSIFT, downscaling, resume, worker pool, options, real data.
EXIF and image formats are in test_features_input.py, cameras in test_features_cameras.py."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from _helpers_features import FAST, close_sets, read_db, textured, write

from sfm.cli import add_options, options_of
from sfm.errors import InputError
from sfm.execution.local import LocalExecutor
from sfm.features import extraction as features
from sfm.features.extraction import extract_features
from sfm.features.options import ExtractOptions
from sfm.features.sift import quantize_descriptors
from sfm.io.database import Database
from sfm.stages.extract import run_extract

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


# ------------------------------------------------------------------------- SIFT and RootSIFT
def test_extract_counts_layout_and_rootsift(tmp_path):
    for i in range(3):
        write(tmp_path / "img" / f"im{i}.png", textured(480, 640, i))
    opts = ExtractOptions(max_num_features=500)
    result = run_extract(tmp_path / "img", tmp_path / "ws", opts, LocalExecutor(1))
    assert (result.num_images, result.num_extracted, result.bad_files) == (3, 3, [])
    _, images, kps, descs = read_db(tmp_path / "ws")
    for name in images:
        kp, desc = kps[name], descs[name]
        assert 0 < len(np.unique(kp[:, :3], axis=0)) <= 500 and kp.shape[1] == 4 and kp.dtype == np.float32
        assert len(kp) <= 1000
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


def test_max_num_features_keeps_the_largest_scale_locations_by_default():
    """COLMAP's rule: of all detections, the locations kept are the largest-scale ones (every
    dropped location is finer than every kept one), each with its descriptors as detected;
    ``keep_features="strongest"`` keeps the highest responses instead, another set."""
    img = cv2.cvtColor(textured(400, 400, 7), cv2.COLOR_BGR2GRAY)
    everything, all_desc = extract_features(img, ExtractOptions(max_num_features=100_000))
    kept, desc = extract_features(img, ExtractOptions(max_num_features=60))
    strongest, _ = extract_features(img, ExtractOptions(max_num_features=60, keep_features="strongest"))
    locations = lambda kp: {tuple(np.round(r[:3], 3)) for r in kp}  # noqa: E731
    assert len(locations(everything)) > 200 and len(locations(kept)) == 60
    assert locations(kept) <= locations(everything)
    dropped = locations(everything) - locations(kept)
    assert min(r[2] for r in locations(kept)) >= max(r[2] for r in dropped)
    assert len(locations(strongest)) == 60 and locations(strongest) != locations(kept)
    index = {tuple(np.round(r, 4)): k for k, r in enumerate(everything)}
    same = [index[tuple(np.round(r, 4))] for r in kept]
    np.testing.assert_array_equal(desc, all_desc[same])
    with pytest.raises(ValueError, match="keep_features"):
        ExtractOptions(keep_features="random")


def test_describing_all_or_only_the_kept_keypoints_gives_the_same_features(monkeypatch):
    """Small images describe every detection, large ones only the kept keypoints (a second
    pyramid): the same keypoints and descriptors either way."""
    import sfm.features.sift as sift

    img = cv2.cvtColor(textured(400, 400, 7), cv2.COLOR_BGR2GRAY)
    opts = ExtractOptions(max_num_features=80)
    monkeypatch.setattr(sift, "DESCRIBE_ALL_PIXELS", 10**9)
    kp_all, desc_all = features.detect_sift(img, opts)
    monkeypatch.setattr(sift, "DESCRIBE_ALL_PIXELS", 0)
    kp_kept, desc_kept = features.detect_sift(img, opts)
    assert len(kp_all) >= 80
    np.testing.assert_array_equal(kp_kept, kp_all)
    np.testing.assert_array_equal(desc_kept, desc_all)


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
        ExtractOptions(max_image_size=320, max_num_features=400),
        LocalExecutor(1),
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
    monkeypatch.setattr(features, "detect_sift", lambda g, o, m=None: seen.append(g.shape) or real(g, o, m))
    big = cv2.resize(textured(300, 400, 5), (4000, 3000), interpolation=cv2.INTER_LINEAR)
    write(tmp_path / "img" / "big.jpg", big, quality=90)
    run_extract(
        tmp_path / "img", tmp_path / "ws", ExtractOptions(max_image_size=800), LocalExecutor(1)
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
    result = run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(), LocalExecutor(2))
    assert result.num_extracted == 1 and result.mean_keypoints > 2000
    _, _, kps, _ = read_db(tmp_path / "ws")
    assert kps["huge.jpg"][:, 0].max() > 11000 and kps["huge.jpg"][:, 1].max() > 8000



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
    third = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))
    assert (third.num_extracted, third.num_skipped_existing, third.num_cameras) == (1, 3, 1)
    _, images, kps, _ = read_db(tmp_path / "ws")
    assert {n: r.image_id for n, r in images.items() if n in images_before} == {
        n: r.image_id for n, r in images_before.items()
    }
    assert images["later.png"].camera_id == images["im0.png"].camera_id
    np.testing.assert_array_equal(kps["im1.png"], kps_before["im1.png"])
    assert not (tmp_path / "ws" / "database.db-wal").exists()

    # A feature option changed: the stored features are stale, every image is extracted again.
    with caplog.at_level(logging.WARNING):
        fourth = run_extract(d, tmp_path / "ws", ExtractOptions(**{**FAST, "max_num_features": 200}))
    assert (fourth.num_extracted, fourth.num_skipped_existing, fourth.num_cameras) == (4, 0, 1)
    assert any("max_num_features: 1000 -> 200" in r.getMessage() for r in caplog.records)
    _, _, kps, _ = read_db(tmp_path / "ws")
    # 200 keypoint locations (COLMAP's meaning), each with at most two orientations
    assert max(len(np.unique(k[:, :3], axis=0)) for k in kps.values()) == 200
    assert all(len(k) <= 400 for k in kps.values())


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
    # camera_mode changed: the cameras of the stored images are stale, all are extracted again
    result = run_extract(d, tmp_path / "ws", ExtractOptions(**FAST))  # auto: one camera per size
    assert (result.num_extracted, result.num_skipped_existing, result.num_cameras) == (3, 0, 2)


def test_interrupted_run_keeps_finished_images(tmp_path, monkeypatch):
    for i in range(4):
        write(tmp_path / "img" / f"im{i}.png", textured(240, 320, i))
    import sfm.stages.extract as extract_stage

    real, calls = extract_stage._extract_job, []

    def interrupted_at_third(job):
        calls.append(job.name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(extract_stage, "_extract_job", interrupted_at_third)
    with pytest.raises(KeyboardInterrupt):
        run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(**FAST), LocalExecutor(1))
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
        tmp_path / "img", tmp_path / "one", ExtractOptions(max_num_features=300), LocalExecutor(1)
    )
    result = run_extract(
        tmp_path / "img", tmp_path / "two", ExtractOptions(max_num_features=300), LocalExecutor(2)
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
    opts = options_of(ExtractOptions, args)
    assert opts == ExtractOptions(
        max_num_features=100, root_sift=False, intrinsics=tmp_path / "K.txt"
    )
    assert all(a.help for a in parser._actions if a.dest in ExtractOptions.__dataclass_fields__)
    for mode in ["auto", "single", "per-folder", "per-image"]:
        args = parser.parse_args(["--camera-mode", mode])
        assert options_of(ExtractOptions, args).camera_mode == mode
    with pytest.raises(ValueError, match="camera_mode"):
        ExtractOptions(camera_mode="per-camera")


# ------------------------------------------------------------------------- real data
def test_lund_door_with_gt_intrinsics(tmp_path):
    data = SHARED_DATA / "lund_door"
    if not (data / "images").is_dir():
        pytest.skip(f"lund_door not found at {data} (../shared/data beside the checkout)")
    opts = ExtractOptions(
        max_image_size=1000, intrinsics=data / "gt" / "cameras_gt_opencv.txt"
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
