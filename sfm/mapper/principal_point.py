"""Whether a model's data determine a camera's principal point: the test that decides if a final
bundle adjustment keeps the principal point it refined, or holds it at its nominal value.

The principal point of a camera whose intrinsics are not given starts at the image centre, a
nominal value: real lenses and sensors are off it by up to a few percent of the image size, which
the growing model absorbs into its poses and distortion, so the poses carry a systematic error.
COLMAP holds it by default (its documentation calls its estimation ill-posed in general: a young
model cannot tell it from a rotation); refining it always (``intrinsics_refinement="all"``) moves
it on models that do not determine it too.  ``intrinsics_refinement="auto"`` refines it in the final BAs of a model
(every image and every track) and keeps the estimate only when this test, the one of
photogrammetric self-calibration for additional parameters, passes for the camera:

- significant: the shift from the nominal value is larger than its uncertainty explains,
  ``d^T C^-1 d`` above the chi-square quantile of 2 degrees of freedom at 99.73% (the two-sided
  3-sigma level), with ``C`` the principal point's 2x2 covariance from the BA
  (:func:`backend.bundle_adjustment.calibration_step`: poses and points marginalised
  out, scaled by the a-posteriori variance factor);
- determinable: its correlation with every other refined intrinsic (focal length, distortion)
  below :data:`MAX_CORRELATION` in magnitude; above it, the shift is a trade between parameters
  the data do not separate, whatever its apparent significance.

A camera that fails keeps the nominal principal point and the final BA runs again without it.
Nothing here depends on the scene: the test reads only the camera's estimate and its covariance.
That is also its limit: the covariance knows only the modelled parameters, so where lens error the
camera model lacks lets a shifted principal point fit the photos as well as the centred one, the
test can still call the shift significant.  This is why "auto" is an option, not the default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Chi-square quantile of 2 degrees of freedom at 0.9973 (the two-sided 3-sigma probability):
# -2 ln(1 - 0.9973).
SIGNIFICANCE_CHI2 = float(-2.0 * np.log(1.0 - 0.9973))
# Largest correlation magnitude between the principal point and another refined intrinsic that
# still counts as determined (the usual bound for additional parameters in self-calibrating BA).
MAX_CORRELATION = 0.9
PP = (3, 4)  # principal point in the Cal3DS2 vector [fx, fy, s, u0, v0, k1, k2, p1, p2]


@dataclass(frozen=True)
class PrincipalPointTest:
    """The test's figures for one camera: shift from the nominal principal point (px), its
    standard deviations (px), ``d^T C^-1 d``, the largest correlation with another refined
    intrinsic, and the outcome with the reason."""

    accepted: bool
    shift: tuple[float, float]
    std: tuple[float, float]
    chi2: float
    max_correlation: float
    reason: str

    def summary(self) -> str:
        return (f"principal point shift ({self.shift[0]:+.2f}, {self.shift[1]:+.2f}) px, std ({self.std[0]:.2f}, "
                f"{self.std[1]:.2f}) px, chi2 {self.chi2:.1f}, max correlation {self.max_correlation:.2f}: "
                f"{'refined' if self.accepted else 'held'} ({self.reason})")


def check_principal_point(nominal_ds2: np.ndarray, estimate_ds2: np.ndarray, covariance: np.ndarray | None,
                         free: list[int]) -> PrincipalPointTest:
    """The test (module docstring) of an estimate against the nominal value, both Cal3DS2
    vectors, with the estimate's (9, 9) covariance (None: not available, held) and the
    components that were free."""
    shift = np.asarray(estimate_ds2, float)[list(PP)] - np.asarray(nominal_ds2, float)[list(PP)]
    nan2 = (float("nan"), float("nan"))
    if covariance is None:
        return PrincipalPointTest(False, tuple(shift), nan2, float("nan"), float("nan"), "no covariance")
    cov = np.asarray(covariance, float)
    pp_cov = cov[np.ix_(PP, PP)]
    std = np.sqrt(np.maximum(np.diag(pp_cov), 0.0))
    if not np.all(np.isfinite(pp_cov)) or np.any(std <= 0):
        return PrincipalPointTest(False, tuple(shift), tuple(std), float("nan"), float("nan"), "singular covariance")
    chi2 = float(shift @ np.linalg.solve(pp_cov, shift))
    others = [j for j in free if j not in PP]
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = [abs(cov[p, j]) / (sd[p] * sd[j]) for p in PP for j in others if sd[j] > 0]
    max_corr = float(max(corr, default=0.0))
    if max_corr >= MAX_CORRELATION:
        return PrincipalPointTest(False, tuple(shift), tuple(std), chi2, max_corr, "not determinable")
    if chi2 <= SIGNIFICANCE_CHI2:
        return PrincipalPointTest(False, tuple(shift), tuple(std), chi2, max_corr, "not significant")
    return PrincipalPointTest(True, tuple(shift), tuple(std), chi2, max_corr, "significant and determinable")
