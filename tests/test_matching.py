"""Descriptor matching, pair selection and the ``match`` stage on synthetic data."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

from sfm.execution.local import LocalExecutor
from backend.camera_models import project
from sfm.io.database import Database
from sfm.errors import InputError
from backend.geometry import look_at, quaternion_to_rotation, rotation_angle_deg
from sfm.matching.options import MatchOptions
from sfm.matching.descriptors import match_descriptors
from sfm.matching.descriptors import normalize_descriptors
from sfm.stages.match import run_match
from sfm.matching.pairs import exhaustive_pairs, select_pairs, sequential_pairs


def rootsift_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """Non-negative unit vectors, like RootSIFT (float)."""
    d = np.abs(rng.normal(size=(n, 128)))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def quantised(d: np.ndarray) -> np.ndarray:
    """uint8 as the database stores RootSIFT (unit vectors times 512)."""
    return np.clip(np.round(d * 512), 0, 255).astype(np.uint8)


def noisy(rng: np.random.Generator, d: np.ndarray, sigma: float) -> np.ndarray:
    out = np.abs(d + rng.normal(0, sigma, d.shape))
    return out / np.linalg.norm(out, axis=1, keepdims=True)


# ------------------------------------------------------------------------------ matcher
def synthetic_descriptor_pair(seed: int, n_true: int = 1000, n_distract: int = 1000):
    """Image 1: n_true shared + n_distract own descriptors; image 2: the shared ones with noise,
    its own distractors, shuffled. Returns (desc1, desc2, true (n_true, 2) index pairs)."""
    rng = np.random.default_rng(seed)
    shared = rootsift_like(rng, n_true)
    d1 = np.vstack([shared, rootsift_like(rng, n_distract)])
    d2 = np.vstack([noisy(rng, shared, 0.03), rootsift_like(rng, n_distract)])
    order = rng.permutation(len(d2))  # d2_shuffled[k] = d2[order[k]]
    where = np.argsort(order)
    truth = np.stack([np.arange(n_true), where[:n_true]], axis=1)
    return quantised(d1), quantised(d2[order]), truth


@pytest.mark.parametrize("matcher", ["brute", "ivf", "flann"])
def test_ratio_and_mutual_matcher_recall_and_precision(matcher):
    d1, d2, truth = synthetic_descriptor_pair(0)
    m = match_descriptors(d1, d2, matcher=matcher)
    found = {tuple(r) for r in m.tolist()}
    true = {tuple(r) for r in truth.tolist()}
    assert len(found & true) / len(true) > 0.95
    assert len(found - true) / len(found) < 0.02
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)  # one-to-one


def test_brute_force_equals_a_direct_computation():
    rng = np.random.default_rng(1)
    f1, f2 = rootsift_like(rng, 300), rootsift_like(rng, 260)
    f2[:100] = noisy(rng, f1[:100], 0.03)
    d1, d2 = quantised(f1), quantised(f2)
    a = d1 / np.linalg.norm(d1.astype(float), axis=1, keepdims=True)
    b = d2 / np.linalg.norm(d2.astype(float), axis=1, keepdims=True)
    dist = np.linalg.norm(a[:, None] - b[None], axis=2)
    order = np.argsort(dist, axis=1)
    first, second = dist[np.arange(300), order[:, 0]], dist[np.arange(300), order[:, 1]]
    back = np.argmin(dist, axis=0)
    for cross_check in (True, False):
        keep = first < 0.8 * second
        if cross_check:
            keep &= back[order[:, 0]] == np.arange(300)
        expected = np.stack([np.flatnonzero(keep), order[keep, 0]], axis=1)
        got = match_descriptors(d1, d2, cross_check=cross_check, matcher="brute")
        assert np.array_equal(got, expected)
    sorted_first = np.sort(first[keep])
    limit = float(sorted_first[len(sorted_first) // 2 : len(sorted_first) // 2 + 2].mean())
    near = match_descriptors(d1, d2, cross_check=False, max_distance=limit, matcher="brute")
    assert np.array_equal(near, expected[first[keep] <= limit])


def test_brute_force_blocks_and_reused_buffer_give_the_same_answer():
    """Rows go in blocks through one reused buffer: any block size, and a buffer left larger or
    smaller by the pair before, give the nearest neighbours of one full product."""
    from sfm.matching.descriptors import _nearest_brute

    rng = np.random.default_rng(3)
    for n1, n2 in ((700, 650), (90, 40), (1200, 1300), (5, 1)):
        d1 = normalize_descriptors(quantised(rootsift_like(rng, n1)))
        d2 = normalize_descriptors(quantised(rootsift_like(rng, n2)))
        sim = d1.astype(np.float64) @ d2.T.astype(np.float64)
        best = np.argmax(sim, axis=1)
        for block in (None, 1, 64, 5000):
            got_best, dist1, dist2, mutual = _nearest_brute(d1, d2, block=block)
            assert np.array_equal(got_best, best)
            np.testing.assert_allclose(dist1, 2 - 2 * sim.max(axis=1), atol=1e-5)
            if n2 > 1:
                np.testing.assert_allclose(dist2, 2 - 2 * np.sort(sim, axis=1)[:, -2], atol=1e-5)
            assert np.array_equal(mutual, np.argmax(sim, axis=0)[best] == np.arange(n1))


def test_ratio_test_rejects_ambiguous_matches():
    rng = np.random.default_rng(2)
    d = rootsift_like(rng, 50)
    d2 = np.vstack([noisy(rng, d, 0.02), noisy(rng, d[:10], 0.02)])  # the first 10 twice
    m = match_descriptors(quantised(d), quantised(d2))
    assert set(m[:, 0].tolist()) == set(range(10, 50))


def test_prenormalised_descriptors_give_the_same_matches():
    d1, d2, _ = synthetic_descriptor_pair(5, 700, 600)
    q1, q2 = d1, d2  # already quantised
    expected = match_descriptors(q1, q2, matcher="brute")
    assert len(expected) > 300
    got = match_descriptors(normalize_descriptors(q1), normalize_descriptors(q2), matcher="brute", normalized=True)
    assert np.array_equal(got, expected)


def test_flann_is_deterministic_for_a_seed():
    d1, d2, _ = synthetic_descriptor_pair(3, 500, 500)
    a = match_descriptors(d1, d2, matcher="flann", seed=7)
    b = match_descriptors(d1, d2, matcher="flann", seed=7)
    assert np.array_equal(a, b)


def test_empty_descriptors_give_no_matches():
    assert match_descriptors(np.zeros((0, 128), np.uint8), np.ones((5, 128), np.uint8)).shape == (
        0,
        2,
    )


# ------------------------------------------------------------------------------ pairs
def test_exhaustive_and_sequential_pairs():
    ids = [5, 3, 9, 1, 7, 2]
    pairs = exhaustive_pairs(ids)
    assert len(pairs) == 6 * 5 // 2 and np.all(pairs[:, 0] < pairs[:, 1])
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    seq = sequential_pairs(ids, 2)  # in the given order: (5,3),(5,9),(3,9),(3,1),...
    expected = {(3, 5), (5, 9), (3, 9), (1, 3), (1, 9), (7, 9), (1, 7), (1, 2), (2, 7)}
    assert {tuple(p) for p in seq.tolist()} == expected
    assert len(sequential_pairs(ids, 0)) == 0 and len(sequential_pairs(ids, 100)) == 15


def grouped_descriptors(
    places: int = 6, per_place: int = 5, seed: int = 0
) -> dict[int, np.ndarray]:
    """Images of the same place share many descriptors (noisy copies from the place's pool)."""
    rng = np.random.default_rng(seed)
    out = {}
    for p in range(places):
        pool = rootsift_like(rng, 400)
        for k in range(per_place):
            seen = pool[rng.choice(400, 250, replace=False)]
            own = rootsift_like(rng, 250)
            out[p * per_place + k + 1] = quantised(np.vstack([noisy(rng, seen, 0.03), own]))
    return out


def test_retrieval_picks_same_place_neighbours_first():
    desc = grouped_descriptors()
    ids = sorted(desc)
    place = {i: (i - 1) // 5 for i in ids}
    pairs = select_pairs(ids, "retrieval", top_k=4, seed=0, load_descriptors=desc.__getitem__)
    assert {tuple(p) for p in pairs.tolist()} == {
        (a, b) for a in ids for b in ids if a < b and place[a] == place[b]
    }
    again = select_pairs(ids, "retrieval", top_k=4, seed=0, load_descriptors=desc.__getitem__)
    assert np.array_equal(pairs, again)
    # auto: exhaustive below the threshold, retrieval at it; sequential pairs are added
    assert len(select_pairs(ids, "auto", exhaustive_threshold=31)) == 30 * 29 // 2
    auto = select_pairs(ids, "auto", top_k=4, sequential=1, exhaustive_threshold=30,
                        load_descriptors=desc.__getitem__)  # fmt: skip
    assert len(auto) == len(pairs) + 5  # + the 5 sequential pairs that cross places


# ------------------------------------------------------------------------------ the stage
def write_two_cluster_database(path, seed: int = 0, reverse: bool = False):
    """5 PINHOLE images with focal priors: images 1-3 see point cloud A, images 4-5 cloud B
    (far away). Every 3D point has a descriptor, seen with per-view noise; each image also has
    distractor keypoints. ``reverse``: the same images added in the reverse order (other ids).
    Returns the true cam_from_world rotations by image id."""
    rng = np.random.default_rng(seed)
    width, height, f = 800, 600, 700.0
    params = np.array([f, f, (width - 1) / 2, (height - 1) / 2])
    clouds = [np.zeros(3), np.array([100.0, 0.0, 0.0])]
    points = [c + rng.uniform(-2, 2, (500, 3)) for c in clouds]
    point_desc = [rootsift_like(rng, 500) for _ in clouds]
    views = [(0, -10), (0, 0), (0, 12), (1, -8), (1, 6)]  # (cloud, azimuth in degrees)
    made = []
    for c, az in views:
        center = clouds[c] + 9 * np.array([np.sin(np.radians(az)), 0.0, -np.cos(np.radians(az))])
        rotation, translation = look_at(center, clouds[c], np.array([0.0, -1.0, 0.0]))
        kp = project("PINHOLE", params, points[c] @ rotation.T + translation)
        seen = np.flatnonzero((kp[:, 0] > 0) & (kp[:, 0] < width - 1) & (kp[:, 1] > 0) & (kp[:, 1] < height - 1))
        kp = np.vstack([kp[seen] + rng.normal(0, 0.3, (len(seen), 2)), rng.uniform(0, [width, height], (200, 2))])
        desc = np.vstack([noisy(rng, point_desc[c][seen], 0.02), rootsift_like(rng, 200)])
        order = rng.permutation(len(kp))
        made.append((rotation, kp[order], quantised(desc[order])))
    rotations = {}
    with Database(path) as db:
        for k in (reversed(range(len(views))) if reverse else range(len(views))):
            rotation, kp, desc = made[k]
            cam = db.add_camera("PINHOLE", width, height, params, prior_focal_length=True)
            image_id = db.add_image(f"img{k}.png", cam)
            db.write_keypoints(image_id, kp)
            db.write_descriptors(image_id, desc)
            rotations[image_id] = rotation
    return rotations


def all_geometries(path):
    with Database(path, readonly=True) as db:
        pairs = sorted(db.pairs_with_geometry())
        return {p: (db.read_two_view_geometry(*p), db.read_matches(*p)) for p in pairs}


def test_run_match_verifies_overlapping_pairs_deterministically_and_resumes(tmp_path):
    (tmp_path / "a").mkdir()
    rotations = write_two_cluster_database(tmp_path / "a" / "database.db")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    serial = run_match(tmp_path / "a", MatchOptions(seed=3), LocalExecutor(1))
    run_match(tmp_path / "b", MatchOptions(seed=3), LocalExecutor(2))  # the process pool
    for ws in ("a", "b"):  # closed and checkpointed: complete on its own
        assert not (tmp_path / ws / "database.db-wal").exists()
    assert serial.num_images == 5 and serial.num_pairs_considered == 10
    assert serial.num_pairs_processed == 10 and serial.num_verified == 4
    assert serial.median_inliers > 100
    ga, gb = (
        all_geometries(tmp_path / "a" / "database.db"),
        all_geometries(tmp_path / "b" / "database.db"),
    )
    assert sorted(ga) == sorted(gb) and len(ga) == 10
    for p in ga:
        assert ga[p][0].config == gb[p][0].config
        assert np.array_equal(ga[p][0].inlier_matches, gb[p][0].inlier_matches)
        assert np.array_equal(ga[p][1], gb[p][1])
    verified = {p for p, (g, _) in ga.items() if g.config >= 2 and g.num_inliers >= 15}
    assert verified == {(1, 2), (1, 3), (2, 3), (4, 5)}
    for a, b in verified:  # relative rotations are the true ones
        c2_from_c1 = rotations[b] @ rotations[a].T
        assert rotation_angle_deg(quaternion_to_rotation(ga[(a, b)][0].qvec) @ c2_from_c1.T) < 0.5
    again = run_match(tmp_path / "a", MatchOptions(seed=3), LocalExecutor(1))
    assert again.num_pairs_skipped_existing == 10 and again.num_pairs_processed == 0
    assert again.num_verified == 4


def test_a_pair_gets_the_same_matches_and_geometry_whatever_ids_the_database_gave_its_images(tmp_path):
    # An extension numbers its images after the old ones: the same two photos must verify the
    # same way as in a workspace that held them all from the start (seed and direction by name).
    for ws, reverse in (("a", False), ("b", True)):
        (tmp_path / ws).mkdir()
        write_two_cluster_database(tmp_path / ws / "database.db", reverse=reverse)
        run_match(tmp_path / ws, MatchOptions(seed=3), LocalExecutor(1))
    by_name = {}
    for ws in ("a", "b"):
        with Database(tmp_path / ws / "database.db", readonly=True) as db:
            ids = {r.name: i for i, r in db.read_images().items()}
            by_name[ws] = {(n1, n2): (db.read_two_view_geometry(ids[n1], ids[n2]), db.read_matches(ids[n1], ids[n2]))
                           for n1 in sorted(ids) for n2 in sorted(ids) if n1 < n2}
    assert ids == {f"img{k}.png": 5 - k for k in range(5)}  # b: reversed ids
    verified = 0
    for pair, (ga, ma) in by_name["a"].items():
        gb, mb = by_name["b"][pair]
        assert ga.config == gb.config, pair
        assert np.array_equal(ma, mb), pair
        assert np.array_equal(ga.inlier_matches, gb.inlier_matches), pair
        if ga.config >= 2:
            verified += 1
            np.testing.assert_allclose(ga.qvec, gb.qvec, atol=1e-12)  # cam2_from_cam1 of the same direction
    assert verified == 4


def test_run_match_skips_images_without_keypoints(tmp_path, caplog):
    write_two_cluster_database(tmp_path / "database.db")
    with Database(tmp_path / "database.db") as db:
        db.add_image("empty.png", 1)
    with caplog.at_level(logging.WARNING, logger="sfm.stages.match"):
        result = run_match(tmp_path, MatchOptions(sequential=1), LocalExecutor(1))
    assert "empty.png has no keypoints" in caplog.text
    assert result.num_images == 5 and result.num_pairs_considered == 10


def test_run_match_without_images_is_an_input_error(tmp_path):
    with pytest.raises(InputError):
        run_match(tmp_path)  # no database
    Database(tmp_path / "database.db").close()
    with pytest.raises(InputError):
        run_match(tmp_path)


def test_match_options_reject_unknown_choices():
    with pytest.raises(ValueError):
        MatchOptions(matcher="exact")
    with pytest.raises(ValueError):
        MatchOptions(pairs="vocab_tree")


def _lru_loads(order, capacity):
    """Feature loads of a worker whose cache holds ``capacity`` images, taking pairs in ``order``."""
    from collections import OrderedDict

    cache, loads = OrderedDict(), 0
    for pair in order:
        for image in pair:
            if image in cache:
                cache.move_to_end(image)
                continue
            loads += 1
            cache[image] = True
            if len(cache) > capacity:
                cache.popitem(last=False)
    return loads


def test_cache_order_reads_each_image_a_few_times():
    """A 40 x 40 block of photos, each paired with its neighbours up to two steps away, ids
    shuffled: sorted by id, a cache of 120 images loads each image ten times; in
    ``cache_order`` (the same pairs) at most two and a half times."""
    from sfm.matching.pair_matcher import cache_order

    side = 40
    ids = np.random.default_rng(0).permutation(side * side) + 1
    grid = ids.reshape(side, side)
    pairs = set()
    for r in range(side):
        for c in range(side):
            for dr in range(0, 3):
                for dc in range(-2, 3):
                    if (dr, dc) > (0, 0) and 0 <= r + dr < side and 0 <= c + dc < side:
                        a, b = int(grid[r, c]), int(grid[r + dr, c + dc])
                        pairs.add((min(a, b), max(a, b)))
    pairs = sorted(pairs)
    ordered = cache_order(pairs, 120)
    assert sorted(ordered) == pairs
    assert _lru_loads(pairs, 120) > 8 * side * side
    assert _lru_loads(ordered, 120) < 2.5 * side * side
