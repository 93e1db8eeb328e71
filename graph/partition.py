"""NCut partition of the image graph into cluster cores (paper section 3.1.1, Alg. 1, lines 1-2).

The paper cuts the image graph once with NCut (Shi & Malik) into ``K = floor(n / S_max)``
clusters (Alg. 1, line 1). That ``K`` makes the average cluster larger than its bound ``S_max``,
so we take ``K = ceil(n / S_max)`` per connected component (a departure from the paper) and
then:

1. K-way spectral clustering of the component (normalized Laplacian embedding, sparse ARPACK
   eigensolver with a seeded start vector, ``cluster_qr`` label assignment: deterministic);
2. every part is split into its connected components (a spectral part need not be connected);
3. every part still larger than ``S_max`` is cut again by a normalized 2-way cut: the Fiedler
   vector of the normalized Laplacian, split at the best normalized-cut value along the sorted
   vector among the splits that keep the recursion's cluster count at ``ceil(size / S_max)``;
4. tiny fragments (smaller than ``min_fragment_size``) are merged into the neighbouring part
   they share most edge weight with, as long as the merged part stays within ``S_max``.

A component of size ``<= S_max`` is one cluster, and so is a component of at most
``max_whole_component`` nodes (the expanded-cluster bound when the cores are cut smaller to leave
the expansion room, ``graph.expansion.core_size_bound``: a component that fits one cluster needs
no cut and no merge). No dense ``n x n`` matrix is ever built.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.linalg import eigh
from scipy.sparse.csgraph import connected_components as _cc_labels
from scipy.sparse.linalg import eigsh

from graph.image_graph import ImageGraph, connected_components, edge_arrays

logger = logging.getLogger(__name__)

__all__ = [
    "cut_weight",
    "fiedler_vector",
    "labels_from_clusters",
    "ncut_bisect",
    "partition_graph",
]

# Below this many nodes the 2-way cut uses a dense eigensolver (cheap and exact).
_DENSE_EIGEN_MAX_NODES = 300


def partition_graph(
    graph: ImageGraph,
    max_cluster_size: int,
    seed: int = 0,
    min_fragment_size: int | None = None,
    max_whole_component: int | None = None,
) -> list[np.ndarray]:
    """Partition the image graph into cores of at most ``max_cluster_size`` images (section 3.1.1).

    Implements Alg. 1, lines 1-2 (GraphPartition by NCut) with ``K = ceil(n / S_max)`` per
    connected component and recursive normalized 2-way cuts of parts above ``S_max``; see the
    module docstring for the four steps and why ``K`` departs from the paper's floor.

    Args:
        graph: the weighted image graph.
        max_cluster_size: ``S_max >= 1``, the upper bound on the size of every core.
        seed: seeds the eigensolvers' start vectors; the same graph and seed give the same
            partition.
        min_fragment_size: parts smaller than this are merged into a neighbour when the bound
            allows; default ``max(1, S_max // 4)``.
        max_whole_component: a connected component of at most this many nodes is one core
            even when larger than ``S_max`` (default: ``S_max``).

    Returns:
        Disjoint sorted int64 arrays of node ids covering ``0..n-1``, ordered by their
        smallest member; each of size ``<= S_max`` unless it is a whole component of at most
        ``max_whole_component`` nodes.
    """
    s_max = int(max_cluster_size)
    if s_max < 1:
        raise ValueError(f"max_cluster_size must be >= 1, got {max_cluster_size!r}")
    min_frag = max(1, s_max // 4) if min_fragment_size is None else int(min_fragment_size)
    whole = s_max if max_whole_component is None else max(s_max, int(max_whole_component))

    clusters: list[np.ndarray] = []
    for comp in connected_components(graph):
        if comp.size <= whole:
            clusters.append(comp)
            continue
        if s_max == 1:
            clusters.extend(comp.reshape(-1, 1))
            continue
        adj = graph.subgraph_adjacency(comp)
        k = math.ceil(comp.size / s_max)
        labels = _spectral_kway(adj, k, seed)
        parts = _split_disconnected(adj, labels)
        final: list[np.ndarray] = []
        for part in parts:
            final.extend(_bisect_recursive(adj, part, s_max, seed))
        final = _merge_fragments(adj, final, s_max, min_frag)
        logger.debug(
            "component of %d nodes: K=%d spectral parts -> %d cores", comp.size, k, len(final)
        )
        clusters.extend(comp[p] for p in final)

    clusters = [np.sort(c).astype(np.int64) for c in clusters]
    clusters.sort(key=lambda c: int(c[0]))
    logger.info(
        "partitioned %d images into %d cores (S_max=%d)", graph.num_nodes, len(clusters), s_max
    )
    return clusters


def cut_weight(graph: ImageGraph, labels: npt.ArrayLike) -> float:
    """Total weight of the image edges whose endpoints carry different labels ("lost edges").

    Args:
        graph: the image graph.
        labels: one integer label per node, shape ``(n,)``.
    """
    lab = np.asarray(labels).ravel()
    if lab.size != graph.num_nodes:
        raise ValueError(f"labels must have one entry per node ({graph.num_nodes}), got {lab.size}")
    i, j, w = edge_arrays(graph)
    return float(w[lab[i] != lab[j]].sum())


def labels_from_clusters(clusters: list[np.ndarray], num_nodes: int) -> np.ndarray:
    """Label array (cluster index per node, -1 if uncovered) of a list of disjoint clusters."""
    labels = np.full(num_nodes, -1, dtype=np.int64)
    for k, members in enumerate(clusters):
        labels[np.asarray(members, dtype=np.int64)] = k
    return labels


def fiedler_vector(adjacency: sp.spmatrix, seed: int = 0) -> np.ndarray:
    """Relaxed NCut indicator of a connected graph (Shi & Malik; paper section 3.1.1).

    Returns ``y = D^{-1/2} u2`` where ``u2`` is the eigenvector of the second smallest
    eigenvalue of the normalized Laplacian ``I - D^{-1/2} A D^{-1/2}``; its sign is fixed so
    that the entry of largest magnitude is positive. Sparse shift-invert ARPACK with a seeded
    start vector above ``_DENSE_EIGEN_MAX_NODES`` nodes, dense ``eigh`` below.
    """
    adj = sp.csr_matrix(adjacency, dtype=np.float64)
    n = adj.shape[0]
    if n < 2:
        return np.zeros(n)
    deg = np.asarray(adj.sum(axis=1)).ravel()
    d_isqrt = 1.0 / np.sqrt(np.maximum(deg, np.finfo(float).tiny))
    lap = sp.identity(n, format="csr") - sp.diags(d_isqrt) @ adj @ sp.diags(d_isqrt)
    if n <= _DENSE_EIGEN_MAX_NODES:
        _, vecs = eigh(lap.toarray())
        u2 = vecs[:, 1]
    else:
        v0 = np.random.default_rng(seed).uniform(-1.0, 1.0, n)
        _, vecs = eigsh(lap.tocsc(), k=2, sigma=-1e-5, which="LM", v0=v0, tol=1e-10)
        u2 = vecs[:, 1]
    y = u2 * d_isqrt
    if y[np.argmax(np.abs(y))] < 0:
        y = -y
    return y


def _spectral_kway(adj: sp.csr_matrix, k: int, seed: int) -> np.ndarray:
    """K-way normalized spectral clustering of a connected graph (section 3.1.1, Alg. 1, line 2)."""
    if k <= 1:
        return np.zeros(adj.shape[0], dtype=np.int64)
    # imported here: scikit-learn is slow to import, and a scene that fits in one cluster
    # never gets this far
    from sklearn.cluster import SpectralClustering

    model = SpectralClustering(
        n_clusters=k,
        affinity="precomputed",
        assign_labels="cluster_qr",
        eigen_solver="arpack",
        random_state=seed,
    )
    return model.fit_predict(adj).astype(np.int64)


def _split_disconnected(adj: sp.csr_matrix, labels: np.ndarray) -> list[np.ndarray]:
    """Split every labelled part into its connected components (local index arrays)."""
    parts: list[np.ndarray] = []
    for lab in np.unique(labels):
        members = np.flatnonzero(labels == lab)
        parts.extend(_components_of(adj, members))
    return parts


def _components_of(adj: sp.csr_matrix, members: np.ndarray) -> list[np.ndarray]:
    """Connected components of the subgraph induced by ``members`` (sorted local indices)."""
    if members.size <= 1:
        return [members]
    ncomp, lab = _cc_labels(adj[members][:, members], directed=False)
    if ncomp == 1:
        return [members]
    return [members[lab == c] for c in range(ncomp)]


def _bisect_recursive(
    adj: sp.csr_matrix, part: np.ndarray, s_max: int, seed: int
) -> list[np.ndarray]:
    """Normalized 2-way cuts of ``part`` until every piece has at most ``s_max`` nodes."""
    out: list[np.ndarray] = []
    stack = [part]
    while stack:
        members = stack.pop()
        if members.size <= s_max:
            out.append(members)
            continue
        left, right = ncut_bisect(adj[members][:, members], s_max, seed)
        for side in (members[left], members[right]):
            stack.extend(_components_of(adj, side))
    return out


def ncut_bisect(sub: sp.spmatrix, s_max: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Best normalized 2-way cut of a connected graph along its sorted Fiedler vector.

    The Shi & Malik sweep used for parts still above ``S_max`` (step 3 of the module docstring;
    Alg. 1, line 2, with the departure the module docstring explains).

    Splits ``n`` nodes into ``i`` and ``n - i`` with both sides non-empty and
    ``ceil(i / S) + ceil((n - i) / S) == ceil(n / S)``, so recursion keeps ``K`` minimal;
    among those, the split with the smallest ``cut/vol(A) + cut/vol(B)`` wins (ties: the
    most balanced, then the smaller ``i``). Returns local index arrays (left, right).
    """
    sub = sp.csr_matrix(sub, dtype=np.float64)
    n = sub.shape[0]
    if n < 2:
        raise ValueError("a 2-way cut needs at least 2 nodes")
    y = fiedler_vector(sub, seed)
    order = np.lexsort((np.arange(n), y))  # ascending y, ties by index: deterministic
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)

    deg = np.asarray(sub.sum(axis=1)).ravel()
    coo = sp.triu(sub, k=1, format="coo")
    a, b = pos[coo.row], pos[coo.col]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    # Edge (lo, hi) is cut by the prefix split of size i iff lo < i <= hi.
    delta = np.zeros(n + 1)
    np.add.at(delta, lo + 1, coo.data)
    np.add.at(delta, hi + 1, -coo.data)
    cut = np.cumsum(delta)[1:n]  # cut[i - 1] for i = 1..n-1
    vol_left = np.cumsum(deg[order])[: n - 1]
    vol_total = deg.sum()
    vol_right = vol_total - vol_left
    tiny = np.finfo(float).tiny
    ncut = cut / np.maximum(vol_left, tiny) + cut / np.maximum(vol_right, tiny)

    sizes = np.arange(1, n)
    k_total = math.ceil(n / s_max)
    feasible = (np.ceil(sizes / s_max) + np.ceil((n - sizes) / s_max)) == k_total
    if not feasible.any():  # only when n <= s_max: any split is as good
        feasible[:] = True
    imbalance = np.abs(2 * sizes - n)
    cand = np.flatnonzero(feasible)
    best = cand[np.lexsort((sizes[cand], imbalance[cand], ncut[cand]))[0]]
    i = int(sizes[best])
    return np.sort(order[:i]), np.sort(order[i:])


def _merge_fragments(
    adj: sp.csr_matrix, parts: list[np.ndarray], s_max: int, min_frag: int
) -> list[np.ndarray]:
    """Merge parts smaller than ``min_frag`` into the neighbour sharing the most weight.

    Smallest fragment first (ties: smallest member). A fragment joins the adjacent part with
    the largest shared edge weight among those whose merged size stays ``<= s_max`` (ties:
    smaller merged size, then smallest member); a fragment with no such neighbour is kept.
    """
    parts = [np.sort(p) for p in parts if p.size]
    if len(parts) <= 1 or min_frag <= 1:
        return parts
    n = adj.shape[0]
    label = np.empty(n, dtype=np.int64)
    for k, p in enumerate(parts):
        label[p] = k
    coo = sp.triu(adj, k=1, format="coo")
    la, lb = label[coo.row], label[coo.col]
    mask = la != lb
    nbr: dict[int, dict[int, float]] = {k: {} for k in range(len(parts))}
    for a, b, w in zip(la[mask].tolist(), lb[mask].tolist(), coo.data[mask].tolist()):
        nbr[a][b] = nbr[a].get(b, 0.0) + w
        nbr[b][a] = nbr[b].get(a, 0.0) + w

    members: dict[int, np.ndarray] = dict(enumerate(parts))
    while True:
        frags = [
            k
            for k, m in members.items()
            if m.size < min_frag and any(members[q].size + m.size <= s_max for q in nbr[k])
        ]
        if not frags:
            break
        k = min(frags, key=lambda q: (members[q].size, int(members[q][0])))
        size_k = members[k].size
        target = min(
            (q for q in nbr[k] if members[q].size + size_k <= s_max),
            key=lambda q: (-nbr[k][q], members[q].size, int(members[q][0])),
        )
        members[target] = np.sort(np.concatenate([members[target], members.pop(k)]))
        for q, w in nbr.pop(k).items():
            del nbr[q][k]
            if q != target:
                nbr[target][q] = nbr[target].get(q, 0.0) + w
                nbr[q][target] = nbr[q].get(target, 0.0) + w
    return list(members.values())
