"""Tests of graph.image_graph: the weighted image graph (paper Sec. 3.1.1)."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graph.image_graph import ImageGraph, build_image_graph, connected_components, edge_arrays


def test_duplicates_keep_max_weight_and_self_loops_are_dropped():
    g = build_image_graph(
        4,
        edges_i=[0, 1, 0, 2, 3, 2],
        edges_j=[1, 0, 1, 2, 2, 3],
        weights=[10, 30, 20, 99, 5, 7],
    )
    i, j, w = edge_arrays(g)
    assert i.tolist() == [0, 2]
    assert j.tolist() == [1, 3]
    assert w.tolist() == [30.0, 7.0]
    assert g.num_edges == 2
    adj = g.adjacency
    assert adj.dtype == np.float64
    assert adj.diagonal().tolist() == [0.0, 0.0, 0.0, 0.0]
    assert (adj != adj.T).nnz == 0
    assert adj[1, 0] == 30.0 and adj[3, 2] == 7.0
    assert g.degrees().tolist() == [30.0, 30.0, 7.0, 7.0]


def test_zero_weight_edges_are_dropped_and_isolated_nodes_kept():
    g = build_image_graph(3, [0, 1], [1, 2], [0.0, 4.0])
    assert g.num_edges == 1
    nxg = g.to_networkx()
    assert sorted(nxg.nodes) == [0, 1, 2]
    assert list(nxg.edges(data="weight")) == [(1, 2, 4.0)]


@pytest.mark.parametrize(
    "args",
    [
        (3, [0], [3], [1.0]),  # id out of range
        (3, [-1], [0], [1.0]),  # negative id
        (3, [0, 1], [1], [1.0]),  # length mismatch
        (3, [0], [1], [-2.0]),  # negative weight
        (3, [0], [1], [np.nan]),  # NaN weight
        (3, [0], [1], [np.inf]),  # inf weight
        (3, [0.5], [1], [1.0]),  # non-integer id
    ],
)
def test_bad_input_raises(args):
    with pytest.raises(ValueError):
        build_image_graph(*args)


def test_empty_graph():
    g = build_image_graph(0, [], [], [])
    assert g.num_edges == 0
    assert connected_components(g) == []
    g5 = build_image_graph(5, np.array([], dtype=int), np.array([], dtype=int), [])
    assert [c.tolist() for c in connected_components(g5)] == [[0], [1], [2], [3], [4]]


def test_connected_components_order():
    # components {0,5}, {1,2,3}, {4}, {6,7}: largest first, ties by smallest node id
    g = build_image_graph(8, [0, 1, 2, 6], [5, 2, 3, 7], [1, 1, 1, 1])
    comps = connected_components(g)
    assert [c.tolist() for c in comps] == [[1, 2, 3], [0, 5], [6, 7], [4]]
    assert all(c.dtype == np.int64 for c in comps)


def test_subgraph_adjacency():
    g = build_image_graph(4, [0, 1, 2], [1, 2, 3], [5, 6, 7])
    sub = g.subgraph_adjacency([3, 2, 1])
    assert sub.toarray().tolist() == [[0, 7, 0], [7, 0, 6], [0, 6, 0]]


edge_lists = st.integers(min_value=1, max_value=25).flatmap(
    lambda n: st.tuples(
        st.just(n),
        st.lists(
            st.tuples(st.integers(0, n - 1), st.integers(0, n - 1), st.integers(1, 500)),
            max_size=80,
        ),
    )
)


@settings(max_examples=60, deadline=None)
@given(edge_lists)
def test_matches_networkx(data):
    n, edges = data
    ei = [e[0] for e in edges]
    ej = [e[1] for e in edges]
    w = [e[2] for e in edges]
    g = build_image_graph(n, ei, ej, w)
    assert isinstance(g, ImageGraph)

    expected: dict[tuple[int, int], float] = {}
    for a, b, wt in edges:
        if a != b:
            key = (min(a, b), max(a, b))
            expected[key] = max(expected.get(key, 0.0), float(wt))
    i, j, ww = edge_arrays(g)
    assert dict(zip(zip(i.tolist(), j.tolist()), ww.tolist())) == expected
    assert np.all(i < j)

    ref = nx.Graph()
    ref.add_nodes_from(range(n))
    ref.add_edges_from(expected)
    comps = connected_components(g)
    assert sorted(map(frozenset, (c.tolist() for c in comps)), key=min) == sorted(
        map(frozenset, nx.connected_components(ref)), key=min
    )
    sizes = [c.size for c in comps]
    assert sizes == sorted(sizes, reverse=True)
    nxg = g.to_networkx()
    assert sorted(nxg.nodes) == list(range(n))
    assert {(min(a, b), max(a, b)): d for a, b, d in nxg.edges(data="weight")} == expected
