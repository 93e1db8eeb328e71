"""How a local model grew, as data: what the recording shows of incremental SfM.

Clusters run in worker processes (or on other machines) that cannot write the run's recording,
so :func:`sfm.mapper.incremental.reconstruct_incremental` fills a :class:`Growth` instead, which
travels back with the models and is logged by the main process (``sfm.viz.mapping``): a
cluster run in the main process and one run by a worker look the same in the recording.

A :class:`Growth` is bounded: per registration the new image's pose, the RMS reprojection error
of the last bundle adjustment and at most ``max_points`` points, a fixed sample of the model's
tracks (the tracks with the smallest hash of their id among the triangulated ones, so a point,
once shown, stays in the sample while it exists); the poses of all registered images (which
every global bundle adjustment moves) only while the model has at most
:data:`ALL_POSES_UP_TO` images and then whenever it has grown by :data:`ALL_POSES_GROWTH`, and
after the final refinement: O(n log n) poses for a model of n images, not O(n^2).
With ``max_points`` 0 (no recording) it keeps no steps at all.  Per model it also keeps, for
each image the model left out, why, and what its final bundle adjustments refined of each
camera: :meth:`Growth.left_out` says why each image is not in the cluster's largest model, and
:meth:`Growth.unjoined` why each other kept model did not join it as a whole, for the run's
report as for the recording.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from backend.camera_models import calibration_matrix
from sfm.mapper.output import mean_colors
from sfm.mapper.state import MIN_POSE_POINTS, MapperState


ALL_POSES_UP_TO = 10  # images: young models move a lot (as EARLY_GLOBAL_BA_IMAGES)
ALL_POSES_GROWTH = 1.2  # then every 20% of growth


@dataclass
class GrowthStep:
    """The model after one registration: ``num_registered`` images, ``new`` the images
    registered by it (two for the initial pair; none for the final refinement), ``posed`` the
    local indices of the images whose ``cam_from_world`` poses this step holds (the new ones, or
    all), ``ba_rms_px`` the last bundle adjustment's RMS reprojection error, ``points`` /
    ``colors`` the sample of points."""

    num_registered: int
    new: list[int]
    posed: np.ndarray
    rotations: np.ndarray  # (n, 3, 3) float32
    translations: np.ndarray  # (n, 3) float32
    ba_rms_px: float
    points: np.ndarray  # (P, 3) float32
    colors: np.ndarray  # (P, 3) uint8


@dataclass
class ModelGrowth:
    """One model's attempt: its steps, whether it was kept (``rank`` among the kept models,
    largest first, as ``clusters/C<k>/<rank>`` is written; -1: too small, dropped), for each
    image of the cluster it does not hold, why (image name -> reason), and what its final
    bundle adjustments decided to refine of each camera (a line per camera)."""

    steps: list[GrowthStep] = field(default_factory=list)
    rank: int = -1
    size: int = 0
    left_out: dict[str, str] = field(default_factory=dict)
    registered: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # when it closed
    all_posed_at: int = 0  # images when the poses of all were last kept
    calibration: list[str] = field(default_factory=list)
    absorbed: bool = False  # joined a later model as a whole (``sfm.mapper.joining``)
    joins: list[str] = field(default_factory=list)  # the earlier models that joined this one, in words
    # the earlier models that did not join this one (their index in Growth.models) -> why, in words
    unjoined: dict[int, str] = field(default_factory=dict)
    taken_apart: str = ""  # why a later model freed its images again, in words (``free_models_grown_far_from``)


@dataclass
class Growth:
    """Every model attempt of one cluster, with the cluster's image names and cameras (each
    image's calibration matrix and size, as the last finished model refined them).  With
    ``max_points`` 0 no step is kept: only what each model left out and why, and its
    calibration."""

    label: str
    names: list[str]
    max_points: int
    models: list[ModelGrowth] = field(default_factory=list)
    min_size: int = 2  # the fewest images of a kept model (set by finish)
    K: np.ndarray | None = None  # (n, 3, 3): each image's calibration, set when a model closes
    sizes: np.ndarray | None = None  # (n, 2) width, height
    _track_rgb: np.ndarray | None = None
    _priority: np.ndarray | None = None

    def record(self, state: MapperState, ba_rms_px: float, new: list[int]) -> None:
        """A step of the current model (a new model starts when the previous one was closed)."""
        if not self.models or self.models[-1].size:
            self.models.append(ModelGrowth())
        if self.max_points <= 0:
            return
        if self._track_rgb is None:
            rows = np.arange(len(state.obs_image))  # grouped by track
            self._track_rgb = mean_colors(state, rows, state.starts)
            ids = np.arange(state.num_tracks, dtype=np.uint64)
            self._priority = (ids * np.uint64(2654435761)) & np.uint64(0xFFFFFFFF)  # Knuth's hash
        valid = np.flatnonzero(state.track_valid)
        if len(valid) > self.max_points:
            valid = valid[np.argpartition(self._priority[valid], self.max_points - 1)[: self.max_points]]
            valid.sort()
        reg = np.flatnonzero(state.registered)
        model = self.models[-1]
        n = len(reg)
        if not new or n <= ALL_POSES_UP_TO or n >= ALL_POSES_GROWTH * model.all_posed_at:
            model.all_posed_at = n
            posed = reg
        else:
            posed = np.array(sorted(new), dtype=np.int64)
        self.models[-1].steps.append(GrowthStep(
            num_registered=n, new=[int(i) for i in new], posed=posed, rotations=state.R[posed].astype(np.float32),
            translations=state.t[posed].astype(np.float32), ba_rms_px=float(ba_rms_px),
            points=state.track_xyz[valid].astype(np.float32), colors=self._track_rgb[valid]))

    def discard(self) -> None:
        """The current model's attempt is dropped (it is grown again from other starting values):
        its steps go."""
        if self.models and not self.models[-1].size:
            self.models.pop()

    def close(self, state: MapperState, calibration: list[str] = ()) -> None:
        """The current model is finished: note why each image outside it is left out, and
        ``calibration``, what its final BAs refined of each camera
        (``SelfCalibration.report``)."""
        if not self.models or self.models[-1].size:
            return
        model = self.models[-1]
        model.size = int(state.num_registered)
        model.registered = np.flatnonzero(state.registered)
        model.calibration = list(calibration)
        self._cameras(state)
        for i in np.flatnonzero(~state.registered):
            model.left_out[self.names[i]] = left_out_reason(state, int(i))

    def absorb(self, index: int, how: str) -> None:
        """Model ``index`` (of :attr:`models`), closed before, joined the current model as a
        whole (``how``: in words, for the recording): it is no longer a model of its own."""
        self.models[index].absorbed = True
        self.models[-1].joins.append(how)

    def not_joined(self, why: dict[int, str]) -> None:
        """The current model's last try to join the earlier models as a whole failed: ``why``
        each did not (index in :attr:`models` -> in words, ``sfm.mapper.joining``)."""
        if self.models:
            self.models[-1].unjoined = dict(why)

    def take_apart(self, index: int, why: str) -> None:
        """Model ``index`` (of :attr:`models`), closed before, was taken apart (``why``: in words,
        for the recording): its images are free again, and it is no longer a model."""
        self.models[index].taken_apart = why

    def finish(self, min_size: int) -> None:
        """Rank the kept models as :func:`reconstruct_incremental` sorts them (largest first,
        stable); attempts below ``min_size`` images stay at rank -1."""
        self.min_size = min_size
        kept = [k for k, m in enumerate(self.models) if m.size >= min_size and not m.absorbed and not m.taken_apart]
        for rank, k in enumerate(sorted(kept, key=lambda k: -self.models[k].size)):
            self.models[k].rank = rank

    def left_out(self) -> dict[str, str]:
        """Why each image of the cluster is not in its largest kept model (image name ->
        reason, in words): the reason that model gave when it closed, or the model of fewer
        than ``min_size`` images that took the image and was dropped, or that no initial
        pair could be reconstructed."""
        kept = [m for m in self.models if m.rank >= 0]
        largest = min(kept, key=lambda m: m.rank) if kept else None
        reasons = dict(largest.left_out) if largest is not None else {}
        for m in self.models:
            if m.rank < 0 and m.size and not m.absorbed and not m.taken_apart:
                for i in m.registered.tolist():
                    reasons[self.names[i]] = (f"registered only in a model of {m.size} images, fewer than the "
                                              f"{self.min_size} a kept model needs")
        held = set() if largest is None else {self.names[i] for i in largest.registered.tolist()}
        return {name: reasons.get(name, "no initial pair could be reconstructed")
                for name in self.names if name not in held}

    def unjoined(self) -> list[str]:
        """Why each kept model other than the largest did not join it as a whole, a line per
        model in rank order: what the later of the two found when it tried
        (``sfm.mapper.joining.estimate_similarity``)."""
        kept = sorted((k for k, m in enumerate(self.models) if m.rank >= 0), key=lambda k: self.models[k].rank)
        lines = []
        for k in kept[1:]:
            model = self.models[k]
            why = self.models[kept[0]].unjoined.get(k) or model.unjoined.get(kept[0])
            if why:
                lines.append(f"model {model.rank} ({model.size} images) did not join model 0 as a whole: {why}")
        return lines

    def _cameras(self, state: MapperState) -> None:
        n = len(self.names)
        if self.K is None:
            self.K, self.sizes = np.zeros((n, 3, 3)), np.zeros((n, 2), np.int64)
        for i in range(n):
            c = state.cam_index[i]
            prior = state.priors[c]
            self.K[i] = calibration_matrix(prior.model, state.params[c])
            self.sizes[i] = prior.width, prior.height


def left_out_reason(state: MapperState, i: int) -> str:
    """Why image ``i`` is not in the model just finished, in words."""
    opts = state.opts
    if state.used[i]:
        return "registered in an earlier model"
    if len(state.image_rows[i]) == 0:
        return f"no pair with {opts.min_num_matches}+ verified inliers inside the cluster"
    visible = len(state.visible_points(i)[0])
    if state.unsupported[i]:
        return (f"registered, but left the model {state.unsupported[i]} time(s) keeping fewer than "
                f"{MIN_POSE_POINTS} points after a BA's filtering: nothing determined its pose")
    if state.failed[i]:
        return (f"PnP RANSAC failed {state.failed[i]} time(s), the last with {state.fail_visible[i]} model points "
                f"in view (it needs {opts.abs_pose_min_num_inliers} inliers, {opts.abs_pose_min_inlier_ratio:.0%} of them)")
    if visible < opts.abs_pose_min_num_inliers:
        return f"sees {visible} points of the model, fewer than the {opts.abs_pose_min_num_inliers} registration needs"
    return "dropped: its camera's intrinsics became degenerate, or the model stopped before reaching it"
