"""Tests of sfm.evaluation.ground_truth: GT from a reconstruction, the GT table reader, the
projection-matrix reader, and the real GT tables of ../shared/data."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from _helpers_evaluation import _estimate, _ring_scene

from sfm.evaluation.metrics import evaluate
from sfm.evaluation.ground_truth import gt_from_reconstruction, read_gt_table, read_projection_matrices
from sfm.core.model import Camera, Image, Reconstruction

DATA = Path(__file__).parents[1] / ".." / "shared" / "data"


# ------------------------------------------------------------------------- GT input
def test_gt_from_reconstruction_skips_unregistered():
    recon = _ring_scene(n=6, num_points=0)
    recon.images[3].registered = False
    gt = gt_from_reconstruction(recon)
    assert sorted(gt) == [f"seq/img_{k:03d}.jpg" for k in (0, 1, 3, 4, 5)]
    pose = gt["seq/img_004.jpg"]
    np.testing.assert_array_equal(pose.K, recon.cameras[1].K)
    np.testing.assert_allclose(pose.center, recon.images[5].center, atol=1e-15)
    assert (pose.width, pose.height) == (640, 480)
    result = evaluate(recon, gt_from_reconstruction(_ring_scene(n=6, num_points=0)))
    assert result.registered_ratio == pytest.approx(5 / 6)
    assert math.isnan(result.mean_reprojection_error)
    json.dumps(result.to_dict(), allow_nan=False)


def test_read_gt_table_parses_and_rejects(tmp_path):
    good = "a/b/c.png 640 480 500 501 319.5 239.5 1 0 0 0 1 2 3"
    f = tmp_path / "gt.txt"
    other = "d.png 10 20 5 5 4.5 9.5 0 0 0 2 0 0 -1"
    f.write_text(f"# comment\n\n{good}\n  # indented comment\n{other}\n")
    gt = read_gt_table(f)
    assert list(gt) == ["a/b/c.png", "d.png"]
    p = gt["a/b/c.png"]
    np.testing.assert_array_equal(p.K, [[500, 0, 319.5], [0, 501, 239.5], [0, 0, 1]])
    np.testing.assert_array_equal(p.rotation, np.eye(3))
    np.testing.assert_array_equal(p.center, [-1.0, -2.0, -3.0])
    # quaternion (0,0,0,2) is normalised: 180 degrees about z
    np.testing.assert_allclose(gt["d.png"].rotation, np.diag([-1.0, -1.0, 1.0]), atol=1e-15)
    with pytest.raises(ValueError):
        p.rotation[0, 0] = 2.0  # read-only
    bad_lines = {
        "columns": "x.png 640 480 500 500 1 1 1 0 0 0 1 2",
        "number": "x.png 640 480 500 abc 1 1 1 0 0 0 1 2 3",
        "size": "x.png 640.5 480 500 500 1 1 1 0 0 0 1 2 3",
        "focal": "x.png 640 480 -500 500 1 1 1 0 0 0 1 2 3",
        "quaternion": "x.png 640 480 500 500 1 1 0 0 0 0 1 2 3",
        "nan": "x.png 640 480 500 500 1 1 1 0 0 0 nan 2 3",
        "twice": good,
    }
    for what, line in bad_lines.items():
        bad = tmp_path / f"bad_{what}.txt"
        bad.write_text(f"# header\n{good}\n{line}\n")
        with pytest.raises(ValueError, match=rf"bad_{what}\.txt:3"):
            read_gt_table(bad)


def _real_gt(name: str) -> Path:
    path = DATA / name / "gt" / "cameras_gt_opencv.txt"
    if not path.is_file():
        pytest.skip(f"real data absent: {path.resolve()} not found (../shared/data)")
    return path


def _model_of(gt: dict) -> Reconstruction:
    """GT poses as a reconstruction, one PINHOLE camera per image."""
    recon = Reconstruction()
    for k, pose in enumerate(gt.values()):
        recon.add_camera(Camera(k + 1, "PINHOLE", pose.width, pose.height,
                                [pose.K[0, 0], pose.K[1, 1], pose.K[0, 2], pose.K[1, 2]]))
        recon.add_image(Image(k + 1, pose.name, k + 1, pose.rotation, pose.translation))
    return recon


@pytest.mark.parametrize("name, count", [("lund_door", 12), ("temple_ring", 47)])
def test_read_real_gt_tables(name, count):
    gt = read_gt_table(_real_gt(name))
    assert len(gt) == count
    for pose in gt.values():
        assert pose.K[0, 0] > 0 and pose.K[1, 1] > 0 and pose.K[2, 2] == 1.0
        assert 0 < pose.K[0, 2] < pose.width and 0 < pose.K[1, 2] < pose.height
        np.testing.assert_allclose(pose.rotation @ pose.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(pose.rotation) == pytest.approx(1.0, abs=1e-12)
    # evaluating the GT against itself is perfect
    result = evaluate(_estimate(_model_of(gt)), gt)
    assert result.auc[1] == pytest.approx(1.0, abs=1e-9) and result.median_rotation_error_deg < 1e-9


def test_temple_ring_table_agrees_with_middlebury_parameters():
    path = _real_gt("temple_ring")
    par = path.parent / "templeR_par.txt"
    if not par.is_file():
        pytest.skip(f"{par} not found")
    gt = read_gt_table(path)
    lines = par.read_text().split("\n")[1:]
    checked = 0
    for line in lines:
        tok = line.split()
        if len(tok) != 22:
            continue
        values = np.array([float(v) for v in tok[1:]])
        k, r, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:]
        pose = gt[tok[0]]
        np.testing.assert_allclose(pose.rotation, r, atol=1e-8)
        np.testing.assert_allclose(pose.translation, t, atol=1e-9)
        np.testing.assert_allclose(pose.K, k, atol=1e-6)
        checked += 1
    assert checked == 47


def test_read_projection_matrices_splits_p_into_k_r_t(tmp_path):
    """P = s K [R | t] with known K (skewed, fx != fy), R and t, and a negative scale s: the
    reader gives back K (K[2, 2] = 1), R and t; an image without a size is left out; a short block
    is an error."""
    rng = np.random.default_rng(1)
    K = np.array([[2400.0, 3.0, 630.0], [0.0, 2390.0, 930.0], [0.0, 0.0, 1.0]])  # noqa: N806
    poses = {}
    text = ["# name, then P"]
    for k, scale in enumerate((1.0, -2.5, 1e-3)):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],  # noqa: N806
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        t = rng.standard_normal(3)
        poses[f"img{k}.jpg"] = (R, t)
        P = scale * K @ np.column_stack([R, t])  # noqa: N806
        text += [f"img{k}.jpg"] + [" ".join(f"{v:.17g}" for v in row) for row in P]
    path = tmp_path / "P_matrices.txt"
    path.write_text("\n".join(text) + "\n")
    gt = read_projection_matrices(path, {"img0.jpg": (1296, 1936), "img1.jpg": (1296, 1936), "img2.jpg": (1296, 1936)})
    assert sorted(gt) == ["img0.jpg", "img1.jpg", "img2.jpg"]
    for name, (R, t) in poses.items():  # noqa: N806
        np.testing.assert_allclose(gt[name].K, K, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(gt[name].rotation, R, atol=1e-12)
        np.testing.assert_allclose(gt[name].translation, t, atol=1e-11)
        assert (gt[name].width, gt[name].height) == (1296, 1936)
    assert sorted(read_projection_matrices(path, {"img1.jpg": (1296, 1936)})) == ["img1.jpg"]
    path.write_text("img0.jpg\n1 0 0 0\n0 1 0 0\n")
    with pytest.raises(ValueError, match="3 rows of 4 numbers"):
        read_projection_matrices(path, {})


def test_lund_door_projection_matrices_agree_with_its_table_up_to_a_similarity():
    """Olsson's P matrices of lund_door and its COLMAP pose table are two reconstructions of the
    same photos: after the Sim3 alignment their median rotation difference is below a degree."""
    path = _real_gt("lund_door").parent / "olsson_P_matrices.txt"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    table = read_gt_table(_real_gt("lund_door"))
    gt = read_projection_matrices(path, {n: (p.width, p.height) for n, p in table.items()})
    assert sorted(gt) == sorted(table)
    result = evaluate(_estimate(_model_of(gt)), table)
    assert result.num_registered == 12 and result.median_rotation_error_deg < 1.0
