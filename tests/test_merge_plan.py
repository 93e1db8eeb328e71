"""Tests of graph.merge_plan: MinST and minimum-height-tree anchor (paper Sec. 3.2.3, Alg. 2)."""

from __future__ import annotations

import math

import networkx as nx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graph.merge_plan import MergePlan, minimum_spanning_edges, plan_merges

# Paper Figure 4: MinST edges c0-c1, c2-c1, c1-c3, c3-c4 (+ non-tree edges with larger MSD).
FIG4_WEIGHTS = {
    (0, 1): 0.10,
    (2, 1): 0.20,
    (1, 3): 0.15,
    (3, 4): 0.05,
    (0, 2): 0.90,  # dotted edges of the figure: never in the MinST
    (2, 3): 0.80,
    (4, 1): math.inf,
}


def test_figure4_larger_c1_is_anchor():
    sizes = {0: 30, 1: 80, 2: 40, 3: 60, 4: 50}
    (plan,) = plan_merges(range(5), sizes, FIG4_WEIGHTS)
    assert plan.anchor == 1
    assert plan.clusters == (0, 1, 2, 3, 4)
    assert plan.total_size == 260
    assert {(a, b) for a, b, _ in plan.edges} == {(0, 1), (1, 2), (1, 3), (3, 4)}
    assert [w for *_, w in plan.edges] == [0.05, 0.10, 0.15, 0.20]  # Kruskal order
    assert plan.parent == {0: 1, 1: None, 2: 1, 3: 1, 4: 3}
    assert plan.layer == {0: 1, 2: 1, 4: 1, 3: 2, 1: 2}
    assert plan.num_layers == 2
    assert plan.merge_order == ((0, 1), (2, 1), (4, 3), (3, 1))
    assert plan.path == {0: (0, 1), 1: (1,), 2: (2, 1), 3: (3, 1), 4: (4, 3, 1)}


def test_figure4_mirrored_larger_c3_is_anchor():
    sizes = {0: 30, 1: 60, 2: 40, 3: 80, 4: 50}
    (plan,) = plan_merges(range(5), sizes, FIG4_WEIGHTS)
    assert plan.anchor == 3
    assert plan.parent == {0: 1, 1: 3, 2: 1, 3: None, 4: 3}
    assert plan.layer == {0: 1, 2: 1, 4: 1, 1: 2, 3: 2}
    assert plan.merge_order == ((0, 1), (2, 1), (4, 3), (1, 3))
    assert plan.path[0] == (0, 1, 3) and plan.path[2] == (2, 1, 3) and plan.path[4] == (4, 3)


def test_figure4_equal_sizes_smaller_id_wins():
    sizes = {0: 1, 1: 50, 2: 1, 3: 50, 4: 1}
    (plan,) = plan_merges(range(5), sizes, FIG4_WEIGHTS)
    assert plan.anchor == 1


def test_single_centre_is_anchor_whatever_the_sizes():
    # path 0-1-2: the centre 1 is the anchor even if it is the smallest cluster
    (plan,) = plan_merges([0, 1, 2], {0: 100, 1: 1, 2: 100}, {(0, 1): 1.0, (1, 2): 1.0})
    assert plan.anchor == 1
    assert plan.num_layers == 1
    assert plan.layer == {0: 1, 1: 1, 2: 1}


def test_forest_gives_one_plan_per_component_largest_first():
    ids = [10, 11, 12, 20, 21, 30]
    sizes = {10: 5, 11: 5, 12: 5, 20: 40, 21: 1, 30: 7}
    weights = {(10, 11): 1.0, (11, 12): 2.0, (20, 21): 0.5, (12, 20): math.inf}
    plans = plan_merges(ids, sizes, weights)
    assert [p.clusters for p in plans] == [(20, 21), (10, 11, 12), (30,)]
    assert [p.total_size for p in plans] == [41, 15, 7]
    assert [p.anchor for p in plans] == [20, 11, 30]
    iso = plans[2]
    assert iso.parent == {30: None} and iso.layer == {30: 0} and iso.num_layers == 0
    assert iso.path == {30: (30,)} and iso.edges == () and iso.merge_order == ()


def test_inf_edges_are_not_used():
    weights = {(0, 1): 1.0, (1, 2): math.inf, (0, 2): math.inf}
    plans = plan_merges([0, 1, 2], {0: 1, 1: 1, 2: 1}, weights)
    assert [p.clusters for p in plans] == [(0, 1), (2,)]
    assert minimum_spanning_edges([0, 1, 2], weights) == [(0, 1, 1.0)]


def test_both_orientations_use_the_smaller_weight():
    for weights in (
        {(0, 1): 5.0, (1, 0): 1.0, (1, 2): 3.0, (0, 2): 2.0},
        {(1, 0): 1.0, (0, 1): 5.0, (1, 2): 3.0, (0, 2): 2.0},
    ):
        assert minimum_spanning_edges([0, 1, 2], weights) == [(0, 1, 1.0), (0, 2, 2.0)]


def test_no_clusters():
    assert plan_merges([], {}, {}) == []


@pytest.mark.parametrize(
    "ids, sizes, weights",
    [
        ([0, 1], {0: 1, 1: 1}, {(0, 1): math.nan}),
        ([0, 1], {0: 1, 1: 1}, {(0, 1): -math.inf}),
        ([0, 1], {0: 1, 1: 1}, {(0, 2): 1.0}),
        ([0, 1], {0: 1, 1: 1}, {(1, 1): 1.0}),
        ([0, 1], {0: 1}, {(0, 1): 1.0}),
        ([0, 0], {0: 1}, {}),
    ],
)
def test_bad_input_raises(ids, sizes, weights):
    with pytest.raises(ValueError):
        plan_merges(ids, sizes, weights)


@st.composite
def cluster_graphs(draw):
    n = draw(st.integers(min_value=1, max_value=14))
    ids = draw(st.lists(st.integers(0, 1000), min_size=n, max_size=n, unique=True))
    sizes = {c: draw(st.integers(1, 6)) for c in ids}  # small range: many size ties
    weights = {}
    for a in range(n):
        for b in range(a + 1, n):
            if draw(st.booleans()):
                w = draw(st.one_of(st.integers(1, 5).map(float), st.just(math.inf)))
                weights[(ids[a], ids[b])] = w
    return ids, sizes, weights


def check_plan(plan: MergePlan, sizes) -> None:
    nodes = list(plan.clusters)
    tree = nx.Graph()
    tree.add_nodes_from(nodes)
    tree.add_edges_from((a, b) for a, b, _ in plan.edges)
    assert nx.is_tree(tree)
    # The anchor is a centre of the MinST: it minimises the longest path to it (brute force).
    ecc = nx.eccentricity(tree)
    radius = min(ecc.values())
    assert ecc[plan.anchor] == radius
    assert plan.num_layers == radius
    centres = [v for v in nodes if ecc[v] == radius]
    if len(centres) == 2:  # two left: the larger cluster wins, ties by smaller id
        assert plan.anchor == min(centres, key=lambda v: (-sizes[v], v))
    assert max(len(p) - 1 for p in plan.path.values()) == radius
    # Parents, layers, paths and merge order are consistent with the tree.
    assert plan.parent[plan.anchor] is None and plan.layer[plan.anchor] == plan.num_layers
    for v in nodes:
        path = plan.path[v]
        assert path[0] == v and path[-1] == plan.anchor
        assert path == tuple(nx.shortest_path(tree, v, plan.anchor))
        if v != plan.anchor:
            p = plan.parent[v]
            assert tree.has_edge(v, p)
            assert 1 <= plan.layer[v] <= plan.num_layers
            assert plan.layer[v] < plan.layer[p] or (
                p == plan.anchor and plan.layer[v] == plan.layer[p]
            )
    order = plan.merge_order
    assert sorted(c for c, _ in order) == sorted(v for v in nodes if v != plan.anchor)
    assert list(order) == sorted(order, key=lambda cp: (plan.layer[cp[0]], cp[0]))
    position = {c: i for i, (c, _) in enumerate(order)}
    for child, parent in order:
        assert plan.parent[child] == parent
        if parent != plan.anchor:
            assert position[child] < position[parent]  # a cluster merges after its children


@settings(max_examples=150, deadline=None)
@given(cluster_graphs())
def test_plan_properties_on_random_cluster_graphs(data):
    ids, sizes, weights = data
    plans = plan_merges(ids, sizes, weights)
    # Plans partition the clusters and follow the components of the finite-weight graph.
    g = nx.Graph()
    g.add_nodes_from(ids)
    g.add_weighted_edges_from((a, b, w) for (a, b), w in weights.items() if w != math.inf)
    assert sorted(p.clusters for p in plans) == sorted(
        tuple(sorted(c)) for c in nx.connected_components(g)
    )
    keys = [(-p.total_size, p.clusters[0]) for p in plans]
    assert keys == sorted(keys)
    # The MinST is minimum: same total weight as networkx's spanning forest.
    ref = nx.minimum_spanning_tree(g)
    assert sum(w for p in plans for *_, w in p.edges) == pytest.approx(ref.size(weight="weight"))
    for plan in plans:
        assert plan.total_size == sum(sizes[c] for c in plan.clusters)
        check_plan(plan, sizes)
    assert plan_merges(ids, sizes, weights) == plans
