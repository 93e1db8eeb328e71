"""``intrinsics_refinement="auto"``: a model's final BAs refine a camera's distortion only where the
data determine it (``sfm.mapper.distortion``).  The test's arithmetic against known answers, and
end to end on a nadir block, the configuration where an undetermined radial distortion bends the
block (Wu, CVPR 2014): a lens without distortion keeps its nominal zero and the rotations its
accuracy, a distorting lens is found."""

from __future__ import annotations

import numpy as np
import pytest

from backend.bundle_adjustment import free_ds2, refine_level
from sfm.evaluation.ground_truth import gt_from_reconstruction
from sfm.evaluation.metrics import evaluate
from sfm.execution.local import LocalExecutor
from sfm.io.colmap_model import read_model
from sfm.mapper.distortion import check_distortion, distortion_components, hold_components, significance_chi2
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import gt_reconstruction, make_scene, with_lens

NOMINAL = np.array([500.0, 500.0, 0.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0])  # Cal3DS2 [fx fy s u0 v0 k1 k2 p1 p2]


@pytest.mark.parametrize("dof, quantile", [(1, 9.0), (2, 11.829), (4, 16.251)])
def test_the_threshold_is_the_two_sided_three_sigma_quantile_of_chi_square(dof, quantile):
    assert significance_chi2(dof) == pytest.approx(quantile, abs=1e-3)  # scipy.stats.chi2.ppf(0.9973, dof)


def test_each_model_tests_its_own_distortion_parameters():
    assert distortion_components("SIMPLE_PINHOLE") == [] and distortion_components("PINHOLE") == []
    assert distortion_components("SIMPLE_RADIAL") == [5]
    assert distortion_components("RADIAL") == [5, 6]
    assert distortion_components("OPENCV") == [5, 6, 7, 8]


@pytest.mark.parametrize("k, accepted", [(0.004, True), (-0.004, True), (0.0029, False), (0.0, False)])
def test_a_radial_coefficient_is_refined_only_beyond_three_sigma(k, accepted):
    estimate = NOMINAL.copy()
    estimate[5] = k
    cov = np.diag([4.0, 4.0, 0.0, 1.0, 1.0, 1e-6, 0.0, 0.0, 0.0])  # std of k1: 0.001
    test = check_distortion("SIMPLE_RADIAL", NOMINAL, estimate, cov)
    assert test.accepted == accepted
    assert test.reason == ("significant" if accepted else "not significant")
    assert test.chi2 == pytest.approx((k / 0.001) ** 2, rel=1e-9)
    assert test.shift == pytest.approx((k,)) and test.std == pytest.approx((0.001,))


def test_the_opencv_model_is_tested_jointly_with_the_correlations():
    """Four parameters, correlated: chi2 = d^T C^-1 d of the 4x4 block, against chi2(4)."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 4))
    block = a @ a.T * 1e-6 + np.eye(4) * 1e-7
    cov = np.zeros((9, 9))
    cov[:5, :5] = np.eye(5)
    cov[5:, 5:] = block
    shift = np.array([1e-3, -2e-3, 5e-4, 1e-4])
    estimate = NOMINAL.copy()
    estimate[5:] += shift
    test = check_distortion("OPENCV", NOMINAL, estimate, cov)
    expected = shift @ np.linalg.solve(block, shift)
    assert test.chi2 == pytest.approx(expected, rel=1e-9)
    assert test.threshold == pytest.approx(significance_chi2(4))
    assert test.accepted == (expected > significance_chi2(4))


def test_without_a_covariance_or_with_a_singular_one_the_distortion_is_refined_as_colmap_does():
    """Only a covariance can show the distortion undetermined; without one, COLMAP's choice."""
    estimate = NOMINAL.copy()
    estimate[5] = 0.001
    test = check_distortion("SIMPLE_RADIAL", NOMINAL, estimate, None)
    assert test.accepted and test.reason == "no covariance: refined as COLMAP does"
    test = check_distortion("SIMPLE_RADIAL", NOMINAL, estimate, np.zeros((9, 9)))
    assert test.accepted and test.reason == "singular covariance: refined as COLMAP does"


@pytest.mark.parametrize("model, index, value, accepted", [
    ("SIMPLE_RADIAL", 5, -0.99, True),  # a strong barrel distortion, but a lens's
    ("SIMPLE_RADIAL", 5, -1.01, False),
    ("SIMPLE_RADIAL", 5, 3.5, False),
    ("OPENCV", 8, 1.2, False),  # any parameter of the model counts, tangential ones too
    ("SIMPLE_RADIAL", 5, float("nan"), False),
])
def test_an_estimate_beyond_any_lens_is_held_however_significant(model, index, value, accepted):
    """COLMAP's limit for a bogus camera (|parameter| <= 1): a small model can fit a wrong focal
    length with such a distortion at a chi-square in the hundreds; with or without a covariance,
    the final BA holds it."""
    estimate = NOMINAL.copy()
    estimate[index] = value
    cov = np.diag([4.0, 4.0, 0.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4, 1e-4])  # std 0.01 of each distortion parameter
    for covariance in (cov, None):
        test = check_distortion(model, NOMINAL, estimate, covariance)
        assert test.accepted == accepted
        if not accepted:
            assert test.reason == "beyond a lens: a parameter above 1 in magnitude"
    assert check_distortion(model, NOMINAL, estimate, cov).std[distortion_components(model).index(index)] == pytest.approx(0.01)


def test_holding_components_solves_the_normal_equations_of_the_rest():
    """With the information matrix L and the right-hand side e of the free components [f, u0, v0,
    k1], the step and covariance from them (L^-1 e, L^-1) restricted to [f, k1] are those of
    the normal equations of [f, k1] alone: L_rr^-1 e_r and L_rr^-1."""
    free = [0, 3, 4, 5]
    rng = np.random.default_rng(1)
    a = rng.normal(size=(4, 4))
    information = a @ a.T + np.eye(4)
    eta = rng.normal(size=4)
    step, cov = np.zeros(9), np.zeros((9, 9))
    step[free] = np.linalg.solve(information, eta)
    cov[np.ix_(free, free)] = np.linalg.inv(information)
    held_step, held_cov = hold_components(step, cov, free, [3, 4])
    rest = [0, 3]  # f and k1 among the free components
    np.testing.assert_allclose(held_step[[0, 5]], np.linalg.solve(information[np.ix_(rest, rest)], eta[rest]), rtol=1e-10)
    np.testing.assert_allclose(held_cov[np.ix_([0, 5], [0, 5])], np.linalg.inv(information[np.ix_(rest, rest)]),
                               rtol=1e-10)
    assert not held_step[[3, 4]].any() and not held_cov[[3, 4]].any()


def test_a_model_without_distortion_has_nothing_to_hold():
    test = check_distortion("PINHOLE", NOMINAL, NOMINAL, None)
    assert test.accepted and test.shift == ()


def test_the_levels_name_what_they_refine():
    assert refine_level(False, False) == "focal" and refine_level(True, False) == "focal_radial"
    assert refine_level(False, True) == "focal_principal" and refine_level(True, True) == "all"
    assert free_ds2("SIMPLE_RADIAL", "focal_principal") == [0, 1, 3, 4]
    assert free_ds2("OPENCV", "all") == [0, 1, 5, 6, 7, 8, 3, 4]


def _nadir_block(lens_k: float):
    """A 36-image nadir block over gently rolling terrain, seen through a SIMPLE_RADIAL lens of
    coefficient ``lens_k`` (0: no distortion), and its ground truth."""
    opts = SynthOptions(scene="aerial", num_images=36, observations_per_image=800, seed=0)
    scene = make_scene(opts)
    if lens_k:
        centre = [(scene.width - 1) / 2, (scene.height - 1) / 2]
        scene = with_lens(scene, "SIMPLE_RADIAL", [scene.focal, *centre, lens_k])
    return scene, simulate_matching(scene, opts), gt_from_reconstruction(gt_reconstruction(scene))


def _map(tmp_path, name, scene, pairs, mode):
    ws = tmp_path / name
    ws.mkdir()
    write_database(scene, pairs, ws / "database.db", camera_model="SIMPLE_RADIAL")
    run_map(ws, MapperOptions(intrinsics_refinement=mode), executor=LocalExecutor(1))
    model = read_model(ws / "sparse" / "0")
    assert len(model.registered_image_ids) == 36
    [camera] = model.cameras.values()
    return model, camera


def test_a_nadir_block_without_distortion_keeps_it_at_zero_and_its_rotations(tmp_path):
    """Without lens distortion, refining the radial coefficient anyway (COLMAP's "focal_radial")
    bends the block: noise sets the coefficient, the rotations follow.  "auto" finds it not
    significant and holds it at the nominal zero; the median rotation error falls by more than
    a tenth."""
    scene, pairs, gt = _nadir_block(0.0)
    refined, refined_camera = _map(tmp_path, "focal_radial", scene, pairs, "focal_radial")
    auto, auto_camera = _map(tmp_path, "auto", scene, pairs, "auto")
    assert refined_camera.params[3] != 0.0 and auto_camera.params[3] == 0.0
    rot_refined = evaluate(refined, gt).median_rotation_error_deg
    rot_auto = evaluate(auto, gt).median_rotation_error_deg
    assert rot_auto < 0.9 * rot_refined, (rot_auto, rot_refined)


def test_a_distorting_lens_is_refined_as_colmap_does(tmp_path):
    """A lens with k = -0.05 over the same block: the distortion is significant, so "auto" gives
    the model "focal_radial" gives, with the coefficient found within 0.005."""
    scene, pairs, _ = _nadir_block(-0.05)
    _, refined_camera = _map(tmp_path, "focal_radial", scene, pairs, "focal_radial")
    _, auto_camera = _map(tmp_path, "auto", scene, pairs, "auto")
    np.testing.assert_array_equal(auto_camera.params, refined_camera.params)
    assert auto_camera.params[3] == pytest.approx(-0.05, abs=0.005)
