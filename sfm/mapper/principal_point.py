"""Whether a model's data determine a camera's principal point: the test that decides if a final
bundle adjustment keeps the principal point it refined, or holds it at its nominal value.

The principal point of a camera whose intrinsics are not given starts at the image centre, a
nominal value: real lenses and sensors are off it by up to a few percent of the image size, which
the growing model absorbs into its poses and distortion, so the poses carry a systematic error.
COLMAP holds it by default (its documentation calls its estimation ill-posed in general: a young
model cannot tell it from a rotation); refining it always (``intrinsics_refinement="all"``) moves
it on models that do not determine it too.  ``intrinsics_refinement="auto"`` (the default)
refines it in the final BAs of a model (every image and every track) only for the cameras that
pass this test, the one of photogrammetric self-calibration for additional parameters followed by
a split-sample check:

- significant: the shift from the nominal value is larger than its uncertainty explains,
  ``d^T C^-1 d`` above the chi-square quantile of 2 degrees of freedom at 99.73% (the two-sided
  3-sigma level), with ``C`` the principal point's 2x2 covariance from the BA
  (:func:`backend.calibration_step.calibration_step`: poses and points marginalised
  out, scaled by the a-posteriori variance factor);
- determinable: its correlation with every other refined intrinsic (focal length, distortion)
  below :data:`MAX_CORRELATION` in magnitude; above it, the shift is a trade between parameters
  the data do not separate, whatever its apparent significance;
- reproducible: the two halves of the camera's images on either side of the median of their
  centres along the centres' principal axis (:func:`split_halves`), each bundle-adjusted on its
  own with the principal point free, give a significant shift from their own estimates
  (:func:`confirm_by_halves`): their weighted mean (the minimum-variance combination of two
  independent estimates, each weighed by its inverse covariance, so a half that sees the
  principal point poorly counts for little), with its covariance widened by the Birge ratio of
  metrology where they disagree beyond their covariances (``d^T (C_a + C_b)^-1 d`` for the
  difference ``d``, the chi-square of the two about their weighted mean, above the same 3-sigma
  quantile; the ratio is that chi-square over its 2 degrees of freedom, 1 on average when the
  covariances are right).  A chi-square within the quantile is the scatter the covariances
  predict, and widening by it would discount halves that agree.  This is split-sample
  validation: the principal point is one constant of the camera, so independent photos of it
  must give the same value.  A shift that is instead lens or sensor error the camera model
  lacks (decentering distortion, a sensor not parallel to the lens, rolling shutter), which the
  covariance cannot see because it knows only the modelled parameters, shows up as estimates
  that depend on where the photos were taken from, and the widened uncertainty swallows it.
  Where a half alone could not call the whole model's shift ``s`` significant (``s^T C_half^-1
  s`` at most the same quantile), the halves cannot confirm the shift.  They can still
  contradict it: halves that disagree beyond their uncertainty (the chi-square of their
  difference above the quantile too) show a shift that depends on the viewpoint, and the
  weighted mean decides as above.  Halves that agree within it are evidence neither for nor
  against the shift: the step abstains and the first two decide.  An object ring photographed
  in few, wide steps is such a case: each half loses the ring's closure, on which the
  principal point rests.

A camera that fails keeps its nominal principal point in that final BA.
Nothing here depends on the scene: the test reads only the camera's estimates and their
covariances.  The halves need :data:`MIN_HALF_IMAGES` images each; a camera with fewer keeps
its nominal principal point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sfm.mapper.distortion import chi_square

# Chi-square quantile of 2 degrees of freedom at 0.9973 (the two-sided 3-sigma probability):
# -2 ln(1 - 0.9973).
SIGNIFICANCE_CHI2 = float(-2.0 * np.log(1.0 - 0.9973))
# Largest correlation magnitude between the principal point and another refined intrinsic that
# still counts as determined (the usual bound for additional parameters in self-calibrating BA).
MAX_CORRELATION = 0.9
PP = (3, 4)  # principal point in the Cal3DS2 vector [fx, fy, s, u0, v0, k1, k2, p1, p2]
# Fewest images in each half of the split-sample test: three views, the fewest that fix a
# camera's calibration from image observations alone (the classical self-calibration minimum).
MIN_HALF_IMAGES = 3


@dataclass(frozen=True)
class PrincipalPointTest:
    """The test's figures for one camera: shift from the nominal principal point (px), its
    standard deviations (px), ``d^T C^-1 d``, the largest correlation with another refined
    intrinsic, the halves' estimates of the shift and the chi-square of their difference (nan
    where that step did not run), and the outcome with the reason."""

    accepted: bool
    shift: tuple[float, float]
    std: tuple[float, float]
    chi2: float
    max_correlation: float
    reason: str
    halves_shift: tuple[tuple[float, float], tuple[float, float]] | None = None
    halves_chi2: float = float("nan")

    def summary(self) -> str:
        return (f"principal point shift ({self.shift[0]:+.2f}, {self.shift[1]:+.2f}) px, std ({self.std[0]:.2f}, "
                f"{self.std[1]:.2f}) px, chi2 {self.chi2:.1f}, max correlation {self.max_correlation:.2f}"
                + (f", halves ({self.halves_shift[0][0]:+.2f}, {self.halves_shift[0][1]:+.2f}) and "
                   f"({self.halves_shift[1][0]:+.2f}, {self.halves_shift[1][1]:+.2f}) px, chi2 {self.halves_chi2:.1f}"
                   if self.halves_shift is not None else "")
                + f": {'refined' if self.accepted else 'held'} ({self.reason})")


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


def split_halves(centers: np.ndarray) -> np.ndarray:
    """The split of the split-sample test: for camera centres (N, 3), a boolean mask of the
    images on the low side of the median along the centres' principal axis (the direction of
    their largest spread).  The two halves see the scene from the two ends of the camera path,
    so an estimate that depends on the viewpoint differs between them."""
    centers = np.asarray(centers, float)
    spread = centers - centers.mean(axis=0)
    axis = np.linalg.svd(spread, full_matrices=False)[2][0]
    along = spread @ axis
    return along < np.median(along) if len(centers) % 2 == 0 else along <= np.median(along)


def confirm_by_halves(test: PrincipalPointTest, nominal_ds2: np.ndarray,
                      halves: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None) -> PrincipalPointTest:
    """``test`` (accepted by :func:`check_principal_point`) completed by the split-sample step:
    ``halves`` the two halves' (Cal3DS2 estimate, (9, 9) covariance), None when they could not be
    estimated (too few images, a singular system).  Where a half has no power to see the
    shift, ``s^T C_a^-1 s`` or ``s^T C_b^-1 s`` of the whole model's shift ``s`` at most
    :data:`SIGNIFICANCE_CHI2`, and the halves agree, ``d^T (C_a + C_b)^-1 d`` at most the same,
    ``test`` stands (refined).  Otherwise refined only if the halves' weighted mean shift from
    the nominal value, ``m = C_m (C_a^-1 p_a + C_b^-1 p_b) - nominal`` with ``C_m = (C_a^-1 +
    C_b^-1)^-1``, is significant: ``m^T C_m^-1 m`` above :data:`SIGNIFICANCE_CHI2`, with ``C_m``
    times the squared Birge ratio ``d^T (C_a + C_b)^-1 d / 2`` of their difference ``d = p_a -
    p_b`` where the halves disagree (that chi-square above :data:`SIGNIFICANCE_CHI2` too).
    Halves of equal covariance give the plain mean with ``C_m = C_a / 2``."""
    if halves is None:
        return replace(test, accepted=False, reason=f"halves not estimable (fewer than {MIN_HALF_IMAGES} images each, "
                                                    "or singular)")
    nominal = np.asarray(nominal_ds2, float)[list(PP)]
    (a, cov_a), (b, cov_b) = halves
    pa, pb = np.asarray(a, float)[list(PP)], np.asarray(b, float)[list(PP)]
    ca, cb = np.asarray(cov_a, float)[np.ix_(PP, PP)], np.asarray(cov_b, float)[np.ix_(PP, PP)]
    d = pa - pb
    chi2 = chi_square(d, ca + cb)
    shifts = (tuple(pa - nominal), tuple(pb - nominal))
    if not np.isfinite(chi2):
        return replace(test, accepted=False, reason="halves not estimable (singular covariance)", halves_shift=shifts)
    power = min(chi_square(np.asarray(test.shift, float), c) for c in (ca, cb))  # NaN: singular
    if not power > SIGNIFICANCE_CHI2 and chi2 <= SIGNIFICANCE_CHI2:  # no evidence either way: the step abstains
        return replace(test, halves_shift=shifts, halves_chi2=chi2,
                       reason=f"significant and determinable; the halves cannot check it: a half sees the shift at "
                              f"chi2 {power:.1f}, and they agree (chi2 {chi2:.1f})")
    try:
        info_a, info_b = np.linalg.inv(ca), np.linalg.inv(cb)
        cov_mean = np.linalg.inv(info_a + info_b)
    except np.linalg.LinAlgError:
        return replace(test, accepted=False, reason="halves not estimable (singular covariance)", halves_shift=shifts)
    mean = cov_mean @ (info_a @ pa + info_b @ pb) - nominal
    disagree = chi2 > SIGNIFICANCE_CHI2
    widened = float(mean @ np.linalg.solve(cov_mean * (chi2 / 2.0 if disagree else 1.0), mean))
    if widened <= SIGNIFICANCE_CHI2:
        spread = " with their spread" if disagree else ""
        return replace(test, accepted=False, halves_shift=shifts, halves_chi2=chi2,
                       reason=f"not reproducible: chi2 {widened:.1f} of the halves' weighted mean shift{spread}")
    return replace(test, halves_shift=shifts, halves_chi2=chi2,
                   reason=f"significant, determinable and reproducible: chi2 {widened:.1f} of the halves' weighted mean shift")
