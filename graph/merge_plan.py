"""Merge plan of the local models: MinST + minimum-height-tree anchor (paper section 3.2, Alg. 2).

Given the cluster graph (Alg. 2, line 1: one node per cluster; an edge where two local models
could be aligned, weighted by their residual error, the MSD of Eq. 11, the larger of the two
directions' MSE of Eq. 10; section 3.2.2), the plan is:

1. the Kruskal minimum spanning tree (Alg. 2, line 2) selects the ``N - 1`` most accurate
   similarity transformations (section 3.2.2, Eq. 7-9: minimising the sum of ``-log p_ij``
   maximises the probability that every tree edge aligns);
2. the anchor (reference frame) is the root of a minimum height tree (section 3.2.3), found by
   peeling the leaves layer by layer, each leaf merging into its only neighbour (Alg. 2, lines
   4-7); when one node remains it is the anchor; when two remain, the larger cluster is the
   anchor (ties: the smaller id) and the other merges into it in the last layer (Alg. 2, lines
   8-11);
3. every cluster is transformed along its tree path to the anchor.

The anchor is a centre of the tree, so it minimises the longest path any cluster's
transformation is chained along (the error accumulation the paper wants to bound). A forest
(several merge components) gives one plan per component. "Size" is the cluster's own size
(number of images or registered images, as the caller decides), not the size accumulated by the
merges of the earlier layers.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import networkx as nx

logger = logging.getLogger(__name__)

__all__ = ["MergePlan", "minimum_spanning_edges", "plan_merges"]


@dataclass(frozen=True)
class MergePlan:
    """How the clusters of one merge component are stitched together (Alg. 2).

    Attributes:
        anchor: the reference cluster all others are transformed into.
        clusters: the cluster ids of this component, ascending.
        total_size: sum of the clusters' sizes.
        parent: the cluster each cluster merges into; ``None`` for the anchor.
        layer: the peeling layer (1-based) at which each cluster merged into its parent; the
            anchor's entry is ``num_layers``.
        num_layers: number of peeling layers (0 for a single cluster).
        path: for each cluster, the cluster ids from itself to the anchor (both included).
        edges: the MinST edges ``(a, b, weight)``, ``a < b``, in Kruskal order.
        merge_order: ``(child, parent)`` merges in the order to apply them: by layer, then by
            child id; applying them in order folds every cluster into the anchor.
    """

    anchor: int
    clusters: tuple[int, ...]
    total_size: int
    parent: dict[int, int | None]
    layer: dict[int, int]
    num_layers: int
    path: dict[int, tuple[int, ...]]
    edges: tuple[tuple[int, int, float], ...]
    merge_order: tuple[tuple[int, int], ...]


def minimum_spanning_edges(
    cluster_ids: Sequence[int], weights: Mapping[tuple[int, int], float]
) -> list[tuple[int, int, float]]:
    """Kruskal minimum spanning forest of the cluster graph (paper section 3.2.3, Alg. 2, line 2).

    Minimising the sum of the weights ``w_ij = -log p_ij`` (Eq. 9) maximises the probability
    ``P`` that every tree edge aligns (Eq. 7-8); the MSD (Eq. 11) stands in for ``-log p_ij``,
    since only the order of the weights decides the tree (section 3.2.2).

    Edges with infinite weight (or absent) cannot align and are not used. Both orientations
    of a pair may be given; the smaller weight counts. Ties go to the lexicographically
    smaller pair ``(a, b)``.

    Returns:
        ``(a, b, weight)`` with ``a < b``, in Kruskal order (ascending weight).

    Raises:
        ValueError: for a NaN or ``-inf`` weight, a self loop or an id not in ``cluster_ids``.
    """
    ids = set(cluster_ids)
    best: dict[tuple[int, int], float] = {}
    for (a, b), w in weights.items():
        a, b, w = int(a), int(b), float(w)
        if a not in ids or b not in ids:
            raise ValueError(f"weight for ({a}, {b}) names a cluster not in cluster_ids")
        if a == b:
            raise ValueError(f"self loop ({a}, {b}) in the cluster graph")
        if w == math.inf:
            continue
        if not math.isfinite(w):
            raise ValueError(f"invalid weight {w} for clusters ({a}, {b})")
        key = (min(a, b), max(a, b))
        best[key] = min(w, best.get(key, math.inf))
    g = nx.Graph()
    g.add_nodes_from(sorted(ids))
    for (a, b), w in sorted(best.items()):
        g.add_edge(a, b, weight=w)
    # Kruskal's sort is stable: equal weights keep the (a, b) insertion order.
    return [
        (min(a, b), max(a, b), float(d["weight"]))
        for a, b, d in nx.minimum_spanning_edges(g, algorithm="kruskal", data=True)
    ]


def plan_merges(
    cluster_ids: Sequence[int],
    sizes: Mapping[int, int],
    weights: Mapping[tuple[int, int], float],
    anchor: int | None = None,
) -> list[MergePlan]:
    """Plan the merges of local reconstructions: MinST, then MHT anchor (paper section 3.2.3,
    Alg. 2, lines 2-12).

    Args:
        cluster_ids: the clusters (distinct integer ids).
        sizes: size of every cluster (used to pick the anchor when two nodes remain).
        weights: alignment weight (MSD, Eq. 11) of cluster pairs ``(a, b)``; ``math.inf`` or
            an absent pair means the two clusters cannot be aligned.
        anchor: a cluster given as the base node of its component (Alg. 2 with the anchor
            given: an existing model that new clusters are merged into and that must not move);
            that component's tree is rooted there instead of at a minimum-height-tree centre
            (:func:`_plan_rooted`).  The other components are planned as without it.

    Returns:
        One :class:`MergePlan` per connected component of the MinST forest, ordered by total
        size descending, ties by smallest cluster id; with ``anchor``, its component first. An
        isolated cluster is a plan of its own with itself as anchor.
    """
    ids = [int(c) for c in cluster_ids]
    if len(set(ids)) != len(ids):
        raise ValueError("cluster_ids must be distinct")
    missing = [c for c in ids if c not in sizes]
    if missing:
        raise ValueError(f"no size for clusters {missing}")
    if anchor is not None and int(anchor) not in ids:
        raise ValueError(f"anchor {anchor} is not one of the clusters")

    mst_edges = minimum_spanning_edges(ids, weights)
    forest = nx.Graph()
    forest.add_nodes_from(sorted(ids))
    forest.add_weighted_edges_from(mst_edges)

    plans = []
    for comp in nx.connected_components(forest):
        comp_edges = tuple(e for e in mst_edges if e[0] in comp)
        if anchor is not None and int(anchor) in comp:
            plans.append(_plan_rooted(sorted(comp), comp_edges, sizes, int(anchor)))
        else:
            plans.append(_plan_tree(sorted(comp), comp_edges, sizes))
    plans.sort(key=lambda p: (p.anchor != anchor, -p.total_size, p.clusters[0]))
    logger.info(
        "merge plan: %d clusters, %d MinST edges, %d components, anchors %s",
        len(ids),
        len(mst_edges),
        len(plans),
        [p.anchor for p in plans],
    )
    return plans


def _plan_tree(
    nodes: list[int], edges: tuple[tuple[int, int, float], ...], sizes: Mapping[int, int]
) -> MergePlan:
    """Minimum height tree anchor of one tree by peeling leaves (Alg. 2, lines 3-12)."""
    neighbours: dict[int, set[int]] = {v: set() for v in nodes}
    for a, b, _ in edges:
        neighbours[a].add(b)
        neighbours[b].add(a)

    remaining = set(nodes)
    parent: dict[int, int | None] = {}
    layer: dict[int, int] = {}
    merge_order: list[tuple[int, int]] = []
    num_layers = 0
    while len(remaining) > 2:  # Alg. 2, lines 4-7: merge all current leaves
        num_layers += 1
        leaves = sorted(v for v in remaining if len(neighbours[v]) == 1)
        for leaf in leaves:
            (target,) = neighbours[leaf]
            parent[leaf] = target
            layer[leaf] = num_layers
            merge_order.append((leaf, target))
        for leaf in leaves:
            (target,) = neighbours.pop(leaf)
            neighbours[target].discard(leaf)
            remaining.discard(leaf)
    if len(remaining) == 2:  # Alg. 2, lines 8-11: the larger cluster is the anchor
        num_layers += 1
        a, b = sorted(remaining)
        anchor, other = (a, b) if int(sizes[a]) >= int(sizes[b]) else (b, a)
        parent[other] = anchor
        layer[other] = num_layers
        merge_order.append((other, anchor))
    else:
        (anchor,) = remaining
    parent[anchor] = None
    layer[anchor] = num_layers

    path = _paths_to_root(nodes, parent)

    return MergePlan(
        anchor=anchor,
        clusters=tuple(nodes),
        total_size=sum(int(sizes[v]) for v in nodes),
        parent={v: parent[v] for v in nodes},
        layer={v: layer[v] for v in nodes},
        num_layers=num_layers,
        path=path,
        edges=edges,
        merge_order=tuple(merge_order),
    )


def _paths_to_root(nodes: list[int], parent: Mapping[int, int | None]) -> dict[int, tuple[int, ...]]:
    """Each node's chain of parents up to the root (itself first, the root last)."""
    path: dict[int, tuple[int, ...]] = {}
    for v in nodes:
        chain = [v]
        while parent[chain[-1]] is not None:
            chain.append(parent[chain[-1]])  # type: ignore[arg-type]
        path[v] = tuple(chain)
    return path


def _plan_rooted(
    nodes: list[int], edges: tuple[tuple[int, int, float], ...], sizes: Mapping[int, int], anchor: int
) -> MergePlan:
    """Alg. 2 with the base node given (lines 3-12 peel the leaves until one node is left; here
    that node is ``anchor``): the MinST is rooted at ``anchor``, every other node merges into its
    neighbour towards it, and a node merges in the layer after the last of its own children
    (a leaf in layer 1), so the layers are the peeling order of Alg. 2 that ends at ``anchor``."""
    neighbours: dict[int, list[int]] = {v: [] for v in nodes}
    for a, b, _ in edges:
        neighbours[a].append(b)
        neighbours[b].append(a)
    parent: dict[int, int | None] = {anchor: None}
    order = [anchor]  # breadth first from the anchor, neighbours by id
    for v in order:
        for w in sorted(neighbours[v]):
            if w not in parent:
                parent[w] = v
                order.append(w)
    height = {v: 0 for v in nodes}
    for v in reversed(order[1:]):
        p = parent[v]
        height[p] = max(height[p], height[v] + 1)  # type: ignore[index]
    layer = {v: height[v] + 1 for v in nodes if v != anchor}
    num_layers = height[anchor]
    layer[anchor] = num_layers
    path = _paths_to_root(nodes, parent)
    merge_order = tuple((v, parent[v]) for v in sorted((v for v in nodes if v != anchor), key=lambda v: (layer[v], v)))
    return MergePlan(
        anchor=anchor,
        clusters=tuple(nodes),
        total_size=sum(int(sizes[v]) for v in nodes),
        parent={v: parent[v] for v in nodes},
        layer=layer,
        num_layers=num_layers,
        path=path,
        edges=edges,
        merge_order=merge_order,  # type: ignore[arg-type]
    )
