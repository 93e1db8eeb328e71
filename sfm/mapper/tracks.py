"""Feature tracks from pairwise verified matches (union-find over (image, keypoint) nodes).

Every keypoint of every image is a node; every verified inlier match joins two nodes; a track
is a connected component with at least two nodes.  A component that holds two keypoints of one
image is inconsistent: a wrong match chained two physical points.  With long tracks (an object
seen by 20 images is matched in 190 pairs) almost every component would catch one of the few
outliers that survive verification, so dropping inconsistent components would drop most
tracks.  Instead, inconsistent components are rebuilt by a conflict-aware union-find: their
matches are joined strongest pair first, and a union that would put two keypoints of one image
into one track is refused (the wrong match loses against the many right ones it contradicts).
Consistent components (the vast majority of nodes) come from scipy's connected components on
the sparse match graph, with no Python loop.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class Tracks:
    """Observations grouped by track: track ``t`` owns rows ``starts[t]:starts[t+1]``.

    image: image index (0..N-1, the caller's numbering) of each observation.
    keypoint: keypoint index of each observation in its image.
    starts: (T+1,) offsets.
    """

    image: np.ndarray
    keypoint: np.ndarray
    starts: np.ndarray

    @property
    def num_tracks(self) -> int:
        return len(self.starts) - 1

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.starts)

    def track_of_observation(self) -> np.ndarray:
        """Track index of each observation row."""
        return np.repeat(np.arange(self.num_tracks), self.lengths)


def build_tracks(num_keypoints: np.ndarray, matches: Iterable[tuple[int, int, np.ndarray]]) -> Tracks:
    """Tracks from verified matches.

    ``num_keypoints[i]`` is the keypoint count of image ``i``; ``matches`` yields
    ``(i, j, (M, 2) keypoint index pairs)``.  Tracks are ordered by their smallest node, and
    observations inside a track by image index, so the result is deterministic.
    """
    num_keypoints = np.asarray(num_keypoints, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(num_keypoints)])
    # Strongest pairs first: the conflict-aware union below trusts earlier matches.
    pairs = sorted(((i, j, np.asarray(m).reshape(-1, 2)) for i, j, m in matches), key=lambda item: -len(item[2]))
    n = int(offsets[-1])
    total = sum(len(m) for _, _, m in pairs)
    if total == 0:
        empty = np.zeros(0, dtype=np.int64)
        return Tracks(empty, empty, np.zeros(1, dtype=np.int64))
    # Node indices of the match ends, written in place: int32 while they fit (a list of
    # per-pair arrays concatenated would hold them twice, and a large scene has tens of
    # millions of matches).
    index_type = np.int32 if n < np.iinfo(np.int32).max else np.int64
    r, c = np.empty(total, dtype=index_type), np.empty(total, dtype=index_type)
    at = 0
    for i, j, m in pairs:
        r[at : at + len(m)] = offsets[i] + m[:, 0]
        c[at : at + len(m)] = offsets[j] + m[:, 1]
        at += len(m)
    del pairs
    node_image = np.repeat(np.arange(len(num_keypoints)), num_keypoints)
    node_kp = np.arange(n) - offsets[node_image]
    # Components of the matched nodes; those holding no image twice are tracks as they are.
    g_nodes, g_labels, g_bad = _consistent_groups(r, c, node_image)
    bounds = np.flatnonzero(np.r_[True, g_labels[1:] != g_labels[:-1], True])
    keep_obs = ~g_bad[g_labels]
    good_images, good_kp = node_image[g_nodes[keep_obs]], node_kp[g_nodes[keep_obs]]
    good_sizes = np.diff(bounds)[~g_bad[g_labels[bounds[:-1]]]]
    # Rebuild the inconsistent components edge by edge, refusing conflicting unions.
    bad_nodes = np.zeros(n, dtype=bool)
    bad_nodes[g_nodes[~keep_obs]] = True
    sel = bad_nodes[r]
    extra = _conflict_free_components(r[sel], c[sel], node_image, _triangle_support(r[sel], c[sel], n))
    parts_img = [good_images] + [node_image[comp] for comp in extra]
    parts_kp = [good_kp] + [node_kp[comp] for comp in extra]
    all_sizes = np.concatenate([good_sizes, [len(comp) for comp in extra]]).astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(all_sizes)])
    return Tracks(np.concatenate(parts_img).astype(np.int64), np.concatenate(parts_kp).astype(np.int64), starts.astype(np.int64))


def keypoint_match_counts(num_keypoints: Iterable[int], ends: Iterable[tuple[int, np.ndarray]]) -> list[np.ndarray]:
    """Each keypoint's number of verified matches, per image: ``ends`` yields one side of a
    pair's matches at a time, ``(image, keypoint indices of its inlier matches)``."""
    sizes = np.asarray(list(num_keypoints), dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    nodes = [offsets[i] + np.asarray(keypoints, dtype=np.int64) for i, keypoints in ends]
    flat = np.bincount(np.concatenate(nodes) if nodes else np.zeros(0, np.int64), minlength=int(offsets[-1]))
    return np.split(flat, offsets[1:-1])


def two_view_tracks(tracks: Tracks, match_counts: list[np.ndarray]) -> np.ndarray:
    """Which tracks are COLMAP's two-view observations (``tri_ignore_two_view_tracks``): two
    keypoints that each have one verified match (``match_counts``, per image, over the whole
    database), so no third image confirms them.  A track cut to two rows by a cluster's edge,
    whose keypoints match images outside the cluster, is not one."""
    if tracks.num_tracks == 0:
        return np.zeros(0, dtype=bool)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in match_counts])])
    single = np.concatenate(match_counts)[offsets[tracks.image] + tracks.keypoint] == 1
    singles = np.add.reduceat(single.astype(np.int64), tracks.starts[:-1])
    return (tracks.lengths == 2) & (singles == 2)


def _triangle_support(edges_u: np.ndarray, edges_v: np.ndarray, n: int, block_entries: int = 4_000_000) -> np.ndarray:
    """Number of common neighbours of each edge's ends (triangles through the edge).  A right
    match inside a track seen by L images is confirmed by up to L - 2 others; a wrong match
    between two tracks by none.  The squared adjacency is formed a block of rows at a time
    (about ``block_entries`` entries each): whole, it would hold a row of degree² entries per
    node, gigabytes for a few thousand images."""
    if len(edges_u) == 0:
        return np.zeros(0, dtype=np.int64)
    u, v = edges_u.astype(np.int32, copy=False), edges_v.astype(np.int32, copy=False)  # int32: half the memory
    adj = sp.csr_matrix((np.ones(2 * len(u), dtype=np.int32), (np.concatenate([u, v]), np.concatenate([v, u]))),
                        shape=(n, n))
    adj.data[:] = 1  # duplicate matches count once
    # Entries of row r of adj @ adj: at most the summed degrees of r's neighbours.
    work = np.cumsum(adj @ np.diff(adj.indptr).astype(np.int64))
    cuts = work_cuts(work, block_entries)
    support = np.zeros(len(u), dtype=np.int64)
    edge_order = np.argsort(u, kind="stable")
    edge_bounds = np.searchsorted(u[edge_order], cuts)
    for k in range(len(cuts) - 1):
        lo, hi = int(cuts[k]), int(cuts[k + 1])
        if hi <= lo:
            continue
        rows = adj[lo:hi]
        common = (rows @ adj).multiply(rows).tocsr()
        sel = edge_order[edge_bounds[k] : edge_bounds[k + 1]]
        support[sel] = np.asarray(common[u[sel] - lo, v[sel]]).ravel()
    return support


def _consistent_groups(edges_u: np.ndarray, edges_v: np.ndarray, node_image: np.ndarray):
    """Connected components of the given edges: (nodes sorted by component then image,
    component label of each, whether each label holds some image twice)."""
    n = len(node_image)
    graph = sp.coo_matrix((np.ones(len(edges_u), dtype=np.int8), (edges_u.astype(np.int32, copy=False), edges_v.astype(np.int32, copy=False))),
                          shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    involved = np.zeros(n, dtype=bool)
    involved[edges_u] = involved[edges_v] = True
    nodes = np.flatnonzero(involved)
    _, labels = np.unique(labels[nodes], return_inverse=True)  # 0..k-1, by smallest node
    images = node_image[nodes]
    order = np.lexsort((images, labels))
    nodes, labels, images = nodes[order], labels[order], images[order]
    repeated = (labels[1:] == labels[:-1]) & (images[1:] == images[:-1])
    bad = np.zeros(int(labels.max(initial=-1)) + 1, dtype=bool)
    bad[labels[1:][repeated]] = True
    return nodes, labels, bad


def _conflict_free_components(edges_u: np.ndarray, edges_v: np.ndarray, node_image: np.ndarray,
                              support: np.ndarray) -> list[np.ndarray]:
    """Union-find over the given edges, best supported first, refusing any union that would
    hold two nodes of one image, and any union of two tracks (both of >= 2 nodes) through an
    edge no third view confirms; returns the components of size >= 2, sorted by image.

    The confirmed edges (support >= 1) all come before the others, and among them only an
    image conflict can refuse a union.  So a component of the confirmed edges that holds no
    image twice is exactly what the union of its edges builds, in any order: those come from
    scipy at once, and the Python loop runs only over the confirmed edges of the other
    components and over the unconfirmed edges."""
    order = np.argsort(-support, kind="stable")
    edges_u, edges_v, support = edges_u[order], edges_v[order], support[order]
    strong = support > 0
    g_nodes, g_labels, g_bad = _consistent_groups(edges_u[strong], edges_v[strong], node_image)
    bounds = np.flatnonzero(np.r_[True, g_labels[1:] != g_labels[:-1], True]) if len(g_labels) else np.zeros(1, np.int64)
    good = ~g_bad[g_labels[bounds[:-1]]]
    roots = g_nodes[bounds[:-1]]  # the first node of each group is its root
    in_good = np.repeat(good, np.diff(bounds))
    # Parent links: a node of a consistent group starts under its group's root (``base``);
    # links the loop changes go in ``parent``.  A dict of every node would cost ~100 B each.
    base = np.arange(len(node_image))
    base[g_nodes[in_good]] = np.repeat(roots, np.diff(bounds))[in_good]
    parent: dict[int, int] = {}
    group_of_root = {int(r): k for k, r in enumerate(roots.tolist()) if good[k]}
    img = node_image.tolist()
    members: dict[int, dict[int, int]] = {}  # root -> {image: node}, materialised when touched

    def up(x: int) -> int:
        p = parent.get(x)
        return int(base[x]) if p is None else p

    def find(x: int) -> int:
        root = x
        while (p := up(root)) != root:
            root = p
        while (p := up(x)) != root:
            parent[x], x = root, p
        return root

    def members_of(root: int, node: int) -> dict[int, int]:
        got = members.get(root)
        if got is None:
            k = group_of_root.get(root)
            if k is None:
                return {img[node]: node}
            got = {img[x]: x for x in g_nodes[bounds[k] : bounds[k + 1]].tolist()}
            members[root] = got
        return got

    node_label = np.full(len(node_image), -1, dtype=np.int64)
    node_label[g_nodes] = g_labels
    loop = ~strong
    loop[strong] = g_bad[node_label[edges_u[strong]]]
    absorbed: set[int] = set()  # roots joined into another root
    for u, v, sup in _chunked(edges_u[loop], edges_v[loop], support[loop]):
        ru, rv = find(u), find(v)
        if ru == rv:
            continue
        mu, mv = members_of(ru, u), members_of(rv, v)
        if sup == 0 and len(mu) > 1 and len(mv) > 1:
            continue  # an unconfirmed bridge between two tracks
        if len(mu) < len(mv):
            ru, rv, mu, mv = rv, ru, mv, mu
        if any(k in mu for k in mv):
            continue  # would put two keypoints of one image in a track
        absorbed.add(rv)
        mu.update(mv)
        members[ru] = mu
        members.pop(rv, None)
        parent[rv] = ru
    comps = [np.array([m[k] for k in sorted(m)], dtype=np.int64) for m in members.values() if len(m) >= 2]
    comps += [g_nodes[bounds[k] : bounds[k + 1]] for r, k in group_of_root.items() if r not in members and r not in absorbed]
    comps.sort(key=lambda a: int(a.min()))
    return comps


def work_cuts(cumulative_work: np.ndarray, step: int) -> np.ndarray:
    """Boundaries ``0 = c_0 < ... < c_k = len`` that cut items with the given cumulative work
    into consecutive chunks of about ``step`` work each (a chunk holds at least one item)."""
    total = int(cumulative_work[-1]) if len(cumulative_work) else 0
    return np.unique(np.r_[0, np.searchsorted(cumulative_work, np.arange(step, total, step)), len(cumulative_work)])


def _chunked(*arrays: np.ndarray, size: int = 100_000):
    """Rows of the arrays as Python tuples, converted ``size`` at a time (a whole ``tolist``
    of millions of edges would hold ~30 B per value at once)."""
    for lo in range(0, len(arrays[0]), size):
        yield from zip(*(a[lo : lo + size].tolist() for a in arrays))
