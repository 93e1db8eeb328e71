"""Tests of graph.expansion: MaxST-guided subgraph expansion (Alg. 1, lines 3-12)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from _helpers_graph import random_graphs
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from graph.expansion import (
    ExpansionResult,
    IncompleteCluster,
    ThinOverlap,
    expand_clusters,
    lost_edges_by_pair,
)
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


def eta(clusters, i: int) -> float:
    """Completeness eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i| (paper Sec. 3.1), by brute force."""
    ci = set(np.asarray(list(clusters[i])).tolist())
    shared = sum(len(ci & set(np.asarray(list(c)).tolist())) for j, c in enumerate(clusters) if j != i)
    return shared / len(ci)


def replay(graph, cores, result: ExpansionResult, c_ratio, o_max, s_max, m_min) -> None:
    """Replay ``result.additions`` from the cores and check every addition was allowed when made:
    the far end of a walked lost edge of its pair, into a cluster below ``S_max``, at most
    ``O_max`` images per pair; step 1 only while the MaxST pair shares < ``min_overlap`` images,
    steps 2 and 3 only while the cluster is below ``C``; step 2 walks the MaxST's lost edges in one
    descending order of weight; the replay ends at the reported clusters."""
    bound = np.inf if s_max is None else s_max
    members = [set(c.tolist()) for c in result.cores]
    maxst_pairs = {(a, b) for a, b, _ in result.maxst_edges}
    backup_pairs = {(a, b) for a, b, _ in result.backup_edges}
    extra_pairs = {(a, b) for a, b, _ in result.extra_edges}
    added: dict = {}
    last_rank: dict = {}
    last_step, step2_weight = 1, np.inf
    for k, x, k1, k2, step, rank in result.additions.tolist():
        pair = (k1, k2)
        assert k in pair and step >= last_step
        last_step = step
        if step > 1:  # step 1 walks a pair in two rounds, each from its strongest lost edge
            assert rank >= last_rank.get((pair, step), 0)
            last_rank[(pair, step)] = rank
        u, v = result.overlap_edges[pair][rank].tolist()
        assert x == (v if k == k1 else u) and x not in members[k]
        assert len(members[k]) < bound and added.get(pair, 0) < o_max
        if step == 1:
            assert pair in maxst_pairs | backup_pairs and len(members[k1] & members[k2]) < m_min
        else:
            assert eta(members, k) < c_ratio, "a complete cluster takes no image in steps 2 and 3"
        if step == 2:
            assert pair in maxst_pairs
            weight = float(graph.adjacency[u, v])
            assert weight <= step2_weight, "step 2 walks the MaxST's lost edges strongest first"
            step2_weight = weight
        if step == 3:
            assert pair in extra_pairs
        members[k].add(x)
        added[pair] = added.get(pair, 0) + 1
    assert [sorted(m) for m in members] == [c.tolist() for c in result.clusters]


def check_expansion(graph, cores, result: ExpansionResult, c_ratio, o_max, s_max=None, m_min=6) -> None:
    k_count = len(cores)
    lost = brute_force_lost(graph, cores)
    clusters = result.clusters
    bound = np.inf if s_max is None else s_max
    assert [c.tolist() for c in result.cores] == [np.sort(c).tolist() for c in cores]
    assert len(clusters) == len(result.stats) == k_count

    # Clusters hold exactly the images of the cores, every core is kept, the bound holds.
    covered = np.concatenate(clusters)
    assert np.array_equal(np.unique(covered), np.sort(np.concatenate(result.cores)))
    for core, cl in zip(result.cores, clusters):
        assert np.all(np.diff(cl) > 0)
        assert np.isin(core, cl).all()
        assert cl.size <= max(bound, core.size)

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

    # The backup forest is a maximum spanning forest of the other cluster edges.
    backup_pairs = {(a, b) for a, b, _ in result.backup_edges}
    rest = cg.copy()
    rest.remove_edges_from(maxst_pairs)
    if result.backup_edges:
        second = nx.maximum_spanning_tree(rest)
        assert len(backup_pairs) == len(result.backup_edges) == second.number_of_edges()
        assert sum(w for *_, w in result.backup_edges) == second.size(weight="weight")
        assert not backup_pairs & maxst_pairs and nx.is_forest(nx.Graph(list(backup_pairs)))

    # Extra edges are distinct non-tree edges; used pairs have overlap records.
    extra_pairs = [(a, b) for a, b, _ in result.extra_edges]
    assert len(set(extra_pairs)) == len(extra_pairs)
    assert not set(extra_pairs) & maxst_pairs
    used = maxst_pairs | backup_pairs | set(extra_pairs)
    assert set(result.overlap_edges) == used == set(result.common_images)

    # The walked lost edges of a pair are its strongest ones, in order.
    for pair, ends in result.overlap_edges.items():
        weights = sorted((w for w, _, _ in lost[pair]), reverse=True)
        chosen = [float(graph.adjacency[u, v]) for u, v in ends.tolist()]
        assert chosen == weights[: len(chosen)]
    replay(graph, cores, result, c_ratio, o_max, s_max, m_min)

    added = {p: int(np.count_nonzero((result.additions[:, 2] == p[0]) & (result.additions[:, 3] == p[1])))
             for p in used}
    closed = {p: added[p] >= o_max or len(result.overlap_edges[p]) == len(lost[p]) for p in used}
    for pair in used:
        assert added[pair] <= o_max
        assert result.common_images[pair] == np.intersect1d(clusters[pair[0]], clusters[pair[1]]).size

    # Completeness: reported values are right; a cluster below C (with lost edges) is full or
    # has walked every pair it is in to its end; the reason says which.
    incomplete = {c.cluster: c for c in result.incomplete}
    for k, stat in enumerate(result.stats):
        assert stat.core_size == result.cores[k].size
        assert stat.size == clusters[k].size
        assert stat.completeness == pytest.approx(eta(clusters, k))
        incident = [p for p in lost if k in p]
        assert (k in incomplete) == (bool(incident) and stat.completeness < c_ratio)
        if k in incomplete:
            reason = incomplete[k].reason
            full = stat.size >= bound
            assert (reason == "bound") == full
            if not full:
                assert all(p in used and closed[p] for p in incident)
                assert (reason == "max_overlap") == any(added[p] >= o_max for p in incident)

    # Every MaxST edge shares min_overlap images, or the report says why not.
    thin = {(t.k1, t.k2): t for t in result.thin_overlaps}
    for a, b, _ in result.maxst_edges:
        assert ((a, b) in thin) == (result.common_images[(a, b)] < m_min)
        if (a, b) in thin:
            t = thin[(a, b)]
            assert t.common == result.common_images[(a, b)]
            ends = result.overlap_edges[(a, b)]
            missed = [(a, x) for x in ends[:, 1] if x not in clusters[a]]
            missed += [(b, x) for x in ends[:, 0] if x not in clusters[b]]
            assert (t.reason == "max_overlap") == (added[(a, b)] >= o_max)
            if t.reason == "bound":
                assert missed or not closed[(a, b)]
                assert all(clusters[k].size >= bound for k, _ in missed)
                if not closed[(a, b)]:
                    assert clusters[a].size >= bound and clusters[b].size >= bound
            if t.reason == "lost_edges":
                assert closed[(a, b)] and not missed
                assert len(ends) == len(lost[(a, b)])


@settings(max_examples=150, deadline=None)
@given(
    random_graphs(distinct_weights=False),
    st.integers(min_value=2, max_value=30),
    st.one_of(st.none(), st.integers(min_value=0, max_value=20)),
    st.floats(min_value=0.0, max_value=1.5),
    st.integers(min_value=1, max_value=8),
    st.integers(min_value=0, max_value=8),
    st.integers(min_value=0, max_value=5),
)
def test_expansion_properties_on_random_graphs(graph, s_core, room, c_ratio, o_max, m_min, seed):
    cores = partition_graph(graph, s_core, seed=seed)
    labels = labels_from_clusters(cores, graph.num_nodes)
    assert np.all(labels >= 0)
    assert all(c.size <= s_core for c in cores)
    s_max = None if room is None else s_core + room
    backup = seed % 2 == 0
    result = expand_clusters(graph, cores, c_ratio, o_max, seed=seed, max_cluster_size=s_max, min_overlap=m_min,
                             backup_forest=backup)
    check_expansion(graph, cores, result, c_ratio, o_max, s_max, m_min)
    assert backup or result.backup_edges == ()
    again = expand_clusters(graph, cores, c_ratio, o_max, seed=seed, max_cluster_size=s_max, min_overlap=m_min,
                            backup_forest=backup)
    assert [c.tolist() for c in again.clusters] == [c.tolist() for c in result.clusters]
    assert again.extra_edges == result.extra_edges
    assert np.array_equal(again.additions, result.additions)


def test_single_cluster_is_returned_unchanged():
    graph = build_image_graph(30, np.arange(29), np.arange(1, 30), np.full(29, 50))
    cores = partition_graph(graph, max_cluster_size=100)
    assert len(cores) == 1
    result = expand_clusters(graph, cores, max_cluster_size=10)
    assert [c.tolist() for c in result.clusters] == [list(range(30))]
    assert result.stats[0].completeness == 0.0
    assert result.stats[0].core_size == result.stats[0].size == 30
    assert result.maxst_edges == () and result.extra_edges == ()
    assert result.lost_edge_counts == {} and result.overlap_edges == {}
    assert result.incomplete == () and result.thin_overlaps == ()  # nothing to share with


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


def clusters_of(result):
    return [c.tolist() for c in result.clusters]


def test_lost_edges_of_each_pair_strongest_first():
    graph, cores = three_cluster_chain()
    lost = lost_edges_by_pair(graph, labels_from_clusters(cores, 12))
    assert lost[(0, 1)][0].tolist() == [[0, 4], [1, 5], [2, 6]]
    assert lost[(1, 2)][0].tolist() == [[7, 9], [6, 8]]  # 65 before 60
    assert lost[(0, 2)][1].tolist() == [10.0]


def test_merge_overlap_along_the_maxst_first():
    """Step 1: each MaxST edge gets min_overlap common images, both sides taking the far ends of
    the strongest lost edges, whatever C (here 0: nothing more is added)."""
    graph, cores = three_cluster_chain()
    result = expand_clusters(graph, cores, completeness_ratio=0.0, max_overlap=50, min_overlap=2, backup_forest=False)
    assert result.maxst_edges == ((0, 1, 3), (1, 2, 2))
    assert result.extra_edges == ()
    # A-B: (0, 4) gives A image 4 and B image 0: 2 common. B-C: (7, 9) gives B 9 and C 7.
    assert clusters_of(result) == [[0, 1, 2, 3, 4], [0, 4, 5, 6, 7, 9], [7, 8, 9, 10, 11]]
    assert result.overlap_edges[(0, 1)].tolist() == [[0, 4]]
    assert result.additions.tolist() == [[0, 4, 0, 1, 1, 0], [1, 0, 0, 1, 1, 0], [1, 9, 1, 2, 1, 0],
                                         [2, 7, 1, 2, 1, 0]]
    assert result.common_images == {(0, 1): 2, (1, 2): 2}
    assert result.incomplete == () and result.thin_overlaps == ()
    check_expansion(graph, cores, result, 0.0, 50, None, 2)
    # The backup forest (the other cluster edges' maximum spanning forest) is A-C: its lost edge
    # (3, 11) gives A image 11 and C image 3, after the MaxST.
    result = expand_clusters(graph, cores, completeness_ratio=0.0, max_overlap=50, min_overlap=2)
    assert result.backup_edges == ((0, 2, 1),)
    assert result.additions[4:].tolist() == [[0, 11, 0, 2, 1, 0], [2, 3, 0, 2, 1, 0]]
    assert result.common_images == {(0, 1): 2, (0, 2): 2, (1, 2): 2}
    check_expansion(graph, cores, result, 0.0, 50, None, 2)
    # With S_max = 5 the MaxST takes the room first: the backup edge gets nothing.
    result = expand_clusters(graph, cores, completeness_ratio=0.0, max_overlap=50, min_overlap=2,
                             max_cluster_size=5)
    assert result.common_images[(0, 1)] == 2 and result.common_images[(0, 2)] == 0
    check_expansion(graph, cores, result, 0.0, 50, 5, 2)


def test_completeness_stops_a_cluster_at_c_and_pulls_in_non_tree_edges():
    """Steps 2 and 3 by hand, C = 0.5, no merge minimum: the MaxST's lost edges in one
    descending order (90, 80, 70 of A-B, then 65, 60 of B-C), each to the sides below C."""
    graph, cores = three_cluster_chain()
    result = expand_clusters(graph, cores, completeness_ratio=0.5, max_overlap=50, min_overlap=0, backup_forest=False)
    # (0,4): A += 4 (A 1/5, B 1/4), B += 0 (A 2/5, B 2/5); (1,5): A += 5 (A 3/6 = C: stops),
    # B is at 3/5; (2,6): nobody wants; (7,9): C += 7 (B 4/5); (6,8): C += 6 (C 2/6, B 5/5);
    # C is still below: step 3 takes the only non-tree edge A-C, (3,11): C += 3 (C 3/7, A 4/6).
    assert result.additions.tolist() == [
        [0, 4, 0, 1, 2, 0], [1, 0, 0, 1, 2, 0], [0, 5, 0, 1, 2, 1],
        [2, 7, 1, 2, 2, 0], [2, 6, 1, 2, 2, 1], [2, 3, 0, 2, 3, 0],
    ]
    assert clusters_of(result) == [[0, 1, 2, 3, 4, 5], [0, 4, 5, 6, 7], [3, 6, 7, 8, 9, 10, 11]]
    assert [s.completeness for s in result.stats] == pytest.approx([4 / 6, 1.0, 3 / 7])
    assert result.extra_edges == ((0, 2, 1),)
    assert result.overlap_edges[(0, 1)].tolist() == [[0, 4], [1, 5]]  # (2, 6) was never walked
    # C cannot reach 0.5: every lost edge it has was walked.
    assert result.incomplete == (IncompleteCluster(2, pytest.approx(3 / 7), 7, "lost_edges"),)
    check_expansion(graph, cores, result, 0.5, 50, None, 0)


def test_size_bound_and_reasons():
    """S_max = 5 on cores of 4: each cluster takes one image; B-C cannot reach min_overlap 2."""
    graph, cores = three_cluster_chain()
    result = expand_clusters(graph, cores, completeness_ratio=1.0, max_overlap=50, max_cluster_size=5,
                             min_overlap=2, backup_forest=False)
    # A-B: A += 4, B += 0 (both full); B-C: B is full, C += 7 (full): 1 common image.
    assert clusters_of(result) == [[0, 1, 2, 3, 4], [0, 4, 5, 6, 7], [7, 8, 9, 10, 11]]
    assert result.thin_overlaps == (ThinOverlap(1, 2, 1, "bound"),)
    assert [c.reason for c in result.incomplete] == ["bound", "bound", "bound"]
    check_expansion(graph, cores, result, 1.0, 50, 5, 2)


def test_max_overlap_counts_images_per_pair():
    graph, cores = three_cluster_chain()
    result = expand_clusters(graph, cores, completeness_ratio=1.0, max_overlap=2, min_overlap=0, backup_forest=False)
    assert all(n <= 2 for n in np.unique(result.additions[:, 2:4], axis=0, return_counts=True)[1])
    # A-B stops after (0, 4) gave A 4 and B 0; B-C after (7, 9) gave B 9 and C 7; A-C: A 11, C 3.
    assert clusters_of(result) == [[0, 1, 2, 3, 4, 11], [0, 4, 5, 6, 7, 9], [3, 7, 8, 9, 10, 11]]
    assert {c.cluster: c.reason for c in result.incomplete} == {0: "max_overlap", 1: "max_overlap",
                                                                 2: "max_overlap"}
    check_expansion(graph, cores, result, 1.0, 2, None, 0)


def test_an_unreachable_c_uses_every_lost_edge_without_error():
    graph, cores = three_cluster_chain()
    result = expand_clusters(graph, cores, completeness_ratio=5.0, max_overlap=50, backup_forest=False)
    assert set(result.overlap_edges) == {(0, 1), (1, 2), (0, 2)}
    assert all(len(result.overlap_edges[p]) == n for p, n in result.lost_edge_counts.items())
    assert [c.reason for c in result.incomplete] == ["lost_edges"] * 3
    check_expansion(graph, cores, result, 5.0, 50, None, 6)


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


def test_aerial_grid_expansion_within_the_bound():
    rows, cols = 20, 25
    yy, xx = np.mgrid[0:rows, 0:cols]
    centres = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    pairs = cKDTree(centres).query_pairs(3.0, output_type="ndarray")
    dist = np.linalg.norm(centres[pairs[:, 0]] - centres[pairs[:, 1]], axis=1)
    graph = build_image_graph(rows * cols, pairs[:, 0], pairs[:, 1], np.round(400 / dist))
    cores = partition_graph(graph, max_cluster_size=35, seed=0)
    result = expand_clusters(graph, cores, completeness_ratio=0.5, max_overlap=20, seed=0, max_cluster_size=50)
    check_expansion(graph, cores, result, 0.5, 20, 50, 6)
    assert all(s.size <= 50 for s in result.stats)
    assert result.thin_overlaps == ()
    # Without the re-cut of graph.clustering a large core may fill up below C, for that reason only.
    assert all(c.reason == "bound" for c in result.incomplete)
    assert sum(s.completeness >= 0.5 for s in result.stats) >= 0.8 * len(cores)
