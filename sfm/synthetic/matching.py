"""Simulated matching of a synthetic scene, the way a real front-end fails, into a database.

The raw matches of a pair are its true correspondences plus a share ``outlier_ratio`` of random
wrong ones; verification keeps a random share (``recall``) of the true ones and lets a few
outliers through (``verified_outlier_ratio`` of the inliers), and those survivors lie near the
epipolar line, as real RANSAC survivors do.  Matches are one-to-one, as after a mutual check.
All randomness comes from the options' ``seed``.

Repeated structures (a scene's ``appearance``): features of points that look alike match as if
they were one point.  A pair whose images see two copies of a twin then has correspondences
that agree with an apparent geometry, the second camera moved by the motion between the copies,
and verification keeps whichever of its two sets is larger (as RANSAC keeps the larger consensus):
the twin's, with that apparent geometry, or the true one, the other set left among the raw
matches as outliers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import TWIN_LENGTH_M, SyntheticScene


@dataclass(frozen=True)
class SyntheticPair:
    """Simulated matching result of one image pair (indices are keypoint indices, i < j)."""

    image1: int
    image2: int
    raw_matches: np.ndarray  # (R, 2)
    inlier_matches: np.ndarray  # (I, 2); empty if the pair failed verification
    num_true: int
    # (R, d): the world motion from the points image1 sees to the copies image2 sees, ``R X + d``,
    # when the verified matches are a twin's (their geometry is then the apparent one); None
    # otherwise
    twin_motion: tuple[np.ndarray, np.ndarray] | None = None


def relative_pose(scene: SyntheticScene, i: int, j: int, motion=None) -> tuple[np.ndarray, np.ndarray]:
    """``cam_j_from_cam_i`` of the ground truth; with ``motion`` (R, d), the apparent one of a
    twin's matches: image j sees the copies ``R X + d`` of the points X image i sees, as a
    camera with rotation ``R_j R`` and translation ``t_j + R_j d`` would see X."""
    r_j, t_j = scene.rotations[j], scene.translations[j]
    if motion is not None:
        r_j, t_j = r_j @ motion[0], t_j + r_j @ motion[1]
    r = r_j @ scene.rotations[i].T
    return r, t_j - r @ scene.translations[i]


def essential_matrix(scene: SyntheticScene, i: int, j: int, motion=None) -> np.ndarray:
    """E with ``x_j^T E x_i = 0`` for normalised coordinates (unit-norm translation); ``motion``
    as in :func:`relative_pose`."""
    r, t = relative_pose(scene, i, j, motion)
    t = t / np.linalg.norm(t)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ r


def _pair_correspondences(scene: SyntheticScene):
    """All correspondences grouped by pair: (pair keys sorted, kp_i, kp_j, point_i, point_j),
    the key ``i * N + j`` with ``i < j``: the observations of points of one appearance label
    (:attr:`SyntheticScene.appearance`; each point its own without) in two different images."""
    n = len(scene.names)
    label = scene.obs_point if scene.appearance is None else scene.appearance[scene.obs_point]
    order = np.lexsort((scene.obs_image, label))
    labels, imgs, kps, pts = label[order], scene.obs_image[order], scene.obs_keypoint[order], scene.obs_point[order]
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    lengths = np.diff(np.r_[starts, len(labels)])
    pos = np.arange(len(labels)) - np.repeat(starts, lengths)
    track_len = np.repeat(lengths, lengths)
    keys, ka, kb, pa, pb = [], [], [], [], []
    for k in range(1, int(lengths.max())):
        a = np.flatnonzero(pos + k < track_len)
        b = a + k
        a, b = a[imgs[a] != imgs[b]], b[imgs[a] != imgs[b]]  # one image seeing both copies
        keys.append(imgs[a].astype(np.int64) * n + imgs[b])  # imgs sorted within a label: a < b
        ka.append(kps[a])
        kb.append(kps[b])
        pa.append(pts[a])
        pb.append(pts[b])
    keys, ka, kb, pa, pb = map(np.concatenate, (keys, ka, kb, pa, pb))
    s = np.argsort(keys, kind="stable")
    return keys[s], ka[s], kb[s], pa[s], pb[s]


def _rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation and translation (R, d) with ``R a + d = b`` that fit the rows best (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - cb).T @ (a - ca))
    R = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return R, cb - R @ ca


def _one_to_one(matches: np.ndarray) -> np.ndarray:
    """The matches whose keypoints no earlier match uses (an image that sees both copies of a
    twin would otherwise match one keypoint twice)."""
    _, first = np.unique(matches[:, 0], return_index=True)
    matches = matches[np.sort(first)]
    _, first = np.unique(matches[:, 1], return_index=True)
    return matches[np.sort(first)]


def _epipolar_outliers(scene, i, j, count, rng, free_i, free_j, threshold=2.0, motion=None) -> np.ndarray:
    """Up to ``count`` wrong matches that lie within ``threshold`` px of the epipolar line, as
    the outliers that survive a real RANSAC do (vectorised: candidates against a random sample
    of the other image's keypoints).  Only keypoints in ``free_i`` / ``free_j`` (not otherwise
    matched in this pair) are used, so the matches stay one-to-one like mutual-check matches."""
    kp_i, kp_j = scene.keypoints[i], scene.keypoints[j]
    K_inv = np.linalg.inv(scene.K)
    F = K_inv.T @ essential_matrix(scene, i, j, motion) @ K_inv
    cand = free_i[rng.integers(0, len(free_i), size=3 * count)]
    sample = free_j[rng.integers(0, len(free_j), size=min(len(free_j), 800))]
    lines = np.column_stack([kp_i[cand], np.ones(len(cand))]) @ F.T  # l_j = F x_i
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    rows, cols = np.nonzero(np.abs(lines[:, :2] @ kp_j[sample].T + lines[:, 2:3]) < threshold)
    if len(rows) == 0:
        return np.zeros((0, 2), np.int64)
    shuffled = rng.permutation(len(rows))
    rows, cols = rows[shuffled], cols[shuffled]
    _, first = np.unique(rows, return_index=True)  # one random partner per candidate
    out = np.column_stack([cand[rows[first]], sample[cols[first]]])
    _, distinct = np.unique(out[:, 0], return_index=True)
    out = out[np.sort(distinct)]
    _, distinct = np.unique(out[:, 1], return_index=True)
    return out[np.sort(distinct)][:count].astype(np.int64)


def simulate_matching(scene: SyntheticScene, opts: SynthOptions) -> list[SyntheticPair]:
    """Raw and verified matches of every pair that shares at least one point."""
    rng = np.random.default_rng(opts.seed + 1)
    n = len(scene.names)
    keys, ka, kb, pa, pb = _pair_correspondences(scene)
    bounds = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1], True])
    pairs = []
    for s, e in zip(bounds[:-1], bounds[1:]):
        i, j = divmod(int(keys[s]), n)
        true = np.column_stack([ka[s:e], kb[s:e]])
        motion, other = None, np.zeros((0, 2), np.int64)
        if scene.appearance is not None:  # the larger consensus wins: the twin's or the true one
            twin = pa[s:e] != pb[s:e]
            if 2 * twin.sum() > len(twin):
                a, b = scene.points[pa[s:e]], scene.points[pb[s:e]]
                first = np.flatnonzero(twin)[0]  # one twin's motion: fitted to the copies of the first's stretch
                near = twin & (np.linalg.norm(a - a[first], axis=1) < 2 * TWIN_LENGTH_M)
                motion = _rigid_motion(a[near], b[near])
                twin &= np.linalg.norm(a @ motion[0].T + motion[1] - b, axis=1) < 1e-6
            winner = twin if motion is not None else ~twin
            true, other = _one_to_one(true[winner]), true[~winner]
        keep = rng.random(len(true)) < rng.uniform(opts.recall_min, opts.recall_max)
        inliers = true[keep]
        n_in_out = int(round(len(inliers) * opts.verified_outlier_ratio / (1 - opts.verified_outlier_ratio)))
        # Wrong matches use keypoints this pair matches nowhere else (one-to-one, as after a
        # mutual nearest-neighbour check).
        used_i = np.zeros(len(scene.keypoints[i]), bool)
        used_j = np.zeros(len(scene.keypoints[j]), bool)
        used_i[true[:, 0]] = used_j[true[:, 1]] = True
        other = other[~used_i[other[:, 0]] & ~used_j[other[:, 1]]] if len(other) else other
        if len(other):  # the losing consensus: raw matches that verification rejects
            other = _one_to_one(other)
            used_i[other[:, 0]] = used_j[other[:, 1]] = True
        survivors = np.zeros((0, 2), np.int64)
        if n_in_out:
            survivors = _epipolar_outliers(scene, i, j, n_in_out, rng, np.flatnonzero(~used_i), np.flatnonzero(~used_j),
                                           motion=motion)
            used_i[survivors[:, 0]] = used_j[survivors[:, 1]] = True
        free_i, free_j = np.flatnonzero(~used_i), np.flatnonzero(~used_j)
        n_raw_out = max(int(round(len(true) * opts.outlier_ratio / (1 - opts.outlier_ratio))) - len(survivors), 0)
        n_raw_out = min(n_raw_out, len(free_i), len(free_j))
        random_out = np.column_stack(
            [rng.choice(free_i, n_raw_out, replace=False), rng.choice(free_j, n_raw_out, replace=False)]
        )
        raw = np.vstack([true, other, survivors, random_out])
        raw = raw[rng.permutation(len(raw))]
        verified = np.vstack([inliers, survivors])
        if len(verified) < opts.min_inliers:
            verified = np.zeros((0, 2), np.int64)
        else:
            verified = verified[rng.permutation(len(verified))]
        pairs.append(SyntheticPair(i, j, raw, verified, len(true), motion))
    return pairs


def write_database(scene: SyntheticScene, pairs: list[SyntheticPair], path: Path,
                   camera_model: str = "SIMPLE_RADIAL") -> None:
    """Keypoints, raw matches and verified two-view geometries (config CALIBRATED, E and F,
    relative pose) into a COLMAP-schema database; one transaction, so it is all or nothing.
    The images share one camera of ``camera_model`` with the scene's focal length, principal
    point at the centre and no distortion (what extraction gives a camera with a focal prior)."""
    from backend.camera_models import default_params
    from sfm.io.pixel_convention import params_to_colmap
    from sfm.io.database import Database
    from sfm.io.database_schema import TwoViewConfig, TwoViewGeometry
    from backend.geometry import rotation_to_quaternion

    K_colmap = scene.K.copy()
    K_colmap[:2, 2] = params_to_colmap("PINHOLE", [1, 1, K_colmap[0, 2], K_colmap[1, 2]])[2:]
    K_inv = np.linalg.inv(K_colmap)
    with Database(path) as db, db.transaction():
        cam = db.add_camera(camera_model, scene.width, scene.height,
                            default_params(camera_model, scene.width, scene.height, scene.focal), prior_focal_length=True)
        for i, name in enumerate(scene.names):
            db.add_image(name, cam, image_id=i + 1)
            db.write_keypoints(i + 1, scene.keypoints[i].astype(np.float32))
        db.write_matches_many((p.image1 + 1, p.image2 + 1, p.raw_matches) for p in pairs)
        geoms = []
        for p in pairs:
            if len(p.inlier_matches) == 0:
                continue
            E = essential_matrix(scene, p.image1, p.image2, p.twin_motion)  # the geometry RANSAC would find
            r, t = relative_pose(scene, p.image1, p.image2, p.twin_motion)
            geoms.append(
                (p.image1 + 1, p.image2 + 1, TwoViewGeometry(
                    config=int(TwoViewConfig.CALIBRATED),
                    inlier_matches=p.inlier_matches.astype(np.uint32),
                    F=K_inv.T @ E @ K_inv, E=E, H=None,
                    qvec=rotation_to_quaternion(r), tvec=t / np.linalg.norm(t),
                ))
            )
        db.write_two_view_geometries_many(geoms)
