"""Tests of graph.clustering: Alg. 1 under the size and completeness constraints (paper Sec. 3.1)."""

from __future__ import annotations

import numpy as np
from _helpers_graph import random_graphs
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from test_graph_expansion import check_expansion

from graph.clustering import cluster_images, core_size_bound, recut_size_bound
from graph.image_graph import build_image_graph, connected_components


def test_core_and_recut_bounds():
    # room for C S/2 added images (imports = exports), or half a MaxST edge's overlap
    assert core_size_bound(100, 0.5, 6) == 75
    assert core_size_bound(12, 0.5, 6) == 9
    assert core_size_bound(15, 0.5, 6) == 11
    assert core_size_bound(12, 0.0, 6) == 9  # the merge's overlap alone
    assert core_size_bound(5, 0.5, 6) == 3  # at least half the cluster is its own core
    assert core_size_bound(4, 1.0, 6) == 2
    # a core of (1 - C) S_max reaches C by its own additions; at least half of S_max
    assert recut_size_bound(100, 0.5) == 50
    assert recut_size_bound(100, 0.3) == 70
    assert recut_size_bound(100, 0.9) == 50
    assert recut_size_bound(5, 0.5) == 3


def ring_graph(n: int, reach: int = 4):
    """Views on a ring (like the demo's arc or temple_ring): each matches its ``reach`` nearest
    neighbours on both sides, weight falling with the distance."""
    ei, ej, w = [], [], []
    for i in range(n):
        for d in range(1, reach + 1):
            ei.append(i)
            ej.append((i + d) % n)
            w.append(400 // d)
    return build_image_graph(n, ei, ej, w)


def test_small_bound_on_a_ring_never_makes_a_whole_scene_cluster():
    """The issue's demo case: 30 views, S_max 12. Every cluster within the bound, none holding
    the scene, every cluster complete. Each view matches 4 on either side, so a cut has 4 ends
    of lost edges on each side: a core of 8 with two MaxST edges needs 2 x (6 - 4) added images
    and its neighbours have too little room left for the rest; the MaxST edges that stay below
    min_overlap are reported, for that reason, and still share 5 images."""
    graph = ring_graph(30)
    result = cluster_images(graph, 12, completeness_ratio=0.5, max_overlap=50, min_overlap=6)
    expansion = result.expansion
    assert all(c.size <= 12 for c in expansion.clusters)
    assert all(c.size <= core_size_bound(12, 0.5, 6) for c in expansion.cores)
    assert len(expansion.clusters) >= 3
    assert expansion.incomplete == ()
    assert all(s.completeness >= 0.5 for s in expansion.stats)
    assert all(t.reason == "bound" and t.common == 5 for t in expansion.thin_overlaps)
    assert all(expansion.common_images[(a, b)] >= 5 for a, b, _ in expansion.maxst_edges)
    check_expansion(graph, list(expansion.cores), expansion, 0.5, 50, 12, 6)
    # a looser bound leaves room for every MaxST edge's min_overlap
    looser = cluster_images(graph, 14, completeness_ratio=0.5, max_overlap=50, min_overlap=6)
    assert looser.expansion.thin_overlaps == () and looser.expansion.incomplete == ()
    assert all(c.size <= 14 for c in looser.expansion.clusters)


def test_a_component_that_fits_is_one_cluster_and_isolated_images_are_left_out():
    ring = ring_graph(20)
    i, j, w = ring.edges()
    # nodes 0..19: a ring that fits S_max = 24 although larger than its core bound 18;
    # nodes 20..79: a ring that must be cut; node 80: isolated
    graph = build_image_graph(81, np.r_[i, ring_graph(60).edges()[0] + 20],
                              np.r_[j, ring_graph(60).edges()[1] + 20], np.r_[w, ring_graph(60).edges()[2]])
    result = cluster_images(graph, 24)
    assert result.isolated.tolist() == [80]
    clusters = [c.tolist() for c in result.expansion.clusters]
    assert list(range(20)) in clusters
    assert all(c.size <= 24 for c in result.expansion.clusters)
    assert sum(1 for c in clusters if c[0] >= 20) >= 3


def aerial_grid(rows: int, cols: int):
    yy, xx = np.mgrid[0:rows, 0:cols]
    centres = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    pairs = cKDTree(centres).query_pairs(3.0, output_type="ndarray")
    dist = np.linalg.norm(centres[pairs[:, 0]] - centres[pairs[:, 1]], axis=1)
    return build_image_graph(rows * cols, pairs[:, 0], pairs[:, 1], np.round(400 / dist))


def test_aerial_grid_meets_both_constraints():
    graph = aerial_grid(20, 25)
    result = cluster_images(graph, 50, completeness_ratio=0.5, max_overlap=20, min_overlap=6)
    expansion = result.expansion
    check_expansion(graph, list(expansion.cores), expansion, 0.5, 20, 50, 6)
    assert all(c.size <= 50 for c in expansion.clusters)
    assert all(s.completeness >= 0.5 for s in expansion.stats)
    assert expansion.incomplete == () and expansion.thin_overlaps == ()
    assert max(c.size for c in expansion.cores) <= core_size_bound(50, 0.5, 6)
    # without the backup forest's exports a core fills up below C and is cut again
    plain = cluster_images(graph, 50, completeness_ratio=0.5, max_overlap=20, min_overlap=6, backup_forest=False)
    assert plain.recut_cores == 1 and plain.expansion.incomplete == ()
    assert len(plain.expansion.cores) == len(expansion.cores) + 1
    assert sum(c.size <= plain.recut_size_bound for c in plain.expansion.cores) >= 2
    check_expansion(graph, list(plain.expansion.cores), plain.expansion, 0.5, 20, 50, 6)


@settings(max_examples=80, deadline=None)
@given(
    random_graphs(),
    st.integers(min_value=2, max_value=40),
    st.floats(min_value=0.0, max_value=1.0),
    st.integers(min_value=1, max_value=30),
    st.integers(min_value=2, max_value=8),
    st.integers(min_value=0, max_value=3),
)
def test_clustering_properties_on_random_graphs(graph, s_max, c_ratio, o_max, m_min, seed):
    result = cluster_images(graph, s_max, c_ratio, o_max, m_min, seed=seed)
    expansion = result.expansion
    cores = list(expansion.cores)
    # cores partition the images that have an edge; nothing exceeds the bound
    covered = np.concatenate(cores) if cores else np.array([], dtype=np.int64)
    degree = np.diff(graph.adjacency.indptr)
    assert np.array_equal(np.sort(covered), np.flatnonzero(degree > 0))
    assert result.isolated.tolist() == np.flatnonzero(degree == 0).tolist()
    assert all(c.size <= s_max for c in expansion.clusters)
    check_expansion(graph, cores, expansion, c_ratio, o_max, s_max, m_min) if cores else None
    # a component that fits is one cluster; a core above the re-cut bound never ends full below C
    for comp in connected_components(graph):
        if 2 <= comp.size <= s_max:
            assert any(np.array_equal(comp, c) for c in expansion.clusters)
    for c in expansion.incomplete:
        assert c.reason != "bound" or expansion.cores[c.cluster].size <= result.recut_size_bound
    again = cluster_images(graph, s_max, c_ratio, o_max, m_min, seed=seed)
    assert [c.tolist() for c in again.expansion.clusters] == [c.tolist() for c in expansion.clusters]
