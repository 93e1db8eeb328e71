"""Synthetic scenes with exact ground truth, written straight into a COLMAP-schema database.

Three correspondence-level scenes of any size, for tests and benchmarks:

* ``orbit``: a ring of cameras around a bumpy sphere (an object-centred capture);
* ``street``: a forward-moving camera between two facades above a ground plane; with ``twins``,
  stretches of facade that stand, identical, at two places along the street (repeated
  structures: their features match as if they were one, :func:`street_twins`);
* ``aerial``: a nadir grid over hilly terrain with ~70% forward and side overlap.

Every 3D point is seen by the cameras whose frustum holds it, within a maximum distance and a
maximum angle to the surface normal (features are not matched across much larger viewpoint
changes), so track lengths and pair overlaps behave like real captures.  The number of points is
chosen so that an image sees ``observations_per_image`` points on average.

Matching is simulated in ``sfm.synthetic.matching``: the raw matches of a pair are its true
correspondences plus a share ``outlier_ratio`` of random wrong ones; verification keeps a random
share (``recall``) of the true ones and lets a few outliers through (``verified_outlier_ratio``
of the inliers), and those survivors lie near the epipolar line, as real RANSAC survivors do.
All randomness comes from ``seed``.

Pixels follow OpenCV's convention internally (see ``sfm.core.model``); the database layer shifts them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from backend.geometry import look_at, rotation_about_axis
from sfm.synthetic.options import SynthOptions

log = logging.getLogger(__name__)

@dataclass
class SyntheticScene:
    """Ground truth of a scene: one PINHOLE-like camera (no distortion), poses, points, and
    the keypoints of each image with the index of the GT observation behind each."""

    width: int
    height: int
    focal: float
    names: list[str]
    rotations: np.ndarray  # (N, 3, 3) cam_from_world
    translations: np.ndarray  # (N, 3)
    points: np.ndarray  # (P, 3)
    obs_image: np.ndarray  # (M,) image index of each observation
    obs_point: np.ndarray  # (M,) point index
    obs_keypoint: np.ndarray  # (M,) keypoint index in its image
    keypoints: list[np.ndarray] = field(default_factory=list)  # per image (K_i, 2), noisy
    # (P,) what each point looks like: points of one label match each other (a twin's copy has
    # its original's label); None: every point looks unique
    appearance: np.ndarray | None = None

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        return np.array(
            [[self.focal, 0, (self.width - 1) / 2], [0, self.focal, (self.height - 1) / 2], [0, 0, 1]]
        )

    @property
    def centers(self) -> np.ndarray:
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)


# ---------------------------------------------------------------------------------- cameras
def _orbit_cameras(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    radius = 10.0
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rs, ts = [], []
    for a in angles:
        center = np.array([radius * np.cos(a), radius * np.sin(a), 1.5 * np.sin(3 * a)])
        target = rng.normal(0, 0.3, 3)
        r, t = look_at(center, target, up=np.array([0.0, 0.0, 1.0]))
        rs.append(r)
        ts.append(t)
    return np.array(rs), np.array(ts), 1e9


def _street_cameras(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    rs, ts = [], []
    for i in range(n):
        center = np.array([1.0 * i, rng.normal(0, 0.3), 1.6 + rng.normal(0, 0.05)])
        yaw = rng.normal(0, 8.0)
        forward = rotation_about_axis([0, 0, 1], yaw) @ np.array([1.0, 0.0, 0.0])
        r, t = look_at(center, center + forward, up=np.array([0.0, 0.0, 1.0]))
        rs.append(r)
        ts.append(t)
    return np.array(rs), np.array(ts), 35.0


def _aerial_grid(n: int, footprint: tuple[float, float], overlap: float) -> np.ndarray:
    cols = max(1, int(np.ceil(np.sqrt(n))))
    rows = int(np.ceil(n / cols))
    step_x, step_y = (1 - overlap) * footprint[0], (1 - overlap) * footprint[1]
    centres = []
    for r in range(rows):
        order = range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)  # serpentine flight
        centres.extend((c * step_x, r * step_y) for c in order)
    return np.array(centres[:n])


def _aerial_cameras(n: int, rng: np.random.Generator, opts: SynthOptions, focal: float):
    altitude = 100.0
    footprint = (altitude * opts.width / focal, altitude * opts.height / focal)
    xy = _aerial_grid(n, footprint, overlap=0.7)
    rs, ts = [], []
    for x, y in xy:
        center = np.array([x, y, altitude]) + rng.normal(0, [1.0, 1.0, 0.5])
        r, t = look_at(center, center - np.array([0, 0, 1.0]), up=np.array([0.0, 1.0, 0.0]))
        tilt = rotation_about_axis(rng.normal(size=3), rng.normal(0, 2.0))
        r = tilt @ r
        rs.append(r)
        ts.append(-r @ center)
    half_diag = 0.5 * np.hypot(*footprint)
    return np.array(rs), np.array(ts), 1.2 * np.hypot(altitude, half_diag)


# ---------------------------------------------------------------------------------- points
# The street's facades stand at y = +-FACADE_Y_M (left and right of the walked line y = 0).
FACADE_Y_M = 8.0

def _sample_points(scene: str, centers: np.ndarray, count: int, rng: np.random.Generator):
    """``count`` surface points and their unit normals for a scene."""
    if scene == "orbit":
        d = rng.normal(size=(count, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        bumps = 0.2 * np.sin(5 * d[:, 0]) * np.cos(4 * d[:, 1]) + 0.1 * np.sin(7 * d[:, 2])
        return (3.0 + bumps)[:, None] * d, d
    if scene == "street":
        x0, x1 = centers[:, 0].min() - 10, centers[:, 0].max() + 40
        which = rng.choice(3, size=count, p=[0.4, 0.4, 0.2])
        x = rng.uniform(x0, x1, count)
        pts = np.zeros((count, 3))
        normals = np.zeros((count, 3))
        for side, sign in ((0, 1.0), (1, -1.0)):
            m = which == side
            pts[m] = np.stack([x[m], sign * (FACADE_Y_M + rng.normal(0, 0.2, m.sum())), rng.uniform(0, 12, m.sum())], 1)
            normals[m] = [0, -sign, 0]
        m = which == 2
        pts[m] = np.stack([x[m], rng.uniform(-7.5, 7.5, m.sum()), np.zeros(m.sum())], 1)
        normals[m] = [0, 0, 1]
        return pts, normals
    lo, hi = centers[:, :2].min(0) - 80, centers[:, :2].max(0) + 80
    xy = rng.uniform(lo, hi, size=(count, 2))
    z = 6 * np.sin(xy[:, 0] / 90) * np.cos(xy[:, 1] / 70) + 2 * np.sin(xy[:, 0] / 13 + xy[:, 1] / 17)
    normals = np.tile([0.0, 0.0, 1.0], (count, 1))
    return np.column_stack([xy, z]), normals


# A street twin: this long a stretch of one facade, standing again further along the street.
TWIN_LENGTH_M = 15.0


def street_twins(points: np.ndarray, normals: np.ndarray, centers: np.ndarray, twins: int):
    """``(points, normals, appearance)`` of a street whose facades repeat: the street is
    cut into ``2 * twins`` equal sections along x; twin ``k``'s original is the stretch of the left
    facade (``TWIN_LENGTH_M`` long) 5 m into section ``2k``, and its copy, point for point, stands
    5 m into section ``2k + 1``: on the same facade, moved along the street, for even ``k``; on
    the facade across the street, turned to face it (half a turn about the vertical), for odd
    ``k``.  ``appearance`` labels each point by what it looks like (a copy has its original's
    label)."""
    appearance = np.arange(len(points))
    if twins <= 0:
        return points, normals, appearance
    x0, x1 = centers[:, 0].min(), centers[:, 0].max()
    section = (x1 - x0) / (2 * twins)
    length = min(TWIN_LENGTH_M, section / 2)
    keep = np.ones(len(points), bool)
    left, right = np.abs(points[:, 1] - FACADE_Y_M) < 1.0, np.abs(points[:, 1] + FACADE_Y_M) < 1.0
    extra_points, extra_normals, extra_labels = [], [], []
    for k in range(twins):
        start = x0 + 2 * k * section + 5.0
        original = left & (points[:, 0] >= start) & (points[:, 0] < start + length)
        if k % 2 == 0:
            R, d = np.eye(3), np.array([section, 0.0, 0.0])
            target = left
        else:  # across the street: half a turn about the vertical through the stretch's copy
            R = np.diag([-1.0, -1.0, 1.0])
            d = np.array([2 * start + section + length, 0.0, 0.0])
            target = right
        keep &= ~(target & (points[:, 0] >= start + section) & (points[:, 0] < start + section + length))
        extra_points.append(points[original] @ R.T + d)
        extra_normals.append(normals[original] @ R.T)
        extra_labels.append(appearance[original])
    points = np.vstack([points[keep], *extra_points])
    normals = np.vstack([normals[keep], *extra_normals])
    return points, normals, np.concatenate([appearance[keep], *extra_labels])


def _visibility(points, normals, rotations, translations, K, width, height, max_dist, max_angle_deg):
    """Observations (image, point, true pixel) of points seen within the frustum, closer than
    ``max_dist`` and within ``max_angle_deg`` of the surface normal."""
    centers = -np.einsum("nji,nj->ni", rotations, translations)
    tree = cKDTree(points)
    cos_max = np.cos(np.radians(max_angle_deg))
    out_i, out_p, out_xy = [], [], []
    for i, (r, t, c) in enumerate(zip(rotations, translations, centers)):
        cand = np.arange(len(points)) if max_dist > 1e8 else np.array(tree.query_ball_point(c, max_dist), dtype=np.int64)
        if len(cand) == 0:
            continue
        x_cam = points[cand] @ r.T + t
        z = x_cam[:, 2]
        ok = z > 0.1
        uv = np.full((len(cand), 2), -1.0)
        uv[ok] = (x_cam[ok, :2] / z[ok, None]) * K[0, 0] + K[:2, 2]
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
        to_cam = c - points[cand]
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        ok &= np.sum(to_cam * normals[cand], axis=1) > cos_max
        out_i.append(np.full(ok.sum(), i))
        out_p.append(cand[ok])
        out_xy.append(uv[ok])
    return np.concatenate(out_i), np.concatenate(out_p), np.concatenate(out_xy)


def make_scene(opts: SynthOptions) -> SyntheticScene:
    """Cameras, points and per-image keypoints of a scene, with exact ground truth."""
    rng = np.random.default_rng(opts.seed)
    focal = opts.focal or float(opts.width)
    if opts.scene == "orbit":
        rotations, translations, max_dist = _orbit_cameras(opts.num_images, rng)
        max_angle = 60.0
    elif opts.scene == "street":
        rotations, translations, max_dist = _street_cameras(opts.num_images, rng)
        max_angle = 75.0
    else:
        rotations, translations, max_dist = _aerial_cameras(opts.num_images, rng, opts, focal)
        max_angle = 90.0
    K = np.array([[focal, 0, (opts.width - 1) / 2], [0, focal, (opts.height - 1) / 2], [0, 0, 1]])
    centers = -np.einsum("nji,nj->ni", rotations, translations)

    # Density: measure visibility on a pool, then scale the pool to the target (linear in count).
    count = max(2000, 20 * opts.observations_per_image)
    for _ in range(4):
        points, normals = _sample_points(opts.scene, centers, count, rng)
        appearance = None
        if opts.scene == "street" and opts.twins:
            points, normals, appearance = street_twins(points, normals, centers, opts.twins)
        obs_i, obs_p, obs_xy = _visibility(points, normals, rotations, translations, K, opts.width, opts.height, max_dist, max_angle)
        mean_obs = len(obs_i) / opts.num_images
        if mean_obs >= opts.observations_per_image or mean_obs == 0:
            break
        count = int(count * opts.observations_per_image / mean_obs * 1.1) + 1
    if mean_obs == 0:
        raise RuntimeError("synthetic scene: no point is visible; check the options")
    keep_points = rng.random(len(points)) < min(1.0, opts.observations_per_image / mean_obs)
    # Points seen by a single image carry no geometry: drop them.
    seen = np.bincount(obs_p, minlength=len(points))
    keep_points &= seen >= 2
    new_index = np.cumsum(keep_points) - 1
    m = keep_points[obs_p]
    obs_i, obs_p, obs_xy = obs_i[m], new_index[obs_p[m]], obs_xy[m]
    points = points[keep_points]
    appearance = None if appearance is None else appearance[keep_points]

    # Keypoints: noisy observations plus distractors, in a random order per image.
    keypoints, obs_kp = [], np.empty(len(obs_i), dtype=np.int64)
    order = np.argsort(obs_i, kind="stable")
    starts = np.searchsorted(obs_i[order], np.arange(opts.num_images + 1))
    for i in range(opts.num_images):
        idx = order[starts[i] : starts[i + 1]]
        n_obs = len(idx)
        n_dis = int(round(opts.distractor_ratio * n_obs))
        noisy = obs_xy[idx] + rng.normal(0, opts.pixel_noise, (n_obs, 2))
        dis = rng.uniform([0, 0], [opts.width - 1, opts.height - 1], (n_dis, 2))
        perm = rng.permutation(n_obs + n_dis)
        kps = np.empty((n_obs + n_dis, 2))
        kps[perm] = np.vstack([noisy, dis])
        obs_kp[idx] = perm[:n_obs]
        keypoints.append(kps)
    names = [f"{opts.scene}_{i:05d}.jpg" for i in range(opts.num_images)]
    return SyntheticScene(opts.width, opts.height, focal, names, rotations, translations, points, obs_i, obs_p, obs_kp,
                          keypoints, appearance)


def with_lens(scene: SyntheticScene, model: str, params) -> SyntheticScene:
    """The scene seen through a lens: every keypoint moves from where the pinhole camera ``K``
    puts it to where the COLMAP camera ``model`` with ``params`` does (``params`` must hold the
    scene's focal length and principal point; the distortion is the test's).  Poses, points and
    observations are unchanged."""
    from dataclasses import replace

    from backend.camera_models import calibration_matrix, project

    K = calibration_matrix(model, params)
    if not np.allclose(K, scene.K):
        raise ValueError("with_lens: the lens must keep the scene's focal length and principal point")
    K_inv = np.linalg.inv(scene.K)
    moved = []
    for kps in scene.keypoints:
        rays = np.column_stack([kps, np.ones(len(kps))]) @ K_inv.T
        moved.append(project(model, params, rays))
    return replace(scene, keypoints=moved)


# ---------------------------------------------------------------------------------- output
def write_gt_table(scene: SyntheticScene, path: Path, image_ids: list[int] | None = None) -> None:
    """``IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ`` (the shared GT format)."""
    from backend.geometry import rotation_to_quaternion

    K = scene.K
    lines = ["# IMAGE_NAME WIDTH HEIGHT FX FY CX CY QW QX QY QZ TX TY TZ (cam_from_world, OpenCV pixels)"]
    for name, r, t in zip(scene.names, scene.rotations, scene.translations):
        q = rotation_to_quaternion(r)
        vals = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *q, *t]
        lines.append(f"{name} {scene.width} {scene.height} " + " ".join(f"{v:.17g}" for v in vals))
    tmp = path.with_suffix(".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)


def gt_reconstruction(scene: SyntheticScene):
    """The ground truth as a ``Reconstruction`` (image ids 1..N as in the database; points carry
    every observation of the scene, so their ERROR is the keypoint noise)."""
    from sfm.core.model import Camera, Image, Point3D, Reconstruction

    recon = Reconstruction()
    recon.add_camera(Camera(1, "SIMPLE_RADIAL", scene.width, scene.height, [scene.focal, (scene.width - 1) / 2, (scene.height - 1) / 2, 0.0]))
    for i, name in enumerate(scene.names):
        ids = np.full(len(scene.keypoints[i]), -1, dtype=np.int64)
        own = scene.obs_image == i
        ids[scene.obs_keypoint[own]] = scene.obs_point[own] + 1
        recon.add_image(Image(i + 1, name, 1, scene.rotations[i], scene.translations[i], scene.keypoints[i], ids))
    # Tracks built in bulk (the image tables above already agree with them).
    order = np.argsort(scene.obs_point, kind="stable")
    pts, imgs, kps = scene.obs_point[order], scene.obs_image[order] + 1, scene.obs_keypoint[order]
    starts = np.flatnonzero(np.r_[True, pts[1:] != pts[:-1], True])
    pairs = list(zip(imgs.tolist(), kps.tolist()))
    for s, e in zip(starts[:-1].tolist(), starts[1:].tolist()):
        recon.points3D[int(pts[s]) + 1] = Point3D(scene.points[pts[s]], pairs[s:e])
    recon._next_point_id = len(scene.points) + 1
    recon.update_point_errors()
    return recon
