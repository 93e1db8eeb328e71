"""Whether a model's data determine a camera's lens distortion: the test that decides if a final
bundle adjustment refines a camera's distortion parameters or holds them at their nominal values.

COLMAP refines the distortion of every camera whose intrinsics are not given, in every global
BA.  Where the photos determine it, that is what a lens needs.  Where they do not, the refined
value is noise, and noise along a direction the data barely constrain costs accuracy elsewhere.
The classic case is a nadir block (parallel viewing directions): radial distortion and a
bending of the whole block, the cameras tilting outwards or inwards with their distance from
the block's centre, explain the images almost equally well (Wu, "Critical configurations for
radial distortion self-calibration", CVPR 2014; the "doming" of photogrammetric blocks).  A
distortion coefficient far below its own uncertainty then moves the rotations of the block's
edges by tenths of a degree.

``intrinsics_refinement="auto"`` (the default) therefore applies to the distortion the test of
photogrammetric self-calibration for additional parameters (Gruen, "Progress in photogrammetric
point determination by compensation of systematic errors and detection of gross errors", 1978):
a final BA refines a camera's distortion only when its estimate differs from the nominal values
(the database's: zero unless ``--intrinsics`` or a camera prior gave others) by more than its
uncertainty explains, ``d^T C^-1 d`` above the chi-square quantile of as many degrees of freedom
as the model has distortion parameters at 99.73% (the two-sided 3-sigma level), with ``C`` their
covariance from the BA (:func:`backend.calibration_step.calibration_step`: poses and points
marginalised out, scaled by the a-posteriori variance factor).  Otherwise the camera keeps its
nominal distortion in that BA.  Without a covariance (a singular system) nothing shows the
distortion undetermined, and it is refined, as COLMAP does.  An estimate no lens has, a parameter
above ``MAX_EXTRA_PARAM`` in magnitude (COLMAP's limit for a bogus camera), is held whatever its
chi-square: a small model's data can fit the geometry of a wrong focal length with such a value
at high significance, and a final BA that refines it bends the model's poses by degrees.  The
estimate and covariance are those of COLMAP's camera model, the principal point held where it is
(:func:`hold_components`): the distortion is the first additional parameter a camera gets, and
the principal point is tested after it (``sfm.mapper.principal_point``).  Freeing the principal
point too would widen the distortion's uncertainty by their correlation and hold the distortion
of a real lens whose principal point is also off centre.  Every growing BA still refines the
distortion (a young model needs it to register the next images); only the model's final BAs,
with every image and every track, decide.  Nothing here depends on the scene: the test reads
only the camera's estimates and their covariance.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import chdtri

from backend.bundle_adjustment import free_ds2
from backend.camera_models import MAX_EXTRA_PARAM

# The probability of the two-sided 3-sigma interval, the level of the significance test.
SIGNIFICANCE_LEVEL = 0.9973


@lru_cache(maxsize=None)
def significance_chi2(dof: int) -> float:
    """Chi-square quantile of ``dof`` degrees of freedom at :data:`SIGNIFICANCE_LEVEL` (SciPy's
    inverse of the upper tail, ``chdtri``: ``scipy.stats`` is a heavy import for every process
    that maps)."""
    return float(chdtri(dof, 1.0 - SIGNIFICANCE_LEVEL))


def chi_square(change: np.ndarray, covariance: np.ndarray) -> float:
    """``d^T C^-1 d`` of a ``change`` d with ``covariance`` C; NaN when C is singular."""
    try:
        return float(change @ np.linalg.solve(covariance, change))
    except np.linalg.LinAlgError:
        return float("nan")


def distortion_components(model: str) -> list[int]:
    """Where ``model``'s distortion parameters sit in the Cal3DS2 vector [fx, fy, s, u0, v0, k1,
    k2, p1, p2] (empty for the pinhole models)."""
    return [j for j in free_ds2(model, "focal_radial") if j > 1]


def hold_components(step: np.ndarray, covariance: np.ndarray, free: list[int],
                    held: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton step and covariance of a Cal3DS2 calibration with the components
    ``held`` held at their current values, from the step and covariance with the components
    ``free`` free (``held`` among them): the normal equations ``Lambda step = eta`` restricted
    to the rest, with ``Lambda`` the inverse of the covariance (up to the variance factor, which
    the restricted covariance keeps)."""
    rest = [j for j in free if j not in held]
    information = np.linalg.inv(np.asarray(covariance, float)[np.ix_(free, free)])
    eta = information @ np.asarray(step, float)[free]
    keep = [free.index(j) for j in rest]
    rest_cov = np.linalg.inv(information[np.ix_(keep, keep)])
    out_step, out_cov = np.zeros(9), np.zeros((9, 9))
    out_step[rest] = rest_cov @ eta[keep]
    out_cov[np.ix_(rest, rest)] = rest_cov
    return out_step, out_cov


@dataclass(frozen=True)
class DistortionTest:
    """The test's figures for one camera: the estimate's difference from the nominal distortion,
    its standard deviations, ``d^T C^-1 d`` and the quantile it is compared with, and the
    outcome with the reason."""

    accepted: bool
    shift: tuple[float, ...]
    std: tuple[float, ...]
    chi2: float
    threshold: float
    reason: str
    beyond_lens: bool = False  # held because the estimate is beyond any lens (``MAX_EXTRA_PARAM``)

    def summary(self) -> str:
        shift = ", ".join(f"{v:+.3g}" for v in self.shift)
        std = ", ".join(f"{v:.3g}" for v in self.std)
        return (f"distortion ({shift}) from nominal, std ({std}), chi2 {self.chi2:.1f} against {self.threshold:.1f}: "
                f"{'refined' if self.accepted else 'held'} ({self.reason})")


def check_distortion(model: str, nominal_ds2: np.ndarray, estimate_ds2: np.ndarray,
                     covariance: np.ndarray | None) -> DistortionTest:
    """The test (module docstring) of an estimate against the nominal value, both Cal3DS2
    vectors, with the estimate's (9, 9) covariance.  An estimate beyond any lens (a parameter
    above ``MAX_EXTRA_PARAM`` in magnitude, or not finite) is held.  Otherwise, without a usable
    covariance (None, or singular) nothing shows the distortion undetermined: refined, as COLMAP
    does.  A model without distortion parameters has nothing to hold: accepted."""
    comps = distortion_components(model)
    if not comps:
        return DistortionTest(True, (), (), 0.0, 0.0, "the model has no distortion")
    estimate = np.asarray(estimate_ds2, float)[comps]
    shift = estimate - np.asarray(nominal_ds2, float)[comps]
    threshold = significance_chi2(len(comps))
    cov = None if covariance is None else np.asarray(covariance, float)[np.ix_(comps, comps)]
    std = np.full(len(comps), np.nan) if cov is None else np.sqrt(np.maximum(np.diag(cov), 0.0))
    if not np.all(np.abs(estimate) <= MAX_EXTRA_PARAM):  # NaN fails too
        return DistortionTest(False, tuple(shift), tuple(std), float("nan"), threshold,
                              f"beyond a lens: a parameter above {MAX_EXTRA_PARAM:g} in magnitude", beyond_lens=True)
    if cov is None:
        return DistortionTest(True, tuple(shift), tuple(std), float("nan"), threshold, "no covariance: refined as COLMAP does")
    singular = DistortionTest(True, tuple(shift), tuple(std), float("nan"), threshold,
                              "singular covariance: refined as COLMAP does")
    if not np.all(np.isfinite(cov)) or np.any(std <= 0):
        return singular
    chi2 = chi_square(shift, cov)
    if not np.isfinite(chi2):
        return singular
    if chi2 <= threshold:
        return DistortionTest(False, tuple(shift), tuple(std), chi2, threshold, "not significant")
    return DistortionTest(True, tuple(shift), tuple(std), chi2, threshold, "significant")
