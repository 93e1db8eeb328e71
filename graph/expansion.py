"""Subgraph expansion guided by a maximum spanning tree (paper section 3.1.2, Alg. 1, lines 3-12).

After the NCut partition, the image edges between two cluster cores are "lost". The expansion
gives neighbouring clusters common images so that their local reconstructions can be aligned:

* the cluster graph has one node per cluster and one edge per cluster pair with lost image
  edges, weighted by the NUMBER of lost image edges (Alg. 1, lines 3-4);
* its Kruskal maximum spanning tree (Alg. 1, line 5) is walked edge by edge: along MaxST edge
  ``(k1, k2)`` the strongest lost image edges (descending weight, at most ``O_max``) are added
  to BOTH clusters, cluster ``k1`` gaining the ``k2`` end of each edge and ``k2`` the ``k1`` end
  (Alg. 1, lines 6-9), so every MaxST edge becomes an overlap the merge can use;
* then, while a cluster's completeness ``eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i|`` is below
  ``C``, one of its not-yet-used non-tree cluster edges is picked at random (seeded numpy
  Generator) and its lost edges are added the same way (Alg. 1, lines 10-12), until every
  cluster satisfies ``C`` or the clusters below ``C`` have no unused cluster edge left.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import networkx as nx
import numpy as np

from graph.image_graph import ImageGraph, edge_arrays

logger = logging.getLogger(__name__)

__all__ = ["ClusterStats", "ExpansionResult", "expand_clusters", "lost_edges_by_pair"]

ClusterPair = tuple[int, int]


@dataclass(frozen=True)
class ClusterStats:
    """Per-cluster summary of the expansion.

    Attributes:
        core_size: number of images before expansion (the NCut core).
        size: number of images after expansion.
        completeness: ``eta(i)`` after expansion, with ``|C_i|`` the size AFTER expansion.
    """

    core_size: int
    size: int
    completeness: float


@dataclass(frozen=True, eq=False)
class ExpansionResult:
    """Result of :func:`expand_clusters` (Alg. 1's output ``G_inter``).

    Attributes:
        clusters: members of each cluster after expansion (sorted int64 arrays); index ``k``
            is the index of the core in the input list.
        cores: the input cores (sorted int64 arrays).
        stats: one :class:`ClusterStats` per cluster.
        maxst_edges: MaxST edges ``(k1, k2, n_lost)`` with ``k1 < k2``, in Kruskal order.
        extra_edges: non-tree cluster edges ``(k1, k2, n_lost)`` used for completeness, in the
            order they were picked.
        lost_edge_counts: number of lost image edges of every cluster pair ``(k1, k2)``,
            ``k1 < k2`` (pairs with none are absent): the cluster-graph weights.
        overlap_edges: for every used cluster pair ``(k1, k2)``, the image edges added along it,
            an int64 array of shape ``(m, 2)``, ``m <= O_max``; column 0 is the end in core
            ``k1``, column 1 the end in core ``k2``; strongest first.
        completeness_ratio: the ``C`` that was asked for.
        max_overlap: the ``O_max`` that was used.
    """

    clusters: tuple[np.ndarray, ...]
    cores: tuple[np.ndarray, ...]
    stats: tuple[ClusterStats, ...]
    maxst_edges: tuple[tuple[int, int, int], ...]
    extra_edges: tuple[tuple[int, int, int], ...]
    lost_edge_counts: dict[ClusterPair, int]
    overlap_edges: dict[ClusterPair, np.ndarray]
    completeness_ratio: float
    max_overlap: int


def lost_edges_by_pair(
    graph: ImageGraph, labels: np.ndarray
) -> dict[ClusterPair, tuple[np.ndarray, np.ndarray]]:
    """Collect the lost image edges of every cluster pair (paper section 3.1.2, Alg. 1, line 3).

    Args:
        graph: the image graph.
        labels: core index of every node (``-1``: in no core; its edges are ignored).

    Returns:
        ``{(k1, k2): (ends, weights)}`` for ``k1 < k2`` with at least one lost edge; ``ends`` is
        an int64 ``(m, 2)`` array (column 0 in core ``k1``, column 1 in core ``k2``) sorted by
        descending weight, ties by the ends' ids; ``weights`` the matching float64 weights.
    """
    i, j, w = edge_arrays(graph)
    li, lj = labels[i], labels[j]
    mask = (li != lj) & (li >= 0) & (lj >= 0)
    i, j, w, li, lj = i[mask], j[mask], w[mask], li[mask], lj[mask]
    swap = li > lj
    u = np.where(swap, j, i)  # end in the lower-indexed cluster
    v = np.where(swap, i, j)
    k1 = np.minimum(li, lj)
    k2 = np.maximum(li, lj)
    order = np.lexsort((v, u, -w, k2, k1))
    u, v, w, k1, k2 = u[order], v[order], w[order], k1[order], k2[order]
    out: dict[ClusterPair, tuple[np.ndarray, np.ndarray]] = {}
    if u.size == 0:
        return out
    starts = np.flatnonzero(np.r_[True, (k1[1:] != k1[:-1]) | (k2[1:] != k2[:-1])])
    ends = np.r_[starts[1:], u.size]
    for s, e in zip(starts.tolist(), ends.tolist()):
        out[(int(k1[s]), int(k2[s]))] = (np.column_stack([u[s:e], v[s:e]]), w[s:e].copy())
    return out


def expand_clusters(
    graph: ImageGraph,
    cores: list[np.ndarray],
    completeness_ratio: float = 0.5,
    max_overlap: int = 50,
    seed: int = 0,
) -> ExpansionResult:
    """Expand NCut cores into overlapping clusters (paper section 3.1.2, Alg. 1, lines 3-12).

    Args:
        graph: the image graph the cores were cut from.
        cores: disjoint non-empty arrays of node ids (e.g. from ``partition_graph``); nodes
            in no core are allowed and ignored.
        completeness_ratio: ``C``; a cluster is complete when ``eta(i) >= C`` where
            ``eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i|`` and ``|C_i|`` is the CURRENT size of
            cluster ``i`` (after the additions so far), recomputed after every addition.
        max_overlap: ``O_max >= 1``, the most lost image edges added along one cluster pair.
        seed: seeds the random choice of non-tree cluster edges (Alg. 1, line 11).

    Returns:
        An :class:`ExpansionResult`. A single cluster is returned unchanged with completeness 0.
    """
    if max_overlap < 1:
        raise ValueError(f"max_overlap must be >= 1, got {max_overlap!r}")
    if not np.isfinite(completeness_ratio) or completeness_ratio < 0:
        raise ValueError(f"completeness_ratio must be finite and >= 0, got {completeness_ratio!r}")
    core_arrays = tuple(np.unique(np.asarray(c, dtype=np.int64)) for c in cores)
    labels = _labels_of(core_arrays, graph.num_nodes)
    num_clusters = len(core_arrays)

    lost = lost_edges_by_pair(graph, labels)
    lost_counts = {pair: int(ends.shape[0]) for pair, (ends, _) in lost.items()}

    # Alg. 1, lines 4-5: cluster graph weighted by lost-edge counts, Kruskal MaxST. Edges are
    # inserted in (k1, k2) order and Kruskal's sort is stable, so ties go to the smaller pair.
    cluster_graph = nx.Graph()
    cluster_graph.add_nodes_from(range(num_clusters))
    for (k1, k2), count in sorted(lost_counts.items()):
        cluster_graph.add_edge(k1, k2, weight=count)
    tree = nx.maximum_spanning_edges(cluster_graph, algorithm="kruskal", data=True)
    maxst = tuple((min(a, b), max(a, b), int(d["weight"])) for a, b, d in tree)

    members = [set(c.tolist()) for c in core_arrays]
    multiplicity = np.zeros(graph.num_nodes, dtype=np.int64)  # clusters containing each node
    for c in core_arrays:
        multiplicity[c] += 1
    overlap_edges: dict[ClusterPair, np.ndarray] = {}

    def add_pair(pair: ClusterPair) -> None:
        """Alg. 1, lines 8 and 12: add the pair's strongest lost edges to both clusters."""
        ends = lost[pair][0][:max_overlap]
        overlap_edges[pair] = ends
        k1, k2 = pair
        for u, v in ends.tolist():
            if v not in members[k1]:
                members[k1].add(v)
                multiplicity[v] += 1
            if u not in members[k2]:
                members[k2].add(u)
                multiplicity[u] += 1

    def completeness(k: int) -> float:
        m = members[k]
        return float((multiplicity[list(m)] - 1).sum()) / len(m)

    # Alg. 1, lines 6-9: every MaxST edge becomes an overlap.
    for k1, k2, _ in maxst:
        add_pair((k1, k2))

    # Alg. 1, lines 10-12: random non-tree cluster edges until the completeness holds.
    rng = np.random.default_rng(seed)
    used = {(k1, k2) for k1, k2, _ in maxst}
    unused_of: list[list[ClusterPair]] = [[] for _ in range(num_clusters)]
    for pair in sorted(lost_counts):
        if pair not in used:
            unused_of[pair[0]].append(pair)
            unused_of[pair[1]].append(pair)
    extra: list[tuple[int, int, int]] = []
    while True:
        needy = [
            (completeness(k), k)
            for k in range(num_clusters)
            if any(p not in used for p in unused_of[k]) and completeness(k) < completeness_ratio
        ]
        if not needy:
            break
        _, k = min(needy)  # the least complete cluster first, ties by index
        candidates = [p for p in unused_of[k] if p not in used]
        pair = candidates[int(rng.integers(len(candidates)))]
        used.add(pair)
        add_pair(pair)
        extra.append((pair[0], pair[1], lost_counts[pair]))

    clusters = tuple(np.array(sorted(m), dtype=np.int64) for m in members)
    stats = tuple(
        ClusterStats(
            core_size=int(core_arrays[k].size),
            size=int(clusters[k].size),
            completeness=completeness(k),
        )
        for k in range(num_clusters)
    )
    below = sum(st.completeness < completeness_ratio for st in stats)
    logger.info(
        "expanded %d clusters: %d MaxST edges, %d extra edges, %d below C=%.2f",
        num_clusters,
        len(maxst),
        len(extra),
        below,
        completeness_ratio,
    )
    return ExpansionResult(
        clusters=clusters,
        cores=core_arrays,
        stats=stats,
        maxst_edges=maxst,
        extra_edges=tuple(extra),
        lost_edge_counts=lost_counts,
        overlap_edges=overlap_edges,
        completeness_ratio=float(completeness_ratio),
        max_overlap=int(max_overlap),
    )


def _labels_of(cores: tuple[np.ndarray, ...], num_nodes: int) -> np.ndarray:
    """Core index of every node (-1 if none); rejects empty, out-of-range or overlapping cores."""
    labels = np.full(num_nodes, -1, dtype=np.int64)
    for k, core in enumerate(cores):
        if core.size == 0:
            raise ValueError(f"core {k} is empty")
        if core[0] < 0 or core[-1] >= num_nodes:
            raise ValueError(f"core {k} has node ids outside 0..{num_nodes - 1}")
        if np.any(labels[core] >= 0):
            raise ValueError(f"core {k} overlaps another core; cores must be disjoint")
        labels[core] = k
    return labels
