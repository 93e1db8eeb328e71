"""Tracks by union-find and batched triangulation against exact answers."""

from __future__ import annotations

import numpy as np

from backend.geometry import look_at
from sfm.synthetic.options import SynthOptions
from sfm.synthetic.scenes import make_scene
from sfm.synthetic.matching import simulate_matching
from sfm.mapper.tracks import _conflict_free_components, _triangle_support, build_tracks
from sfm.mapper.triangulation import depths, max_triangulation_angles, triangulate_dlt


def test_tracks_equal_ground_truth_points_without_outliers():
    opts = SynthOptions(num_images=12, observations_per_image=300, verified_outlier_ratio=0.0, recall_min=1.0, recall_max=1.0, seed=2)
    s = make_scene(opts)
    pairs = simulate_matching(s, opts)
    tracks = build_tracks([len(k) for k in s.keypoints], ((p.image1, p.image2, p.inlier_matches) for p in pairs if len(p.inlier_matches)))
    # Every track is one GT point's observations.
    point_of = {(int(i), int(k)): int(p) for i, k, p in zip(s.obs_image, s.obs_keypoint, s.obs_point)}
    for t in range(tracks.num_tracks):
        rows = slice(tracks.starts[t], tracks.starts[t + 1])
        pts = {point_of[(int(i), int(k))] for i, k in zip(tracks.image[rows], tracks.keypoint[rows])}
        assert len(pts) == 1
        assert np.all(np.diff(tracks.image[rows]) > 0)  # sorted, one observation per image
    assert tracks.num_tracks > 0.9 * len(np.unique(s.obs_point))


def test_a_wrong_match_does_not_merge_two_tracks():
    """Two 3-view tracks and one wrong match (0:0 - 2:1) that would chain them: the union that
    puts two keypoints of one image together is refused, the tracks stay apart."""
    matches = [
        (0, 1, np.array([[0, 0], [1, 1]])),
        (1, 2, np.array([[0, 2], [1, 1]])),
        (0, 2, np.array([[2, 0], [0, 1]])),  # (2, 0) is a 2-view track; (0, 1) is wrong
    ]
    tracks = build_tracks([3, 3, 3], matches)
    got = sorted(tuple(zip(tracks.image[s:e].tolist(), tracks.keypoint[s:e].tolist())) for s, e in zip(tracks.starts[:-1], tracks.starts[1:]))
    assert got == [((0, 0), (1, 0), (2, 2)), ((0, 1), (1, 1), (2, 1)), ((0, 2), (2, 0))]


def test_long_tracks_survive_surviving_outliers():
    """With 3% wrong verified matches and tracks of ~20 views, almost every union-find component
    catches a wrong match; the conflict-aware rebuild keeps (nearly) every point a track."""
    opts = SynthOptions(num_images=40, observations_per_image=400, seed=5)
    s = make_scene(opts)
    pairs = simulate_matching(s, opts)
    tracks = build_tracks([len(k) for k in s.keypoints], ((p.image1, p.image2, p.inlier_matches) for p in pairs if len(p.inlier_matches)))
    point_of = {(int(i), int(k)): int(p) for i, k, p in zip(s.obs_image, s.obs_keypoint, s.obs_point)}
    pure = 0
    for t in range(tracks.num_tracks):
        rows = slice(tracks.starts[t], tracks.starts[t + 1])
        assert len(set(tracks.image[rows].tolist())) == tracks.lengths[t]  # one keypoint per image
        pts = [point_of.get((int(i), int(k)), -1) for i, k in zip(tracks.image[rows], tracks.keypoint[rows])]
        pure += max(pts.count(p) for p in set(pts)) >= len(pts) - 1  # at most one wrong observation
    assert tracks.num_tracks > 0.85 * len(np.unique(s.obs_point))
    assert pure > 0.9 * tracks.num_tracks


def _greedy_reference(u, v, node_image, support):
    """The rule of ``_conflict_free_components`` edge by edge, with no shortcut."""
    parent = list(range(len(node_image)))
    members = [{int(node_image[x]): x} for x in range(len(node_image))]

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for k in np.argsort(-support, kind="stable"):
        ru, rv = find(int(u[k])), find(int(v[k]))
        if ru == rv or (support[k] == 0 and len(members[ru]) > 1 and len(members[rv]) > 1):
            continue
        if len(members[ru]) < len(members[rv]):
            ru, rv = rv, ru
        if set(members[ru]) & set(members[rv]):
            continue
        members[ru].update(members[rv])
        parent[rv] = ru
    comps = [np.array([m[i] for i in sorted(m)]) for x, m in enumerate(members) if find(x) == x and len(m) >= 2]
    return sorted(comps, key=lambda a: int(a.min()))


def test_conflict_free_components_equal_the_plain_greedy_union():
    """The scipy shortcut for consistent confirmed components gives exactly what the greedy
    union gives, on random match graphs full of conflicts and unconfirmed bridges."""
    rng = np.random.default_rng(0)
    for trial in range(30):
        n_images, per_image = int(rng.integers(3, 9)), int(rng.integers(2, 12))
        node_image = np.repeat(np.arange(n_images), per_image)
        n = len(node_image)
        m = int(rng.integers(1, 4 * n))
        u, v = rng.integers(0, n, m), rng.integers(0, n, m)
        keep = node_image[u] != node_image[v]
        u, v = u[keep], v[keep]
        support = _triangle_support(u, v, n)
        got = _conflict_free_components(u, v, node_image, support)
        want = _greedy_reference(u, v, node_image, support)
        assert [c.tolist() for c in got] == [c.tolist() for c in want], trial
        # Blocks of a few entries give the same triangle counts as one block.
        np.testing.assert_array_equal(_triangle_support(u, v, n, block_entries=7), support)


def test_dlt_is_exact_and_angles_are_right():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (50, 3))
    poses = [look_at(np.array([5 * np.cos(a), 5 * np.sin(a), 0.5]), np.zeros(3), np.array([0, 0, 1.0])) for a in (0.0, 0.3, 0.7, 1.2)]
    # Points seen by 2, 3 or 4 views (grouped rows).
    counts = rng.integers(2, 5, len(points))
    R, t, x, centers = [], [], [], []
    for p, n in zip(points, counts):
        for r, tr in poses[:n]:
            xc = r @ p + tr
            R.append(r), t.append(tr), x.append(xc[:2] / xc[2]), centers.append(-r.T @ tr)
    starts = np.concatenate([[0], np.cumsum(counts)])
    X = triangulate_dlt(np.array(R), np.array(t), np.array(x), starts)
    np.testing.assert_allclose(X, points, atol=1e-9)
    angles = max_triangulation_angles(np.array(centers), X, starts)
    c0, c1 = np.array(centers[0]), np.array(centers[1])
    expected = np.degrees(np.arccos(np.dot(c0 - points[0], c1 - points[0]) / np.linalg.norm(c0 - points[0]) / np.linalg.norm(c1 - points[0])))
    if counts[0] == 2:
        assert abs(angles[0] - expected) < 1e-9
    assert np.all(angles > 0)
    d = depths(np.array(R), np.array(t), np.repeat(X, counts, axis=0))
    assert np.all(d > 0)
