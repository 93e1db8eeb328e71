"""Tests of graph.partition: NCut partition into cores of at most S_max images (Alg. 1, lines 1-2)."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest
from _helpers_graph import random_graphs
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import connected_components as cc_labels
from scipy.spatial import cKDTree

import graph.partition as partition_module
from graph.image_graph import ImageGraph, build_image_graph, connected_components
from graph.partition import (
    cut_weight,
    fiedler_vector,
    labels_from_clusters,
    ncut_bisect,
    partition_graph,
)

log = logging.getLogger(__name__)


def aerial_graph(rows: int, cols: int, radius: float = 3.0, n_long: int = 20, seed: int = 0):
    """Aerial-like image graph: a rows x cols grid of cameras, edges within ``radius`` grid
    steps with weight decreasing with distance, plus a few random long edges of small weight."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols]
    centres = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    pairs = cKDTree(centres).query_pairs(radius, output_type="ndarray")
    dist = np.linalg.norm(centres[pairs[:, 0]] - centres[pairs[:, 1]], axis=1)
    weights = np.round(400.0 * np.exp(-dist / 1.5))
    n = rows * cols
    long_i = rng.integers(0, n, n_long)
    long_j = rng.integers(0, n, n_long)
    long_w = rng.integers(15, 30, n_long)
    return build_image_graph(
        n, np.r_[pairs[:, 0], long_i], np.r_[pairs[:, 1], long_j], np.r_[weights, long_w]
    )


def assert_valid_partition(graph: ImageGraph, clusters: list[np.ndarray], s_max: int) -> None:
    """Disjoint, covering, bounded, sorted, ordered, connected, inside one component."""
    assert all(c.dtype == np.int64 and c.size >= 1 for c in clusters)
    allnodes = np.concatenate(clusters) if clusters else np.array([], dtype=np.int64)
    assert np.array_equal(np.sort(allnodes), np.arange(graph.num_nodes))
    assert all(c.size <= s_max for c in clusters)
    assert all(np.all(np.diff(c) > 0) for c in clusters)
    firsts = [int(c[0]) for c in clusters]
    assert firsts == sorted(firsts)
    comp_of = np.empty(graph.num_nodes, dtype=np.int64)
    comps = connected_components(graph)
    for k, comp in enumerate(comps):
        comp_of[comp] = k
    for c in clusters:
        assert np.unique(comp_of[c]).size == 1
        ncomp, _ = cc_labels(graph.subgraph_adjacency(c), directed=False)
        assert ncomp == 1, "every core induces a connected subgraph"
    # A component of size <= S_max is exactly one cluster; a larger one needs ceil(n/S) or more.
    for comp in comps:
        inside = sum(1 for c in clusters if comp_of[c[0]] == comp_of[comp[0]])
        if comp.size <= s_max:
            assert inside == 1
        else:
            assert inside >= math.ceil(comp.size / s_max)


def test_small_graph_is_one_cluster():
    g = aerial_graph(5, 6)
    clusters = partition_graph(g, max_cluster_size=100)
    assert len(clusters) == 1
    assert clusters[0].tolist() == list(range(30))


def test_disconnected_components_are_partitioned_separately():
    a = aerial_graph(10, 10)  # 100 nodes
    i, j, w = a.edges()
    # second copy shifted by 100, and an isolated node 200
    g = build_image_graph(201, np.r_[i, i + 100], np.r_[j, j + 100], np.r_[w, w])
    clusters = partition_graph(g, max_cluster_size=100)
    assert [c.tolist() for c in clusters] == [list(range(100)), list(range(100, 200)), [200]]
    clusters = partition_graph(g, max_cluster_size=30)
    assert_valid_partition(g, clusters, 30)
    assert [c.tolist() for c in clusters][-1] == [200]


def test_a_component_within_max_whole_component_is_not_cut():
    a = aerial_graph(5, 6)  # 30 nodes
    b = aerial_graph(10, 10)  # 100 nodes
    ia, ja, wa = a.edges()
    ib, jb, wb = b.edges()
    g = build_image_graph(130, np.r_[ia, ib + 30], np.r_[ja, jb + 30], np.r_[wa, wb])
    clusters = partition_graph(g, max_cluster_size=20, max_whole_component=40)
    assert clusters[0].tolist() == list(range(30))  # 30 <= 40: whole, though above 20
    assert all(c.size <= 20 for c in clusters[1:]) and len(clusters) >= 1 + 5
    assert sorted(np.concatenate(clusters).tolist()) == list(range(130))
    # a bound below max_cluster_size changes nothing
    assert [c.tolist() for c in partition_graph(g, 20, max_whole_component=10)] == [
        c.tolist() for c in partition_graph(g, 20)]


def test_cut_weight_and_labels():
    g = build_image_graph(4, [0, 1, 2, 0], [1, 2, 3, 3], [5, 6, 7, 8])
    assert cut_weight(g, [0, 0, 1, 1]) == 6 + 8
    assert cut_weight(g, [0, 0, 0, 0]) == 0
    labels = labels_from_clusters([np.array([2, 3]), np.array([0])], 4)
    assert labels.tolist() == [1, -1, 0, 0]
    with pytest.raises(ValueError):
        cut_weight(g, [0, 1])


def test_bad_max_cluster_size():
    with pytest.raises(ValueError):
        partition_graph(aerial_graph(3, 3), 0)


def test_fiedler_vector_separates_two_communities_dense_and_sparse():
    for half in (20, 400):  # dense eigensolver path and sparse ARPACK path
        rng = np.random.default_rng(3)
        n = 2 * half
        ii, jj = np.triu_indices(half, 1)
        keep = rng.random(ii.size) < min(1.0, 8.0 / half)
        ii, jj = ii[keep], jj[keep]
        path_i, path_j = np.arange(half - 1), np.arange(1, half)  # keep each side connected
        ei = np.r_[ii, path_i, ii + half, path_i + half, 0]
        ej = np.r_[jj, path_j, jj + half, path_j + half, half]
        w = np.r_[np.full(2 * ii.size + 2 * path_i.size, 50.0), 1.0]
        g = build_image_graph(n, ei, ej, w)
        y = fiedler_vector(g.adjacency, seed=0)
        assert np.all(np.sign(y[:half]) == np.sign(y[0]))
        assert np.all(np.sign(y[half:]) == -np.sign(y[0]))
        clusters = partition_graph(g, max_cluster_size=half)
        assert [c.tolist() for c in clusters] == [list(range(half)), list(range(half, n))]


def clique_chain(sizes: list[int], strong: float = 100.0, weak: float = 1.0) -> ImageGraph:
    """Cliques of the given sizes in a chain, consecutive cliques joined by one weak edge."""
    ei, ej, w = [], [], []
    start = 0
    for k, size in enumerate(sizes):
        ii, jj = np.triu_indices(size, 1)
        ei.extend((ii + start).tolist())
        ej.extend((jj + start).tolist())
        w.extend([strong] * ii.size)
        if k + 1 < len(sizes):
            ei.append(start + size - 1)
            ej.append(start + size)
            w.append(weak)
        start += size
    return build_image_graph(start, ei, ej, w)


def test_ncut_bisect_cuts_at_a_weak_link_not_at_the_median():
    g = clique_chain([30, 30, 40])  # a median split would cut through the middle clique
    left, right = ncut_bisect(g.adjacency, 70, seed=0)
    assert left.size + right.size == 100 and left.size and right.size
    labels = np.zeros(100, dtype=int)
    labels[right] = 1
    assert cut_weight(g, labels) == 1.0
    assert {left.size, right.size} in ({30, 70}, {60, 40})


def test_ncut_bisect_keeps_the_cluster_count_minimal():
    g = clique_chain([20] * 12)  # 240 nodes, S = 100 -> 3 clusters: sides need 1 + 2 clusters
    left, right = ncut_bisect(g.adjacency, 100, seed=0)
    assert math.ceil(left.size / 100) + math.ceil(right.size / 100) == 3
    labels = np.zeros(240, dtype=int)
    labels[right] = 1
    assert cut_weight(g, labels) == 1.0
    clusters = partition_graph(g, 100, seed=0)
    assert_valid_partition(g, clusters, 100)
    assert len(clusters) == 3
    assert cut_weight(g, labels_from_clusters(clusters, 240)) == 2.0


def test_disconnected_bisection_sides_are_split(monkeypatch):
    # A random geometric graph on which one normalized 2-way cut leaves a side disconnected.
    rng = np.random.default_rng(106)
    n = int(rng.integers(20, 300))
    pts = rng.random((n, 2))
    radius = rng.uniform(0.05, 0.3)
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    g = build_image_graph(n, pairs[:, 0], pairs[:, 1], rng.integers(1, 300, len(pairs)))
    s_max = int(rng.integers(3, 60))
    disconnected_sides = []

    def spy(sub, s, seed=0):
        left, right = ncut_bisect(sub, s, seed)
        for side in (left, right):
            ncomp, _ = cc_labels(sub.tocsr()[side][:, side], directed=False)
            disconnected_sides.append(ncomp > 1)
        return left, right

    monkeypatch.setattr(partition_module, "ncut_bisect", spy)
    clusters = partition_graph(g, s_max, seed=0)
    assert any(disconnected_sides), "the scenario no longer exercises the split"
    assert_valid_partition(g, clusters, s_max)


def test_fragments_merge_into_strongest_neighbour_within_the_bound():
    # parts: A = 0..9 (full at S = 10), B = 10..14, fragment F = {15}, fragment G = {16}
    ei = [*range(9), *range(10, 14), 15, 15, 16]
    ej = [*range(1, 10), *range(11, 15), 0, 10, 14]
    w = [50.0] * 13 + [100.0, 1.0, 7.0]
    g = build_image_graph(17, ei, ej, w)
    parts = [np.arange(10), np.arange(10, 15), np.array([15]), np.array([16])]
    merged = partition_module._merge_fragments(g.adjacency, parts, 10, 3)
    # F shares 100 with A but A is full, so F joins B; then G joins B too (7 > 0).
    assert sorted(p.tolist() for p in merged) == [list(range(10)), list(range(10, 17))]
    merged = partition_module._merge_fragments(g.adjacency, parts, 20, 3)
    # With room everywhere, F joins A (weight 100 beats 1).
    assert sorted(p.tolist() for p in merged) == [[*range(10), 15], [*range(10, 15), 16]]
    merged = partition_module._merge_fragments(g.adjacency, parts, 6, 3)
    # B can take only one: F (smallest id first among equal sizes) joins B, G stays alone.
    assert sorted(p.tolist() for p in merged) == [
        list(range(10)),
        list(range(10, 16)),
        [16],
    ]


@settings(max_examples=100, deadline=None)
@given(random_graphs(max_nodes=150), st.integers(min_value=1, max_value=40), st.integers(0, 3))
def test_partition_properties_on_random_graphs(g, s_max, seed):
    clusters = partition_graph(g, s_max, seed=seed)
    assert_valid_partition(g, clusters, s_max)
    again = partition_graph(g, s_max, seed=seed)
    assert [c.tolist() for c in again] == [c.tolist() for c in clusters]


def test_cut_is_much_better_than_random_on_aerial_grid():
    g = aerial_graph(40, 50)
    t0 = time.perf_counter()
    clusters = partition_graph(g, max_cluster_size=100, seed=0)
    log.info("partition of 2,000 images: %.2f s", time.perf_counter() - t0)
    assert_valid_partition(g, clusters, 100)
    labels = labels_from_clusters(clusters, g.num_nodes)
    ours = cut_weight(g, labels)
    rng = np.random.default_rng(0)
    random_cuts = [cut_weight(g, rng.permutation(labels)) for _ in range(10)]
    assert ours <= 0.5 * float(np.mean(random_cuts))
    again = partition_graph(g, max_cluster_size=100, seed=0)
    assert [c.tolist() for c in again] == [c.tolist() for c in clusters]


@pytest.mark.slow
def test_partition_of_10000_images():
    g = aerial_graph(100, 100)
    t0 = time.perf_counter()
    clusters = partition_graph(g, max_cluster_size=100, seed=0)
    log.info("partition of 10,000 images: %.2f s", time.perf_counter() - t0)
    assert_valid_partition(g, clusters, 100)
    labels = labels_from_clusters(clusters, g.num_nodes)
    rng = np.random.default_rng(0)
    random_cuts = [cut_weight(g, rng.permutation(labels)) for _ in range(5)]
    assert cut_weight(g, labels) <= 0.5 * float(np.mean(random_cuts))
