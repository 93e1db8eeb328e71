"""``--camera-model``: each COLMAP model is given at extraction, refined by bundle adjustment,
written and read in COLMAP's files; OPENCV recovers a lens SIMPLE_RADIAL cannot hold."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from _helpers_features import FAST, read_db, textured, write

from backend.camera_models import CAMERA_MODELS, default_params, model_spec, project
from sfm.evaluation.ground_truth import gt_from_reconstruction
from sfm.evaluation.metrics import evaluate
from sfm.execution.local import LocalExecutor
from sfm.features.options import ExtractOptions
from sfm.io.colmap_model import read_model, write_model
from sfm.mapper.options import MapperOptions
from sfm.stages.extract import run_extract
from sfm.stages.map import run_map
from sfm.stages.payloads import load_payloads
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import gt_reconstruction, make_scene, with_lens

MODELS = tuple(CAMERA_MODELS)


@pytest.mark.parametrize("model", MODELS)
def test_extraction_gives_the_chosen_model(tmp_path, model):
    write(tmp_path / "img" / "a.png", textured(240, 320, 1))
    run_extract(tmp_path / "img", tmp_path / "ws", ExtractOptions(camera_model=model, **FAST))
    cameras, images, _, _ = read_db(tmp_path / "ws")
    cam = cameras[images["a.png"].camera_id]
    assert cam.model == model
    np.testing.assert_allclose(cam.params, default_params(model, 320, 240, 1.2 * 320))
    # Only the intrinsics file's cameras are held by the mapper: a chosen PINHOLE is refined.
    [payload] = load_payloads(tmp_path / "ws" / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    assert not any(prior.fixed for prior in payload.cameras.values())


def test_intrinsics_file_cameras_stay_held_beside_a_chosen_model(tmp_path):
    write(tmp_path / "img" / "a.png", textured(240, 320, 1))
    write(tmp_path / "img" / "b.png", textured(240, 320, 2))
    table = tmp_path / "K.txt"
    table.write_text("a.png 320 240 300 300 159.5 119.5\n")
    run_extract(tmp_path / "img", tmp_path / "ws",
                ExtractOptions(camera_model="PINHOLE", intrinsics=table, camera_mode="per-image", **FAST))
    cameras, images, _, _ = read_db(tmp_path / "ws")
    assert cameras[images["a.png"].camera_id].model == cameras[images["b.png"].camera_id].model == "PINHOLE"
    [payload] = load_payloads(tmp_path / "ws" / "database.db", None, fixed_intrinsics=True, min_inliers=15)
    fixed = {payload.names[k]: payload.cameras[c].fixed for k, c in enumerate(payload.camera_ids)}
    assert fixed == {"a.png": True, "b.png": False}


def _lens_scene(num_images: int = 20):
    opts = SynthOptions(scene="orbit", num_images=num_images, observations_per_image=800, seed=3)
    scene = make_scene(opts)
    return opts, scene, simulate_matching(scene, opts)


@pytest.mark.parametrize("model", MODELS)
def test_every_model_maps_and_round_trips_through_colmap_files(tmp_path, model):
    """A mild radial lens (k1 = -0.02): every model registers the scene, its refined camera
    keeps its layout through .bin and .txt, and pycolmap reads the model."""
    opts, scene, pairs = _lens_scene(12)
    f, cx, cy = scene.focal, (scene.width - 1) / 2, (scene.height - 1) / 2
    lensed = with_lens(scene, "RADIAL", [f, cx, cy, -0.02, 0.0])
    write_database(lensed, pairs, tmp_path / "database.db", camera_model=model)
    run_map(tmp_path, MapperOptions(), executor=LocalExecutor(1))
    recon = read_model(tmp_path / "sparse" / "0")
    assert len(recon.registered_image_ids) == 12
    [cam] = recon.cameras.values()
    assert cam.model == model and len(cam.params) == model_spec(model).num_params
    focal = np.mean(np.asarray(cam.params)[list(model_spec(model).focal_idx)])
    assert abs(focal - f) < 0.02 * f
    for fmt in ("bin", "txt"):
        write_model(recon, tmp_path / fmt, fmt=fmt)
        again = read_model(tmp_path / fmt)
        [cam2] = again.cameras.values()
        assert cam2.model == model
        np.testing.assert_allclose(cam2.params, cam.params, rtol=0, atol=1e-9)
    pycolmap = pytest.importorskip("pycolmap")
    theirs = pycolmap.Reconstruction(str(tmp_path / "bin"))
    [their_cam] = theirs.cameras.values()
    assert their_cam.model.name == model
    # COLMAP's principal point is 0.5 px further (image corner at 0, 0)
    expected = np.array(cam.params, float)
    expected[list(model_spec(model).pp_idx)] += 0.5
    np.testing.assert_allclose(np.asarray(their_cam.params), expected, atol=1e-9)


def _lens_field_error(params: np.ndarray, truth: np.ndarray, f: float, cx: float, cy: float,
                      width: int, height: int) -> float:
    """Largest pixel distance between where an OPENCV lens ``params`` (k1, k2, p1, p2 with the
    true f, cx, cy) and the true lens put a ray, over the circle inscribed in the image: the
    directions every image sees.  Beyond it, in the corners, k1 and k2 trade against each other
    (their terms differ by r^2) and the corners are extrapolated from few points."""
    xs, ys = np.meshgrid(np.linspace(0, width - 1, 65), np.linspace(0, height - 1, 49))
    inside = np.hypot(xs - cx, ys - cy) <= min(width, height) / 2
    rays = np.stack([(xs[inside] - cx) / f, (ys[inside] - cy) / f, np.ones(int(inside.sum()))], axis=1)
    seen = project("OPENCV", np.array([f, f, cx, cy, *params]), rays)
    true = project("OPENCV", np.array([f, f, cx, cy, *truth]), rays)
    return float(np.linalg.norm(seen - true, axis=1).max())


def test_opencv_recovers_a_wide_angle_lens_simple_radial_cannot_hold(tmp_path):
    """A phone-like lens with k1, k2, p1, p2: OPENCV recovers the lens (fx and fy within 0.5%,
    k1, p1, p2, and the distortion within 0.5 px over the inscribed circle, where a lens without
    k2, p1, p2 is off by pixels), and its cameras' rotations are several times closer to the truth
    than SIMPLE_RADIAL's."""
    opts, scene, pairs = _lens_scene(20)
    f, cx, cy = scene.focal, (scene.width - 1) / 2, (scene.height - 1) / 2
    truth = np.array([-0.22, 0.06, 0.004, -0.003])
    lensed = with_lens(scene, "OPENCV", [f, f, cx, cy, *truth])
    gt = gt_from_reconstruction(gt_reconstruction(scene))
    results = {}
    for model in ("SIMPLE_RADIAL", "OPENCV"):
        ws = tmp_path / model
        ws.mkdir()
        write_database(lensed, pairs, ws / "database.db", camera_model=model)
        run_map(ws, MapperOptions(), executor=LocalExecutor(1))
        recon = read_model(ws / "sparse" / "0")
        assert len(recon.registered_image_ids) == 20
        [cam] = recon.cameras.values()
        results[model] = (np.asarray(cam.params), evaluate(recon, gt))
    params, opencv = results["OPENCV"]
    assert abs(params[4] - truth[0]) < 0.01
    np.testing.assert_allclose(params[6:8], truth[2:], atol=5e-4)
    assert _lens_field_error(params[4:8], truth, f, cx, cy, scene.width, scene.height) < 0.5
    np.testing.assert_allclose(params[:2], [f, f], rtol=5e-3)
    radial = results["SIMPLE_RADIAL"][1]
    assert opencv.median_rotation_error_deg < 0.5 * radial.median_rotation_error_deg
    assert opencv.median_center_error < 0.6 * radial.median_center_error
    shutil.rmtree(tmp_path / "SIMPLE_RADIAL")
