"""Tests of graph.expansion: MaxST-guided subgraph expansion (Alg. 1, lines 3-12)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from _helpers_graph import random_graphs
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from graph.expansion import ExpansionResult, expand_clusters, lost_edges_by_pair
from graph.image_graph import ImageGraph, build_image_graph
from graph.partition import labels_from_clusters, partition_graph


def brute_force_lost(graph: ImageGraph, cores: list[np.ndarray]):
    """{(k1, k2): [(w, u, v), ...]} of lost edges, u in core k1 < k2, by plain iteration."""
    labels = labels_from_clusters(cores, graph.num_nodes)
    lost: dict[tuple[int, int], list[tuple[float, int, int]]] = {}
    for a, b, w in zip(*graph.edges()):
        ka, kb = int(labels[a]), int(labels[b])
        if ka != kb:
            u, v = (int(a), int(b)) if ka < kb else (int(b), int(a))
            lost.setdefault((min(ka, kb), max(ka, kb)), []).append((float(w), u, v))
    return lost


def eta(clusters: tuple[np.ndarray, ...], i: int) -> float:
    """Completeness eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i| (paper Sec. 3.1), by brute force."""
    ci = set(clusters[i].tolist())
    shared = sum(len(ci & set(c.tolist())) for j, c in enumerate(clusters) if j != i)
    return shared / len(ci)


def check_expansion(graph, cores, result: ExpansionResult, c_ratio: float, o_max: int) -> None:
    k_count = len(cores)
    lost = brute_force_lost(graph, cores)
    labels = labels_from_clusters(cores, graph.num_nodes)
    clusters = result.clusters
    assert [c.tolist() for c in result.cores] == [np.sort(c).tolist() for c in cores]
    assert len(clusters) == len(result.stats) == k_count

    # Every image is in at least one cluster and every core is kept.
    covered = np.concatenate(clusters)
    assert np.array_equal(np.unique(covered), np.arange(graph.num_nodes))
    for core, cl in zip(result.cores, clusters):
        assert np.all(np.diff(cl) > 0)
        assert np.isin(core, cl).all()

    # Cluster-graph weights are the numbers of lost edges.
    assert result.lost_edge_counts == {pair: len(e) for pair, e in lost.items()}

    # The MaxST is a maximum spanning forest of the cluster graph.
    cg = nx.Graph()
    cg.add_nodes_from(range(k_count))
    cg.add_weighted_edges_from((a, b, len(e)) for (a, b), e in lost.items())
    ref = nx.maximum_spanning_tree(cg)
    maxst_pairs = {(a, b) for a, b, _ in result.maxst_edges}
    assert len(maxst_pairs) == len(result.maxst_edges) == ref.number_of_edges()
    assert sum(w for *_, w in result.maxst_edges) == ref.size(weight="weight")
    assert all(result.lost_edge_counts[(a, b)] == w for a, b, w in result.maxst_edges)
    tree = nx.Graph(list(maxst_pairs))
    assert nx.is_forest(tree) if tree.number_of_nodes() else True

    # Extra edges are distinct non-tree edges; used pairs have overlap records.
    extra_pairs = [(a, b) for a, b, _ in result.extra_edges]
    assert len(set(extra_pairs)) == len(extra_pairs)
    assert not set(extra_pairs) & maxst_pairs
    used = maxst_pairs | set(extra_pairs)
    assert set(result.overlap_edges) == used

    # At most O_max lost edges per pair, and they are the strongest ones.
    for pair, ends in result.overlap_edges.items():
        weights = sorted((w for w, _, _ in lost[pair]), reverse=True)
        m = min(o_max, len(weights))
        assert ends.shape == (m, 2)
        chosen = [float(graph.adjacency[u, v]) for u, v in ends.tolist()]
        assert chosen == weights[:m]
        assert all(labels[u] == pair[0] and labels[v] == pair[1] for u, v in ends.tolist())

    # Each cluster is its core plus exactly the far ends of the lost edges added along its pairs,
    # so every added image is joined to its new cluster by a lost edge.
    for k in range(k_count):
        expected = set(result.cores[k].tolist())
        for (a, b), ends in result.overlap_edges.items():
            if a == k:
                expected |= set(ends[:, 1].tolist())
            elif b == k:
                expected |= set(ends[:, 0].tolist())
        assert set(clusters[k].tolist()) == expected
        for v in set(clusters[k].tolist()) - set(result.cores[k].tolist()):
            assert labels[v] != k
            nbrs = graph.adjacency[v].indices
            assert np.any(labels[nbrs] == k), "an added image has a lost edge into the core"

    # Every MaxST edge is an overlap the merge can use.
    for a, b, count in result.maxst_edges:
        shared = np.intersect1d(clusters[a], clusters[b]).size
        m = min(o_max, count)
        assert shared >= min(3, m + 1)

    # Completeness: reported values are right; a cluster below C has used all its lost edges.
    for k, stat in enumerate(result.stats):
        assert stat.core_size == result.cores[k].size
        assert stat.size == clusters[k].size
        assert stat.completeness == pytest.approx(eta(clusters, k))
        if stat.completeness < c_ratio:
            incident = [p for p in lost if k in p]
            assert all(p in used for p in incident)


@settings(max_examples=100, deadline=None)
@given(
    random_graphs(distinct_weights=False),
    st.integers(min_value=2, max_value=30),
    st.floats(min_value=0.0, max_value=1.5),
    st.integers(min_value=1, max_value=8),
    st.integers(min_value=0, max_value=5),
)
def test_expansion_properties_on_random_graphs(graph, s_max, c_ratio, o_max, seed):
    cores = partition_graph(graph, s_max, seed=seed)
    labels = labels_from_clusters(cores, graph.num_nodes)
    assert np.all(labels >= 0)
    assert all(c.size <= s_max for c in cores)
    result = expand_clusters(graph, cores, c_ratio, o_max, seed=seed)
    check_expansion(graph, cores, result, c_ratio, o_max)
    again = expand_clusters(graph, cores, c_ratio, o_max, seed=seed)
    assert [c.tolist() for c in again.clusters] == [c.tolist() for c in result.clusters]
    assert again.extra_edges == result.extra_edges


def test_single_cluster_is_returned_unchanged():
    graph = build_image_graph(30, np.arange(29), np.arange(1, 30), np.full(29, 50))
    cores = partition_graph(graph, max_cluster_size=100)
    assert len(cores) == 1
    result = expand_clusters(graph, cores)
    assert [c.tolist() for c in result.clusters] == [list(range(30))]
    assert result.stats[0].completeness == 0.0
    assert result.stats[0].core_size == result.stats[0].size == 30
    assert result.maxst_edges == () and result.extra_edges == ()
    assert result.lost_edge_counts == {} and result.overlap_edges == {}


def three_cluster_chain():
    """Cores A={0..3}, B={4..7}, C={8..11}; A-B has 3 lost edges, B-C 2, A-C 1."""
    ei, ej, w = [], [], []
    for base in (0, 4, 8):  # each core is a 4-cycle
        for t in range(4):
            ei.append(base + t)
            ej.append(base + (t + 1) % 4)
            w.append(500)
    lost = [(0, 4, 90), (1, 5, 80), (2, 6, 70), (6, 8, 60), (7, 9, 65), (3, 11, 10)]
    for a, b, wt in lost:
        ei.append(a)
        ej.append(b)
        w.append(wt)
    graph = build_image_graph(12, ei, ej, w)
    cores = [np.arange(0, 4), np.arange(4, 8), np.arange(8, 12)]
    return graph, cores


def test_maxst_overlaps_take_strongest_edges_first():
    graph, cores = three_cluster_chain()
    lost = lost_edges_by_pair(graph, labels_from_clusters(cores, 12))
    assert lost[(0, 1)][0].tolist() == [[0, 4], [1, 5], [2, 6]]
    assert lost[(1, 2)][0].tolist() == [[7, 9], [6, 8]]  # 65 before 60
    assert lost[(0, 2)][1].tolist() == [10.0]

    result = expand_clusters(graph, cores, completeness_ratio=0.0, max_overlap=2)
    assert result.maxst_edges == ((0, 1, 3), (1, 2, 2))
    assert result.extra_edges == ()
    assert result.overlap_edges[(0, 1)].tolist() == [[0, 4], [1, 5]]
    assert [c.tolist() for c in result.clusters] == [
        [0, 1, 2, 3, 4, 5],
        [0, 1, 4, 5, 6, 7, 8, 9],
        [6, 7, 8, 9, 10, 11],
    ]
    check_expansion(graph, cores, result, 0.0, 2)


def test_completeness_pulls_in_non_tree_edges():
    graph, cores = three_cluster_chain()
    # After the MaxST step with O_max=2: A={0..5}, B={0,1,4..9}, C={6..11};
    # eta(A) = 4/6, eta(B) = (4 + 4)/8 = 1, eta(C) = 4/6.
    result = expand_clusters(graph, cores, completeness_ratio=0.5, max_overlap=2)
    assert result.extra_edges == ()
    assert [s.completeness for s in result.stats] == pytest.approx([4 / 6, 1.0, 4 / 6])
    # With C = 0.7, A and C are below: the only non-tree edge A-C is used (A gains 11, C 3).
    result = expand_clusters(graph, cores, completeness_ratio=0.7, max_overlap=2)
    assert result.extra_edges == ((0, 2, 1),)
    assert result.overlap_edges[(0, 2)].tolist() == [[3, 11]]
    assert 11 in result.clusters[0] and 3 in result.clusters[2]
    assert [s.completeness for s in result.stats] == pytest.approx([6 / 7, 1.0, 6 / 7])
    check_expansion(graph, cores, result, 0.7, 2)
    # An unreachable C: every lost edge is used and the clusters stay below it, no error.
    result = expand_clusters(graph, cores, completeness_ratio=5.0, max_overlap=50)
    assert set(result.overlap_edges) == {(0, 1), (1, 2), (0, 2)}
    assert all(s.completeness < 5.0 for s in result.stats)
    check_expansion(graph, cores, result, 5.0, 50)


def test_bad_cores_raise():
    graph, _ = three_cluster_chain()
    with pytest.raises(ValueError):
        expand_clusters(graph, [np.arange(0, 6), np.arange(5, 12)])  # overlap
    with pytest.raises(ValueError):
        expand_clusters(graph, [np.arange(0, 12), np.array([], dtype=int)])  # empty
    with pytest.raises(ValueError):
        expand_clusters(graph, [np.arange(0, 13)])  # out of range
    with pytest.raises(ValueError):
        expand_clusters(graph, [np.arange(0, 12)], max_overlap=0)


def test_aerial_grid_expansion_reaches_completeness():
    rows, cols = 20, 25
    yy, xx = np.mgrid[0:rows, 0:cols]
    centres = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    pairs = cKDTree(centres).query_pairs(3.0, output_type="ndarray")
    dist = np.linalg.norm(centres[pairs[:, 0]] - centres[pairs[:, 1]], axis=1)
    graph = build_image_graph(rows * cols, pairs[:, 0], pairs[:, 1], np.round(400 / dist))
    cores = partition_graph(graph, max_cluster_size=50, seed=0)
    result = expand_clusters(graph, cores, completeness_ratio=0.5, max_overlap=10, seed=0)
    check_expansion(graph, cores, result, 0.5, 10)
    assert all(s.completeness >= 0.5 for s in result.stats)
    assert all(s.size <= s.core_size + 10 * (len(cores) - 1) for s in result.stats)
