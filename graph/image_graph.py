"""The weighted image graph of GraphSfM (paper section 3.1.1).

Each image is a node (integer id ``0..n-1``); each verified image pair is an undirected edge
("image edge") whose weight is the number of inlier matches after geometric verification.
The graph is stored as a symmetric ``scipy.sparse`` CSR adjacency matrix of float64 weights,
so that the spectral partition (``graph.partition``) and the subgraph expansion
(``graph.expansion``) work on 10,000+ images without dense ``n x n`` matrices.

This module is pure combinatorics: it knows nothing about images, features or files.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import networkx as nx
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc_labels

logger = logging.getLogger(__name__)

__all__ = [
    "ImageGraph",
    "build_image_graph",
    "connected_components",
    "edge_arrays",
]


@dataclass(frozen=True, eq=False)
class ImageGraph:
    """Undirected weighted image graph (paper section 3.1.1, "image edges").

    Attributes:
        num_nodes: number of images ``n``; node ids are ``0..n-1`` (isolated nodes allowed).
        adjacency: symmetric ``n x n`` CSR matrix, float64 edge weights, empty diagonal,
            canonical format (sorted indices, no duplicates, no explicit zeros).

    Build it with :func:`build_image_graph`, which validates and canonicalises the input.
    Equality is identity (the adjacency matrix is not hashable).
    """

    num_nodes: int
    adjacency: sp.csr_matrix

    @property
    def num_edges(self) -> int:
        """Number of undirected edges."""
        return int(self.adjacency.nnz // 2)

    def degrees(self) -> np.ndarray:
        """Weighted degree ``d_i = sum_j w_ij`` of every node, float64 array of shape (n,)."""
        return np.asarray(self.adjacency.sum(axis=1)).ravel()

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Edge arrays ``(i, j, w)`` with ``i < j``, sorted by ``(i, j)``; see :func:`edge_arrays`."""
        return edge_arrays(self)

    def subgraph_adjacency(self, nodes: npt.ArrayLike) -> sp.csr_matrix:
        """Adjacency of the subgraph induced by ``nodes`` (local index = position in ``nodes``)."""
        idx = np.asarray(nodes, dtype=np.int64)
        return self.adjacency[idx][:, idx].tocsr()

    def to_networkx(self) -> nx.Graph:
        """The graph as a ``networkx.Graph`` with every node and a ``weight`` edge attribute."""
        g = nx.Graph()
        g.add_nodes_from(range(self.num_nodes))
        i, j, w = self.edges()
        g.add_weighted_edges_from(zip(i.tolist(), j.tolist(), w.tolist()))
        return g


def build_image_graph(
    num_nodes: int,
    edges_i: npt.ArrayLike,
    edges_j: npt.ArrayLike,
    weights: npt.ArrayLike,
) -> ImageGraph:
    """Build the weighted image graph from verified pairs (paper section 3.1.1).

    Args:
        num_nodes: number of images ``n``; every id must lie in ``0..n-1``.
        edges_i, edges_j: endpoint ids of each pair (any order, same length).
        weights: edge weights (number of inlier matches); finite and ``>= 0``.

    Returns:
        The :class:`ImageGraph`. Rules: the graph is undirected (``(i, j)`` and ``(j, i)`` are
        the same edge); duplicate edges keep their maximum weight; self loops are dropped;
        edges of weight 0 are dropped (a sparse matrix cannot hold them, and an edge with no
        inlier carries no geometry).

    Raises:
        ValueError: on mismatched lengths, ids out of range, or negative / non-finite weights.
    """
    if int(num_nodes) != num_nodes or num_nodes < 0:
        raise ValueError(f"num_nodes must be a non-negative integer, got {num_nodes!r}")
    n = int(num_nodes)
    ei = np.asarray(edges_i).ravel()
    ej = np.asarray(edges_j).ravel()
    w = np.asarray(weights, dtype=np.float64).ravel()
    if not (ei.shape == ej.shape == w.shape):
        raise ValueError(
            f"edges_i, edges_j and weights must have the same length, "
            f"got {ei.size}, {ej.size}, {w.size}"
        )
    integral = all(
        np.issubdtype(e.dtype, np.integer) or np.all(np.mod(e, 1) == 0) for e in (ei, ej)
    )
    if not integral:
        raise ValueError("edge endpoints must be integer node ids")
    ei = ei.astype(np.int64)
    ej = ej.astype(np.int64)
    if ei.size and (min(ei.min(), ej.min()) < 0 or max(ei.max(), ej.max()) >= n):
        raise ValueError(f"edge endpoints must lie in 0..{n - 1}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("edge weights must be finite and non-negative")

    keep = (ei != ej) & (w > 0)
    dropped_loops = int(np.count_nonzero(ei == ej))
    if dropped_loops:
        logger.debug("dropped %d self loops", dropped_loops)
    lo = np.minimum(ei, ej)[keep]
    hi = np.maximum(ei, ej)[keep]
    w = w[keep]

    # Duplicates: sort by (lo, hi, w) and keep the last (= maximum weight) of each pair.
    order = np.lexsort((w, hi, lo))
    lo, hi, w = lo[order], hi[order], w[order]
    if lo.size:
        last = np.ones(lo.size, dtype=bool)
        last[:-1] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
        lo, hi, w = lo[last], hi[last], w[last]

    rows = np.concatenate([lo, hi])
    cols = np.concatenate([hi, lo])
    vals = np.concatenate([w, w])
    adjacency = sp.csr_matrix((vals, (rows, cols)), shape=(n, n), dtype=np.float64)
    adjacency.sum_duplicates()
    adjacency.sort_indices()
    return ImageGraph(num_nodes=n, adjacency=adjacency)


def edge_arrays(graph: ImageGraph) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges of ``graph`` as arrays ``(i, j, w)``.

    ``i < j`` (int64), ``w`` float64; sorted by ``(i, j)``. Each edge appears once.
    """
    coo = sp.triu(graph.adjacency, k=1, format="coo")
    i = coo.row.astype(np.int64)
    j = coo.col.astype(np.int64)
    w = coo.data.astype(np.float64)
    order = np.lexsort((j, i))
    return i[order], j[order], w[order]


def connected_components(graph: ImageGraph) -> list[np.ndarray]:
    """Connected components of the image graph.

    Returns:
        One sorted int64 array of node ids per component, largest component first; ties by
        the smallest node id. Isolated nodes are components of size 1.
    """
    if graph.num_nodes == 0:
        return []
    _, labels = _cc_labels(graph.adjacency, directed=False)
    order = np.argsort(labels, kind="stable")  # node ids ascending inside each label
    counts = np.bincount(labels)
    comps = np.split(order.astype(np.int64), np.cumsum(counts)[:-1])
    comps.sort(key=lambda c: (-c.size, int(c[0])))
    return comps
