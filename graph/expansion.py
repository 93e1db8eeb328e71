"""Subgraph expansion guided by a maximum spanning tree (paper section 3.1.2, Alg. 1, lines 3-12).

After the NCut partition, the image edges between two cluster cores are "lost". The expansion
gives neighbouring clusters common images so that their local reconstructions can be aligned,
under the paper's two constraints (Sec. 3.1): the size constraint (no cluster above ``S_max``
images) and the completeness constraint ``eta(i) >= C`` with
``eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i|``.

* The cluster graph has one node per cluster and one edge per cluster pair with lost image
  edges, weighted by the NUMBER of lost image edges (Alg. 1, lines 3-4); its Kruskal maximum
  spanning tree (Alg. 1, line 5) says where the merge will need overlap.
* Walking a lost image edge ``(u, v)`` of the pair ``(k1, k2)`` (``u`` in core ``k1``, ``v`` in
  core ``k2``) gives cluster ``k1`` the image ``v`` and cluster ``k2`` the image ``u``, each only
  if that side wants it and is below ``S_max``. A pair's lost edges are walked strongest first,
  and at most ``O_max`` images are added along one pair (Alg. 1: "number of overlapped images
  between two clusters").
* Step 1, merge overlap (Alg. 1, lines 6-9): along every MaxST edge, in Kruskal order, both
  sides take images until the pair shares ``min_overlap``, whatever their completeness: every
  MaxST edge becomes an overlap the Sim3 merge can use. A first round lets each side add at most
  ``ceil(min_overlap / 2)`` images per MaxST edge, and at most its room (``S_max`` minus its
  size) divided by its number of MaxST edges, so a cluster with several tree edges keeps room
  for each; a second round lets either side add what is still missing. Then the same, in the
  room left, along a backup forest: the maximum spanning forest of the cluster edges not in the
  MaxST (Fig. 2(c): "the dotted line could be added to enhance connectivity of clusters"). The
  merge drops an alignment whose residual (MSD) is too large, and a model that has no other
  aligned neighbour then stays a separate model; the backup forest gives most clusters a second
  route to the others.
* Step 2, completeness along the MaxST (Sec. 3.1.2: "We gather the image edges from the MaxST
  and sort them by descending order. We then add the lost image edges into clusters where
  completeness constraint is not satisfied, and only the top-k edges are added"): the lost
  edges of all MaxST edges are walked (again) in one descending order of weight; a side takes an
  image only while its completeness is below ``C``.
* Step 3 (Alg. 1, lines 10-12): while a cluster is below ``C``, below ``S_max`` and has an
  unused non-tree cluster edge, the least complete such cluster picks one at random (seeded
  numpy Generator), and its lost edges are walked the same way.

A cluster that ends below ``C``, and a MaxST edge whose clusters share fewer than
``min_overlap`` images, are reported with the reason: the size bound (the clusters that could
take images are full), ``O_max``, or the image graph (every lost edge was walked).
``graph.clustering`` chooses cores that leave the expansion room within ``S_max``.
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass
from typing import Literal

import networkx as nx
import numpy as np

from graph.image_graph import ImageGraph, edge_arrays

logger = logging.getLogger(__name__)

__all__ = [
    "ClusterStats",
    "ExpansionResult",
    "IncompleteCluster",
    "ThinOverlap",
    "expand_clusters",
    "lost_edges_by_pair",
]

ClusterPair = tuple[int, int]
# Why a constraint is not met: "bound": the clusters that could take images are full at S_max;
# "max_overlap": a pair already has O_max added images; "lost_edges": every lost edge was walked.
Reason = Literal["bound", "max_overlap", "lost_edges"]

# Steps of the expansion, as recorded in ExpansionResult.additions.
STEP_MERGE_OVERLAP, STEP_TREE_COMPLETENESS, STEP_RANDOM_EDGES = 1, 2, 3


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


@dataclass(frozen=True)
class IncompleteCluster:
    """A cluster that has lost edges to other clusters but ends with ``eta(i) < C``.

    ``reason``: "bound" (it is full at ``S_max``); else every cluster pair it is in was walked
    to its end: "max_overlap" (at least one of them stopped at ``O_max`` added images) or
    "lost_edges" (all of them ran out of lost edges).
    """

    cluster: int
    completeness: float
    size: int
    reason: Reason


@dataclass(frozen=True)
class ThinOverlap:
    """A MaxST edge whose clusters share fewer than ``min_overlap`` images.

    ``reason``: "max_overlap" (``O_max`` images were added along it), "bound" (a cluster full at
    ``S_max`` could not take the far end of a lost edge of the pair), "lost_edges" (every lost
    edge was walked and each side holds all its far ends: the image graph has no more).
    """

    k1: int
    k2: int
    common: int
    reason: Reason


@dataclass(frozen=True, eq=False)
class ExpansionResult:
    """Result of :func:`expand_clusters` (Alg. 1's output ``G_inter``).

    Attributes:
        clusters: members of each cluster after expansion (sorted int64 arrays); index ``k``
            is the index of the core in the input list.
        cores: the input cores (sorted int64 arrays).
        stats: one :class:`ClusterStats` per cluster.
        maxst_edges: MaxST edges ``(k1, k2, n_lost)`` with ``k1 < k2``, in Kruskal order.
        backup_edges: the backup forest's edges, the same way (empty without ``backup_forest``).
        extra_edges: non-tree cluster edges ``(k1, k2, n_lost)`` used for completeness, in the
            order they were picked.
        lost_edge_counts: number of lost image edges of every cluster pair ``(k1, k2)``,
            ``k1 < k2`` (pairs with none are absent): the cluster-graph weights.
        overlap_edges: for every used cluster pair ``(k1, k2)``, the lost image edges walked
            along it (by any step): the strongest ``m`` of the pair, an int64 array of shape ``(m, 2)``,
            strongest first (the order of :func:`lost_edges_by_pair`); column 0 is the end in
            core ``k1``, column 1 the end in core ``k2``.
        common_images: ``|C_k1 ∩ C_k2|`` after expansion for every MaxST, backup and extra edge.
        additions: every image added, in order: int64 array of shape ``(m, 6)``, rows
            ``(cluster, image, k1, k2, step, rank)``: ``cluster`` gained ``image`` along the
            pair ``(k1, k2)`` by walking the pair's lost edge number ``rank`` (its index in
            ``overlap_edges``), in step 1 (merge overlap, MaxST or backup forest), 2
            (completeness along the MaxST) or 3 (random non-tree edges).
        incomplete: the clusters left below ``C``, with the reason.
        thin_overlaps: the MaxST edges left below ``min_overlap`` common images, with the reason.
        completeness_ratio: the ``C`` that was asked for.
        max_overlap: the ``O_max`` that was used.
        max_cluster_size: the ``S_max`` bound of the expanded clusters (``None``: no bound).
        min_overlap: the common images asked for along every MaxST edge.
    """

    clusters: tuple[np.ndarray, ...]
    cores: tuple[np.ndarray, ...]
    stats: tuple[ClusterStats, ...]
    maxst_edges: tuple[tuple[int, int, int], ...]
    backup_edges: tuple[tuple[int, int, int], ...]
    extra_edges: tuple[tuple[int, int, int], ...]
    lost_edge_counts: dict[ClusterPair, int]
    overlap_edges: dict[ClusterPair, np.ndarray]
    common_images: dict[ClusterPair, int]
    additions: np.ndarray
    incomplete: tuple[IncompleteCluster, ...]
    thin_overlaps: tuple[ThinOverlap, ...]
    completeness_ratio: float
    max_overlap: int
    max_cluster_size: int | None
    min_overlap: int


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
    *,
    max_cluster_size: int | None = None,
    min_overlap: int = 6,
    backup_forest: bool = True,
) -> ExpansionResult:
    """Expand NCut cores into overlapping clusters within a size bound (Alg. 1, lines 3-12).

    The three steps of the module docstring: the merge overlap along the MaxST (Alg. 1, lines
    6-10) and the backup forest (Fig. 2(c)), completeness along the MaxST with its lost edges in one descending order (Sec.
    3.1.2), then random non-tree cluster edges while a cluster is below ``C`` (lines 10-12).

    Args:
        graph: the image graph the cores were cut from.
        cores: disjoint non-empty arrays of node ids (e.g. from ``partition_graph``); nodes
            in no core are allowed and ignored.
        completeness_ratio: ``C``; a cluster is complete when ``eta(i) >= C`` where
            ``eta(i) = sum_{j != i} |C_i ∩ C_j| / |C_i|`` and ``|C_i|`` is the CURRENT size of
            cluster ``i``, recomputed after every addition. A complete cluster takes no image in
            steps 2 and 3.
        max_overlap: ``O_max >= 1``, the most images added along one cluster pair (both sides
            together).
        seed: seeds the random choice of non-tree cluster edges (Alg. 1, line 11).
        max_cluster_size: ``S_max``; no cluster grows beyond it (a core already larger keeps its
            size and takes nothing). ``None``: no bound.
        min_overlap: common images every MaxST edge is given in step 1 (bound permitting).
        backup_forest: also give ``min_overlap`` to the backup forest's edges, in the room the
            MaxST leaves (step 1).

    Returns:
        An :class:`ExpansionResult`. A single cluster is returned unchanged with completeness 0.
    """
    if max_overlap < 1:
        raise ValueError(f"max_overlap must be >= 1, got {max_overlap!r}")
    if not np.isfinite(completeness_ratio) or completeness_ratio < 0:
        raise ValueError(f"completeness_ratio must be finite and >= 0, got {completeness_ratio!r}")
    if max_cluster_size is not None and max_cluster_size < 1:
        raise ValueError(f"max_cluster_size must be >= 1 or None, got {max_cluster_size!r}")
    if min_overlap < 0:
        raise ValueError(f"min_overlap must be >= 0, got {min_overlap!r}")
    core_arrays = tuple(np.unique(np.asarray(c, dtype=np.int64)) for c in cores)
    labels = _labels_of(core_arrays, graph.num_nodes)
    num_clusters = len(core_arrays)
    bound = math.inf if max_cluster_size is None else int(max_cluster_size)
    c_ratio = float(completeness_ratio)

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
    # Fig. 2(c)'s dotted lines "added to enhance connectivity": a second maximum spanning forest,
    # of the cluster edges not in the MaxST, so that a cluster whose MaxST alignment the merge
    # rejects has another route to the others.
    cluster_graph.remove_edges_from([(a, b) for a, b, _ in maxst])
    second = nx.maximum_spanning_edges(cluster_graph, algorithm="kruskal", data=True) if backup_forest else ()
    backup = tuple((min(a, b), max(a, b), int(d["weight"])) for a, b, d in second)

    members = [set(c.tolist()) for c in core_arrays]
    holders: dict[int, list[int]] = {}  # clusters holding each node, for nodes in some core
    for k, c in enumerate(core_arrays):
        for x in c.tolist():
            holders[x] = [k]
    shared = np.zeros(num_clusters)  # eta numerator: sum over members of (holders - 1)
    walked: dict[ClusterPair, int] = {}  # lost edges walked per pair (a prefix, strongest first)
    added: dict[ClusterPair, int] = {}  # images added along each pair, both sides
    additions: list[tuple[int, int, int, int, int, int]] = []

    def completeness(k: int) -> float:
        return float(shared[k]) / len(members[k])

    def has_room(k: int) -> bool:
        return len(members[k]) < bound

    def add(k: int, x: int, pair: ClusterPair, step: int, rank: int) -> None:
        for j in holders[x]:
            shared[j] += 1
        holders[x].append(k)
        shared[k] += len(holders[x]) - 1
        members[k].add(x)
        added[pair] = added.get(pair, 0) + 1
        additions.append((k, x, pair[0], pair[1], step, rank))

    def offer(pair: ClusterPair, rank: int, step: int, takes) -> None:
        """Walk the pair's lost edge ``rank``: each side gets its far end if ``takes(side)``."""
        u, v = (int(x) for x in lost[pair][0][rank])
        for k, x in ((pair[0], v), (pair[1], u)):
            if added.get(pair, 0) < max_overlap and x not in members[k] and has_room(k) and takes(k):
                add(k, x, pair, step, rank)
        walked[pair] = max(walked.get(pair, 0), rank + 1)

    # Step 1 (Alg. 1, lines 6-9): every MaxST edge becomes an overlap the merge can use. First
    # each side adds at most its half of min_overlap along every MaxST edge, and no more than its
    # room divided by its number of tree edges, so that a cluster with several tree edges keeps
    # room for each; then either side adds what is still missing.
    own: dict[tuple[ClusterPair, int], int] = {}

    def merge_overlap(pair: ClusterPair, share: dict[int, float]) -> None:
        def takes(k: int) -> bool:
            ok = len(members[pair[0]] & members[pair[1]]) < min_overlap and own.get((pair, k), 0) < share[k]
            if ok:
                own[(pair, k)] = own.get((pair, k), 0) + 1  # offer() adds it right after
            return ok

        for rank in range(lost_counts[pair]):
            if len(members[pair[0]] & members[pair[1]]) >= min_overlap or added.get(pair, 0) >= max_overlap:
                break
            if not any(has_room(k) and own.get((pair, k), 0) < share[k] for k in pair):
                break
            offer(pair, rank, STEP_MERGE_OVERLAP, takes)

    for forest in (maxst, backup):  # the MaxST first; the backup forest in the room left
        degree = np.zeros(num_clusters, dtype=np.int64)
        for k1, k2, _ in forest:
            degree[[k1, k2]] += 1
        half = [
            math.ceil(min_overlap / 2) if max_cluster_size is None
            else max(0, min(math.ceil(min_overlap / 2), (int(max_cluster_size) - len(members[k])) // max(int(d), 1)))
            for k, d in enumerate(degree)
        ]
        for k1, k2, _ in forest:  # round 1: each side's half, its room shared among its edges
            merge_overlap((k1, k2), {k1: half[k1], k2: half[k2]})
        for k1, k2, _ in forest:  # round 2: what is still missing, from either side
            merge_overlap((k1, k2), {k1: math.inf, k2: math.inf})

    def below_c(k: int) -> bool:
        return completeness(k) < c_ratio

    # Step 2: the MaxST's lost edges in one descending order of weight (ties: Kruskal order), each
    # from its strongest again, to the sides still below C. A side that is complete or full stays
    # so (an image added to a cluster below C <= 1 cannot bring it down), so a pair neither side of
    # which wants an image is done.
    queue = [(-lost[(k1, k2)][1][0], order, 0, (k1, k2)) for order, (k1, k2, _) in enumerate(maxst)]
    heapq.heapify(queue)
    while queue:
        _, order, rank, pair = heapq.heappop(queue)
        if added.get(pair, 0) >= max_overlap or not any(has_room(k) and below_c(k) for k in pair):
            continue
        offer(pair, rank, STEP_TREE_COMPLETENESS, below_c)
        if rank + 1 < lost_counts[pair]:
            heapq.heappush(queue, (-lost[pair][1][rank + 1], order, rank + 1, pair))

    # Step 3 (Alg. 1, lines 10-12): random non-tree cluster edges while the completeness fails.
    rng = np.random.default_rng(seed)
    used = {(k1, k2) for k1, k2, _ in maxst}  # backup edges may be walked on for completeness
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
            if has_room(k)
            and completeness(k) < c_ratio
            and any(p not in used for p in unused_of[k])
        ]
        if not needy:
            break
        _, k = min(needy)  # the least complete cluster first, ties by index
        candidates = [p for p in unused_of[k] if p not in used]
        pair = candidates[int(rng.integers(len(candidates)))]
        used.add(pair)
        for rank in range(lost_counts[pair]):
            if added.get(pair, 0) >= max_overlap or not any(has_room(j) and below_c(j) for j in pair):
                break
            offer(pair, rank, STEP_RANDOM_EDGES, below_c)
        extra.append((pair[0], pair[1], lost_counts[pair]))

    def is_open(pair: ClusterPair) -> bool:
        return walked.get(pair, 0) < lost_counts[pair] and added.get(pair, 0) < max_overlap

    def why_closed(pairs: list[ClusterPair]) -> Reason:
        capped = any(added.get(p, 0) >= max_overlap for p in pairs)
        return "max_overlap" if capped else "lost_edges"

    pairs_of: list[list[ClusterPair]] = [[] for _ in range(num_clusters)]
    for pair in lost_counts:
        pairs_of[pair[0]].append(pair)
        pairs_of[pair[1]].append(pair)
    incomplete = tuple(
        IncompleteCluster(
            k,
            completeness(k),
            len(members[k]),
            "bound" if not has_room(k) else why_closed(pairs_of[k]),
        )
        for k in range(num_clusters)
        if pairs_of[k] and completeness(k) < c_ratio
    )
    used |= {(k1, k2) for k1, k2, _ in backup}
    common_images = {p: len(members[p[0]] & members[p[1]]) for p in sorted(used)}

    def why_thin(pair: ClusterPair) -> Reason:
        if added.get(pair, 0) >= max_overlap:
            return "max_overlap"
        ends = lost[pair][0][: walked.get(pair, 0)]
        k1_missed = not set(ends[:, 1].tolist()) <= members[pair[0]]
        k2_missed = not set(ends[:, 0].tolist()) <= members[pair[1]]
        return "bound" if is_open(pair) or k1_missed or k2_missed else "lost_edges"

    thin = tuple(
        ThinOverlap(k1, k2, common_images[(k1, k2)], why_thin((k1, k2)))
        for k1, k2, _ in maxst
        if common_images[(k1, k2)] < min_overlap
    )

    clusters = tuple(np.array(sorted(m), dtype=np.int64) for m in members)
    stats = tuple(
        ClusterStats(
            core_size=int(core_arrays[k].size),
            size=int(clusters[k].size),
            completeness=completeness(k),
        )
        for k in range(num_clusters)
    )
    overlap_edges = {p: lost[p][0][: walked.get(p, 0)].copy() for p in sorted(used)}
    logger.info(
        "expanded %d clusters (S_max=%s): %d MaxST edges, %d backup edges, %d extra edges, "
        "%d below C=%.2f, %d MaxST edges below %d common images",
        num_clusters,
        max_cluster_size,
        len(maxst),
        len(backup),
        len(extra),
        len(incomplete),
        c_ratio,
        len(thin),
        min_overlap,
    )
    return ExpansionResult(
        clusters=clusters,
        cores=core_arrays,
        stats=stats,
        maxst_edges=maxst,
        backup_edges=backup,
        extra_edges=tuple(extra),
        lost_edge_counts=lost_counts,
        overlap_edges=overlap_edges,
        common_images=common_images,
        additions=np.array(additions, dtype=np.int64).reshape(-1, 6),
        incomplete=incomplete,
        thin_overlaps=thin,
        completeness_ratio=c_ratio,
        max_overlap=int(max_overlap),
        max_cluster_size=None if max_cluster_size is None else int(max_cluster_size),
        min_overlap=int(min_overlap),
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
