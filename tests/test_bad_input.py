"""Bad input through the command line, as a user meets it: one clear line, never a traceback,
the exit codes of ``sfm.errors`` (0 model written, 2 no usable input, 3 input read but no model), and
the bad files skipped by name while the good ones still give a model."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _helpers_features import textured

from sfm.io.colmap_model import read_model
from sfm.synthetic.options import RenderOptions
from sfm.synthetic.rendered import write_rendered_scene


def graphsfm(*argv: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "sfm", *argv], capture_output=True, text=True, timeout=900,
                          check=False)
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    return proc


def last_line(proc: subprocess.CompletedProcess) -> str:
    return [ln for ln in proc.stderr.splitlines() if ln.strip()][-1]


def reconstruct(images: Path, ws: Path, *extra: str) -> subprocess.CompletedProcess:
    return graphsfm("reconstruct", "--images", str(images), "--workspace", str(ws), "--no-recording",
                    "--max-num-features", "4000", *extra)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """Twelve rendered views (PNG)."""
    out = tmp_path_factory.mktemp("scene")
    return Path(write_rendered_scene(out, RenderOptions(num_images=12, seed=11))["image_dir"])


def test_bad_files_among_good_ones_are_skipped_by_name(scene, tmp_path):
    d = tmp_path / "images"
    shutil.copytree(scene, d)
    views = sorted(p.name for p in d.iterdir())
    # Good images in unusual formats: the same views as 16-bit, RGBA and grey PNGs.
    bgr = cv2.imread(str(d / views[1]))
    cv2.imwrite(str(d / views[1]), bgr.astype(np.uint16) * 257)
    cv2.imwrite(str(d / views[2]), cv2.cvtColor(cv2.imread(str(d / views[2])), cv2.COLOR_BGR2BGRA))
    cv2.imwrite(str(d / views[3]), cv2.cvtColor(cv2.imread(str(d / views[3])), cv2.COLOR_BGR2GRAY))
    assert cv2.imread(str(d / views[1]), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    # Bad files: empty, truncated, text; and an exact duplicate of a view.
    (d / "empty.jpg").write_bytes(b"")
    jpeg = cv2.imencode(".jpg", cv2.imread(str(d / views[4])))[1].tobytes()
    (d / "truncated.jpg").write_bytes(jpeg[: len(jpeg) // 3])
    (d / "notes.jpg").write_text("this is not a picture\n")
    shutil.copy(d / views[5], d / "zz_copy.png")

    proc = reconstruct(d, tmp_path / "ws")
    assert proc.returncode == 0, proc.stderr[-3000:]
    warnings = [ln for ln in proc.stderr.splitlines() if ln.startswith("W ")]
    for bad in ("empty.jpg", "truncated.jpg", "notes.jpg"):
        assert sum(bad in ln for ln in warnings) == 1, warnings
    assert any(f"zz_copy.png is an exact copy of {views[5]}" in ln for ln in warnings), warnings
    model = read_model(tmp_path / "ws" / "sparse" / "0")
    registered = {im.name for im in model.images.values()}
    assert set(views) <= registered  # the 16-bit, RGBA and grey views included
    report = json.loads((tmp_path / "ws" / "report.json").read_text())
    assert report["registered"] >= 12 and report["num_models"] == 1


def test_two_images_give_a_two_view_model(scene, tmp_path):
    d = tmp_path / "two"
    d.mkdir()
    for name in sorted(p.name for p in scene.iterdir())[:2]:
        shutil.copy(scene / name, d / name)
    proc = reconstruct(d, tmp_path / "ws")
    assert proc.returncode == 0, proc.stderr[-3000:]
    model = read_model(tmp_path / "ws" / "sparse" / "0")
    assert len(model.images) == 2 and len(model.points3D) > 100


def test_two_unrelated_scenes_give_two_models_and_say_so(scene, tmp_path):
    d = tmp_path / "both"
    shutil.copytree(scene, d / "a")
    other = write_rendered_scene(tmp_path / "other", RenderOptions(num_images=10, seed=12))
    shutil.copytree(other["image_dir"], d / "b")
    proc = reconstruct(d, tmp_path / "ws")
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((tmp_path / "ws" / "report.json").read_text())
    assert report["num_models"] == 2 and "2 models" in " ".join(report["warnings"])
    sizes = sorted(len(read_model(tmp_path / "ws" / "sparse" / k).images) for k in ("0", "1"))
    assert sizes == [10, 12]
    assert "2 models" in proc.stderr


@pytest.mark.parametrize("case,code,message", [
    ("empty folder", 2, "no images found in"),
    ("one image", 2, "1 image(s) in"),
    ("no overlap", 3, "no two of the 4 images overlap"),
    ("only bad files", 2, "no usable images in"),
    ("missing folder", 2, "image folder not found"),
])
def test_inputs_that_cannot_give_a_model(scene, tmp_path, case, code, message):
    d = tmp_path / "images"
    d.mkdir()
    if case == "one image":
        shutil.copy(next(scene.iterdir()), d / "only.png")
    elif case == "no overlap":  # four views of four different scenes
        for i in range(4):
            other = write_rendered_scene(tmp_path / f"s{i}", RenderOptions(num_images=2, seed=40 + i))
            shutil.copy(min(Path(other["image_dir"]).iterdir()), d / f"im{i}.png")
    elif case == "only bad files":
        (d / "a.jpg").write_bytes(b"")
        (d / "b.png").write_text("text")
    elif case == "missing folder":
        d = tmp_path / "nowhere"
    proc = reconstruct(d, tmp_path / "ws")
    assert proc.returncode == code, proc.stderr[-3000:]
    assert last_line(proc).startswith("graphsfm reconstruct: error: ") and message in last_line(proc)
    assert not (tmp_path / "ws" / "sparse" / "0").exists()


def test_invalid_intrinsics_file_and_unwritable_workspace(scene, tmp_path):
    bad = tmp_path / "K.txt"
    bad.write_text("view_000.png 640 480 five hundred\n")
    proc = reconstruct(scene, tmp_path / "ws", "--intrinsics", str(bad))
    assert proc.returncode == 2 and str(bad) in last_line(proc) and "error" in last_line(proc)
    proc = reconstruct(scene, tmp_path / "ws2", "--intrinsics", str(tmp_path / "missing.txt"))
    assert proc.returncode == 2 and "missing.txt" in last_line(proc)
    blocker = tmp_path / "file"
    blocker.write_text("a file where the workspace folder should be")
    proc = reconstruct(scene, blocker / "ws")
    assert proc.returncode == 2 and "cannot write to workspace" in last_line(proc)


def test_a_huge_image_is_downscaled_not_held_in_memory(tmp_path):
    """12,000 x 9,000 pixels: SIFT at full size would need ~25 GB; it runs at 3200 px."""
    d = tmp_path / "big"
    d.mkdir()
    small = textured(2250, 3000, 7)
    cv2.imwrite(str(d / "huge.jpg"), cv2.resize(small, (12000, 9000), interpolation=cv2.INTER_CUBIC),
                [cv2.IMWRITE_JPEG_QUALITY, 85])
    del small
    ws = tmp_path / "ws"
    code = ("import resource, subprocess, sys; p = subprocess.run(sys.argv[1:]); "
            "print(p.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, sys.executable, "-m", "sfm", "extract", "--images", str(d),
                          "--workspace", str(ws), "--workers", "1", "--no-recording"],
                         capture_output=True, text=True, timeout=900, check=True).stdout.split()
    returncode, peak_kib = int(out[-2]), int(out[-1])
    assert returncode == 0
    assert peak_kib < 3 * 1024**2, f"peak RSS {peak_kib / 1024**2:.2f} GiB"
    import sqlite3

    with sqlite3.connect(ws / "database.db") as conn:
        width, height = conn.execute("SELECT width, height FROM cameras").fetchone()
        rows, blob = conn.execute("SELECT rows, data FROM keypoints").fetchone()
    assert (width, height) == (12000, 9000) and 300 < rows <= 8192
    xy = np.frombuffer(blob, np.float32).reshape(rows, -1)[:, :2]
    assert xy[:, 0].max() > 11000 and xy[:, 1].max() > 8000  # keypoints in full-resolution pixels
