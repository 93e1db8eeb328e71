"""``intrinsics_refinement="auto"``: a model's final BAs refine a camera's principal point only
where the data determine it (``sfm.mapper.principal_point``), so an off-centre principal point is
found and a centred one is left at its nominal value."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sfm.evaluation.ground_truth import gt_from_reconstruction
from sfm.evaluation.metrics import evaluate
from sfm.execution.local import LocalExecutor
from sfm.io.colmap_model import read_model
from sfm.mapper.principal_point import MAX_CORRELATION, SIGNIFICANCE_CHI2, check_principal_point
from sfm.mapper.options import MapperOptions
from sfm.stages.map import run_map
from sfm.synthetic.matching import simulate_matching, write_database
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import gt_reconstruction, make_scene

NOMINAL = np.array([500.0, 500.0, 0.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0])  # Cal3DS2 [fx fy s u0 v0 k1 k2 p1 p2]
FREE = [0, 1, 3, 4, 5]  # fx, fy, u0, v0, k1


def _covariance(std_pp: float, corr_with_focal: float = 0.0) -> np.ndarray:
    cov = np.diag([4.0, 4.0, 1e-12, std_pp**2, std_pp**2, 1e-6, 1e-12, 1e-12, 1e-12])
    cov[0, 3] = cov[3, 0] = corr_with_focal * 2.0 * std_pp
    return cov


def test_the_threshold_is_the_two_sided_three_sigma_quantile_of_chi_square_two():
    assert SIGNIFICANCE_CHI2 == pytest.approx(11.829, abs=1e-3)  # scipy.stats.chi2.ppf(0.9973, 2)


@pytest.mark.parametrize("shift, std, corr, accepted, reason", [
    ((6.0, -4.0), 1.0, 0.0, True, "significant and determinable"),    # chi2 52
    ((2.0, 2.0), 1.0, 0.0, False, "not significant"),                 # chi2 8 < 11.83
    ((3.0, 2.0), 1.0, 0.0, True, "significant and determinable"),     # chi2 13 > 11.83
    ((6.0, -4.0), 1.0, 0.95, False, "not determinable"),              # traded against the focal length
])
def test_a_shift_is_kept_only_when_significant_and_determinable(shift, std, corr, accepted, reason):
    estimate = NOMINAL.copy()
    estimate[[3, 4]] += shift
    test = check_principal_point(NOMINAL, estimate, _covariance(std, corr), FREE)
    assert (test.accepted, test.reason) == (accepted, reason)
    assert test.chi2 == pytest.approx((shift[0] ** 2 + shift[1] ** 2) / std**2, rel=1e-9)  # the 2x2 block of C
    assert test.max_correlation == pytest.approx(corr, abs=1e-12)
    assert (test.max_correlation >= MAX_CORRELATION) == (reason == "not determinable")


def test_without_a_covariance_the_nominal_value_is_held():
    test = check_principal_point(NOMINAL, NOMINAL + 1.0, None, FREE)
    assert not test.accepted and test.reason == "no covariance"


def test_auto_finds_an_off_centre_principal_point_and_holds_a_centred_one(tmp_path):
    """Keypoints of a 16-image orbit moved by (20, -12) px: the camera's principal point is off
    the image centre the database states.  Holding it (COLMAP's default, "focal_radial") the
    poses absorb the offset; "auto" finds it within 1.5 px and the rotations come back to the
    centred scene's accuracy.  On the centred scene "auto" holds it: the same model as
    "focal_radial"."""
    opts = SynthOptions(scene="orbit", num_images=16, observations_per_image=800, seed=3)
    scene = make_scene(opts)
    pairs = simulate_matching(scene, opts)
    gt = gt_from_reconstruction(gt_reconstruction(scene))
    centre = np.array([(scene.width - 1) / 2, (scene.height - 1) / 2])
    runs = {}
    for shift, mode in (((0, 0), "focal_radial"), ((0, 0), "auto"), ((20, -12), "focal_radial"), ((20, -12), "auto")):
        ws = tmp_path / f"{shift[0]}_{mode}"
        ws.mkdir()
        moved = replace(scene, keypoints=[k + np.array(shift, float) for k in scene.keypoints])
        write_database(moved, pairs, ws / "database.db", camera_model="SIMPLE_RADIAL")
        run_map(ws, MapperOptions(intrinsics_refinement=mode), executor=LocalExecutor(1))
        recon = read_model(ws / "sparse" / "0")
        assert len(recon.registered_image_ids) == 16
        [cam] = recon.cameras.values()
        runs[shift, mode] = (np.asarray(cam.params)[1:3] - centre, evaluate(recon, gt).median_rotation_error_deg)
    (pp_c, rot_c), (pp_ca, rot_ca) = runs[(0, 0), "focal_radial"], runs[(0, 0), "auto"]
    np.testing.assert_array_equal(pp_ca, [0.0, 0.0])
    assert rot_ca == rot_c
    (_, rot_held), (pp_found, rot_found) = runs[(20, -12), "focal_radial"], runs[(20, -12), "auto"]
    np.testing.assert_allclose(pp_found, [20.0, -12.0], atol=1.5)
    assert rot_held > 5 * rot_c            # the held offset bends the poses
    assert rot_found < 1.5 * rot_c         # found, they are as good as on the centred scene
