"""Simulated matching of a synthetic scene, the way a real front-end fails, into a database.

The raw matches of a pair are its true correspondences plus a share ``outlier_ratio`` of random
wrong ones; verification keeps a random share (``recall``) of the true ones and lets a few
outliers through (``verified_outlier_ratio`` of the inliers), and those survivors lie near the
epipolar line, as real RANSAC survivors do.  Matches are one-to-one, as after a mutual check.
All randomness comes from the options' ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import SyntheticScene


@dataclass(frozen=True)
class SyntheticPair:
    """Simulated matching result of one image pair (indices are keypoint indices, i < j)."""

    image1: int
    image2: int
    raw_matches: np.ndarray  # (R, 2)
    inlier_matches: np.ndarray  # (I, 2); empty if the pair failed verification
    num_true: int


def relative_pose(scene: SyntheticScene, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """``cam_j_from_cam_i`` of the ground truth."""
    r = scene.rotations[j] @ scene.rotations[i].T
    return r, scene.translations[j] - r @ scene.translations[i]


def essential_matrix(scene: SyntheticScene, i: int, j: int) -> np.ndarray:
    """E with ``x_j^T E x_i = 0`` for normalised coordinates (unit-norm translation)."""
    r, t = relative_pose(scene, i, j)
    t = t / np.linalg.norm(t)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ r


def _pair_correspondences(scene: SyntheticScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All true correspondences grouped by pair: returns (pair_keys sorted, kp_i, kp_j) where the
    key is ``i * N + j`` with ``i < j``."""
    n = len(scene.names)
    order = np.lexsort((scene.obs_image, scene.obs_point))
    pts, imgs, kps = scene.obs_point[order], scene.obs_image[order], scene.obs_keypoint[order]
    starts = np.flatnonzero(np.r_[True, pts[1:] != pts[:-1]])
    lengths = np.diff(np.r_[starts, len(pts)])
    pos = np.arange(len(pts)) - np.repeat(starts, lengths)
    track_len = np.repeat(lengths, lengths)
    keys, ka, kb = [], [], []
    for k in range(1, int(lengths.max())):
        a = np.flatnonzero(pos + k < track_len)
        b = a + k
        keys.append(imgs[a].astype(np.int64) * n + imgs[b])  # imgs sorted within a track: a < b
        ka.append(kps[a])
        kb.append(kps[b])
    keys, ka, kb = np.concatenate(keys), np.concatenate(ka), np.concatenate(kb)
    s = np.argsort(keys, kind="stable")
    return keys[s], ka[s], kb[s]


def _epipolar_outliers(scene, i, j, count, rng, free_i, free_j, threshold=2.0) -> np.ndarray:
    """Up to ``count`` wrong matches that lie within ``threshold`` px of the epipolar line, as
    the outliers that survive a real RANSAC do (vectorised: candidates against a random sample
    of the other image's keypoints).  Only keypoints in ``free_i`` / ``free_j`` (not otherwise
    matched in this pair) are used, so the matches stay one-to-one like mutual-check matches."""
    kp_i, kp_j = scene.keypoints[i], scene.keypoints[j]
    K_inv = np.linalg.inv(scene.K)
    F = K_inv.T @ essential_matrix(scene, i, j) @ K_inv
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
    keys, ka, kb = _pair_correspondences(scene)
    bounds = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1], True])
    pairs = []
    for s, e in zip(bounds[:-1], bounds[1:]):
        i, j = divmod(int(keys[s]), n)
        true = np.column_stack([ka[s:e], kb[s:e]])
        keep = rng.random(len(true)) < rng.uniform(opts.recall_min, opts.recall_max)
        inliers = true[keep]
        n_in_out = int(round(len(inliers) * opts.verified_outlier_ratio / (1 - opts.verified_outlier_ratio)))
        # Wrong matches use keypoints this pair matches nowhere else (one-to-one, as after a
        # mutual nearest-neighbour check).
        used_i = np.zeros(len(scene.keypoints[i]), bool)
        used_j = np.zeros(len(scene.keypoints[j]), bool)
        used_i[true[:, 0]] = used_j[true[:, 1]] = True
        survivors = np.zeros((0, 2), np.int64)
        if n_in_out:
            survivors = _epipolar_outliers(scene, i, j, n_in_out, rng, np.flatnonzero(~used_i), np.flatnonzero(~used_j))
            used_i[survivors[:, 0]] = used_j[survivors[:, 1]] = True
        free_i, free_j = np.flatnonzero(~used_i), np.flatnonzero(~used_j)
        n_raw_out = max(int(round(len(true) * opts.outlier_ratio / (1 - opts.outlier_ratio))) - len(survivors), 0)
        n_raw_out = min(n_raw_out, len(free_i), len(free_j))
        random_out = np.column_stack(
            [rng.choice(free_i, n_raw_out, replace=False), rng.choice(free_j, n_raw_out, replace=False)]
        )
        raw = np.vstack([true, survivors, random_out])
        raw = raw[rng.permutation(len(raw))]
        verified = np.vstack([inliers, survivors])
        if len(verified) < opts.min_inliers:
            verified = np.zeros((0, 2), np.int64)
        else:
            verified = verified[rng.permutation(len(verified))]
        pairs.append(SyntheticPair(i, j, raw, verified, len(true)))
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
            E = essential_matrix(scene, p.image1, p.image2)
            r, t = relative_pose(scene, p.image1, p.image2)
            geoms.append(
                (p.image1 + 1, p.image2 + 1, TwoViewGeometry(
                    config=int(TwoViewConfig.CALIBRATED),
                    inlier_matches=p.inlier_matches.astype(np.uint32),
                    F=K_inv.T @ E @ K_inv, E=E, H=None,
                    qvec=rotation_to_quaternion(r), tvec=t / np.linalg.norm(t),
                ))
            )
        db.write_two_view_geometries_many(geoms)
