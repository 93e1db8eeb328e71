"""The data of a bundle adjustment: the problem, the options, the result.

Conventions: poses are ``cam_from_world`` (x_cam = R X + t, OpenCV axes: x right, y down, z
forward); intrinsics are COLMAP camera models per camera group (:mod:`backend.camera_models`);
the pixel convention is the caller's, as long as principal points and observations agree.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from backend.camera_models import reprojection_errors

Array = np.ndarray


@dataclass(frozen=True)
class BAProblem:
    """One bundle adjustment problem: cameras, poses, points, observations and what is held.

    camera_models (G,), camera_params (G,): COLMAP model name and parameter vector of each
        camera group (:mod:`backend.camera_models`); image_camera (N,): each image's group.
    rotations (N,3,3), translations (N,3): each image's ``cam_from_world``.
    points (P,3): world points.
    obs_image (M,), obs_point (M,), obs_xy (M,2): observation m sees point ``obs_point[m]`` in
        image ``obs_image[m]`` at pixel ``obs_xy[m]``.
    obs_sigma (M,): each observation's standard deviation in pixels (None: 1 px each); the
        robust loss acts on the whitened error, so an observation's loss scale is
        ``BAOptions.loss_scale`` times its sigma.
    fixed_poses: images whose poses are held (returned exactly as given).
    """

    camera_models: Sequence[str]
    camera_params: Sequence[Array]
    image_camera: Array
    rotations: Array
    translations: Array
    points: Array
    obs_image: Array
    obs_point: Array
    obs_xy: Array
    obs_sigma: Array | None = None
    fixed_poses: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        num_obs = len(self.obs_image)
        if len(self.obs_point) != num_obs or len(self.obs_xy) != num_obs:
            raise ValueError("obs_image, obs_point and obs_xy must have one row per observation")
        if self.obs_sigma is not None and np.shape(self.obs_sigma) != (num_obs,):
            raise ValueError(f"obs_sigma must hold {num_obs} values, one per observation")

    def reprojection_errors(self) -> Array:
        """Pixel distance (M,) between each observation and its projected point; inf behind the
        camera (:func:`backend.camera_models.reprojection_errors`)."""
        points = np.asarray(self.points, float)[np.asarray(self.obs_point, np.int64)]
        return reprojection_errors(self.camera_models, self.camera_params, np.asarray(self.image_camera, np.int64),
                                   np.asarray(self.rotations, float), np.asarray(self.translations, float),
                                   self.obs_image, points, np.asarray(self.obs_xy, float))

    def observations(self, mask: Array) -> BAProblem:
        """The same problem over the observations selected by ``mask``."""
        sigma = None if self.obs_sigma is None else np.asarray(self.obs_sigma)[mask]
        return replace(self, obs_image=np.asarray(self.obs_image)[mask], obs_point=np.asarray(self.obs_point)[mask],
                       obs_xy=np.asarray(self.obs_xy)[mask], obs_sigma=sigma)


@dataclass(frozen=True)
class BAOptions:
    """Options of :func:`backend.bundle_adjustment.bundle_adjust`.

    loss, loss_scale: robust loss on each observation's pixel error, "huber" (default),
        "cauchy" or "none", with its scale in pixels (default 1.0; times the observation's
        sigma when ``bundle_adjust`` is given sigmas). Huber at 1 px is the GTSAM
        analogue of COLMAP's local-BA soft-L1 at scale 1: quadratic core, linear tails, convex
        (so no new local minima), yet a 50 px outlier pulls 50x less than under least squares.
        "none" is COLMAP's global-BA default, right when outliers were already filtered.
    refine_intrinsics: "none" | "focal" | "focal_radial" (focal + the model's distortion, the
        default, as COLMAP) | "focal_principal" (focal + principal point, the distortion held) |
        "all" (focal, distortion and principal point); or one of these per camera group (a
        sequence as long as ``BAProblem.camera_models``).
    gauge_pose: image whose pose anchors the gauge when ``BAProblem.fixed_poses`` is empty (None: the
        first image with observations). Gauge: with no fixed pose, a prior on that pose plus a
        prior on the distance from its centre to the farthest camera centre (the scale); with
        one fixed pose, only that distance prior; with two or more, none (they fix all 7 dof).
    max_iterations, relative_tolerance, absolute_tolerance: Levenberg-Marquardt stopping rules
        (tolerances on the decrease of the total cost 0.5 * sum rho(err²); 1e-5 is GTSAM's
        default: robust losses converge linearly in the tail, where a tighter tolerance costs
        many iterations for a change far below the observations' noise).
    ordering: "auto" (default: "points_first" up to ``backend.gtsam_solver.AUTO_METIS_OBSERVATIONS`` observations,
        "points_then_metis" above), "points_first" (every point, then calibrations and poses, the
        Schur ordering of BA: nothing to compute, which pays on small problems),
        "points_then_metis" (every point, then the poses in METIS's nested-dissection order of
        their co-visibility graph, the reduced camera system's structure, then calibrations),
        "metis" or "colamd" (GTSAM's, on the whole graph).  The points come first either way;
        the cameras' order decides the fill of the reduced camera system: in key order, a large
        block's holds dense blocks over all the cameras between two that share points, several
        times the memory and time of METIS's; METIS on the whole graph reaches the same fill
        but takes seconds to compute on a large BA, on the cameras' graph a fraction of one.
    optimizer: "lm" (Levenberg-Marquardt, default) or "gauss_newton_or_lm" (Gauss-Newton while
        every step lowers the cost, else LM from the start: from a good start Gauss-Newton
        takes LM's steps without its damping and step control,
        ``backend.gtsam_solver.gauss_newton_or_lm``).
    predictive_stop: also stop once the last two iterations' relative decreases shrink so fast
        that the rest of the series (geometric: ``d_k r / (1 - r)``, ``r = d_k / d_(k-1)``) is
        below ``relative_tolerance`` (``backend.gtsam_solver.predicted_rest``): the iteration
        that would only confirm convergence is skipped.  Meant for BAs that later BAs refine
        again; a slow, steady creep (``r`` near 1) is never cut short.
    verbose: log every LM iteration at INFO (otherwise DEBUG).
    on_iteration: called as ``on_iteration(iteration, cost_before, cost_after)`` after each
        iteration (a progress display; it must not raise).
    """

    loss: str = "huber"
    loss_scale: float = 1.0
    refine_intrinsics: str | tuple[str, ...] = "focal_radial"
    gauge_pose: int | None = None
    max_iterations: int = 100
    relative_tolerance: float = 1e-5
    absolute_tolerance: float = 1e-6
    ordering: str = "auto"
    optimizer: str = "lm"
    predictive_stop: bool = False
    verbose: bool = False
    on_iteration: Callable[[int, float, float], None] | None = field(default=None, compare=False)


@dataclass(frozen=True)
class BAResult:
    """Result of :func:`backend.bundle_adjustment.bundle_adjust`; errors are pixel distances
    (:func:`backend.camera_models.reprojection_errors`).

    rotations (N,3,3), translations (N,3): optimised cam_from_world poses; points (P,3);
    camera_params: one parameter vector per camera group (the input model's layout);
    initial_rms / final_rms: RMS reprojection error over all observations; final_mean_error;
    iterations; time_s (graph building + optimisation); num_observations;
    success: the optimiser ran and did not increase the cost; converged: it stopped before
    max_iterations; last_decrease: the relative cost decrease of its last iteration (0 when it
    made none; the largest over the parts of a partitioned BA), which says how far from the
    optimum a loose ``relative_tolerance`` stopped it; initial_cost / final_cost: GTSAM's cost
    (half the sum of the robust losses of the whitened errors, priors included; summed over the
    parts of a partitioned BA); stopped: why the optimiser stopped, in words
    (``backend.gtsam_solver.stop_reason``); solver_messages: the lines GTSAM's C++ code
    printed (a ``CheiralityException`` each), kept off the terminal.
    """

    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    camera_params: tuple[np.ndarray, ...]
    initial_rms: float
    final_rms: float
    final_mean_error: float
    iterations: int
    time_s: float
    num_observations: int
    success: bool
    converged: bool
    last_decrease: float = 0.0
    initial_cost: float = float("nan")
    final_cost: float = float("nan")
    stopped: str = ""
    solver_messages: int = 0
