"""Image clustering under the size and completeness constraints (paper Sec. 3.1, Alg. 1).

The paper bounds every cluster by ``S_max`` images (the size constraint) and asks every cluster
for ``eta(i) >= C`` (the completeness constraint). ``S_max`` bounds the EXPANDED cluster (shared
images included: what one local SfM holds in memory), so the NCut cores must leave the
expansion room:

1. a connected component of at most ``S_max`` images is one cluster (it needs no cut and no
   merge); larger components are cut (``graph.partition``) into cores of at most
   :func:`core_size_bound` images;
2. the cores are expanded along the maximum spanning tree within ``S_max``
   (``graph.expansion``);
3. a core whose cluster fills up to ``S_max`` below ``C`` (its neighbours became complete before
   they took enough of its images, so its own additions must carry its completeness) is cut
   again into cores of at most :func:`recut_size_bound` images (``(1 - C) S_max``, at least
   half of ``S_max``), and step 2 runs again: a cluster whose core is at most ``(1 - C) S_max``
   reaches ``C`` by its own additions before it is full (if the graph has the lost edges), and
   only cores above that bound are cut again, so this ends after at most one re-cut per core.
   This is the cut-and-expand alternation of Zhu et al. (paper Sec. 2), applied only to the
   cores that fail, so most scenes keep the paper's single cut.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from graph.expansion import ExpansionResult, expand_clusters
from graph.image_graph import ImageGraph, build_image_graph, connected_components
from graph.partition import partition_graph

logger = logging.getLogger(__name__)

__all__ = ["Clustering", "cluster_images", "core_size_bound", "recut_size_bound"]


def core_size_bound(max_cluster_size: int, completeness_ratio: float, min_overlap: int) -> int:
    """Largest NCut core that leaves its cluster room to expand within ``S_max`` (step 1).

    A cluster of ``s`` images with ``a`` added images and ``e`` core images that other clusters
    took has ``eta = (a + e) / s`` (each shared image counts once per other cluster holding it).
    Every added image is another core's export, so over the whole graph imports equal exports;
    with ``a = e`` a cluster at the bound reaches ``C`` with ``a = C * S_max / 2`` added images.
    The merge also needs ``min_overlap`` common images along each MaxST edge; both sides add
    images, so a cluster needs room for its half of one edge's overlap, and the overlap of its
    other tree edges can come from its neighbours taking its core images (which costs it no
    room): ``ceil(min_overlap / 2)``. The core bound leaves room for the larger of the two, but
    keeps at least half the cluster its own core (a cluster mostly made of other clusters'
    images would only repeat their work)::

        S_core = max(ceil(S_max / 2), S_max - max(ceil(C * S_max / 2), ceil(min_overlap / 2)))

    Smaller cores are not better: a core of a few images makes a weak local model whose
    similarity to its neighbours the merge may reject.
    """
    s_max = int(max_cluster_size)
    if s_max < 1:
        raise ValueError(f"max_cluster_size must be >= 1, got {max_cluster_size!r}")
    room = max(math.ceil(completeness_ratio * s_max / 2), math.ceil(int(min_overlap) / 2))
    return max(math.ceil(s_max / 2), s_max - room)


def recut_size_bound(max_cluster_size: int, completeness_ratio: float) -> int:
    """Core size at which a cluster's own additions reach ``C`` within ``S_max`` (step 3).

    With ``a`` added images and no exports, ``eta >= a / s``; a core of ``c <= (1 - C) S_max``
    has room for ``a = S_max - c >= C S_max`` additions, so it reaches ``C`` before it is full
    (if the graph has the lost edges). As in :func:`core_size_bound`, at least half the cluster
    stays its own core, so for ``C > 1/2`` the re-cut no longer guarantees ``C``::

        S_recut = max(ceil(S_max / 2), floor((1 - C) S_max))
    """
    s_max = int(max_cluster_size)
    return max(math.ceil(s_max / 2), math.floor((1.0 - float(completeness_ratio)) * s_max))


@dataclass(frozen=True, eq=False)
class Clustering:
    """Result of :func:`cluster_images`.

    Attributes:
        expansion: the final expansion (its ``cores`` are the final cores).
        core_size_bound: the bound of the first cut (:func:`core_size_bound`).
        recut_size_bound: the bound of the cores cut again (:func:`recut_size_bound`).
        recut_cores: how many cores were cut again (step 3).
        isolated: nodes without any edge: in no core, no cluster.
    """

    expansion: ExpansionResult
    core_size_bound: int
    recut_size_bound: int
    recut_cores: int
    isolated: np.ndarray


def cluster_images(
    graph: ImageGraph,
    max_cluster_size: int,
    completeness_ratio: float = 0.5,
    max_overlap: int = 50,
    min_overlap: int = 6,
    seed: int = 0,
    backup_forest: bool = True,
) -> Clustering:
    """Cut and expand the image graph into clusters of at most ``S_max`` images (Alg. 1).

    Steps 1-3 of the module docstring; the arguments are those of
    :func:`graph.expansion.expand_clusters`. Isolated nodes (no edge) are left out. The same
    graph and arguments give the same clusters.
    """
    s_max = int(max_cluster_size)
    s_core = core_size_bound(s_max, completeness_ratio, min_overlap)
    s_recut = recut_size_bound(s_max, completeness_ratio)
    isolated = np.array(sorted(int(c[0]) for c in connected_components(graph) if c.size == 1), dtype=np.int64)
    is_isolated = np.zeros(graph.num_nodes, dtype=bool)
    is_isolated[isolated] = True
    cores = [
        c
        for c in partition_graph(graph, s_core, seed=seed, max_whole_component=s_max)
        if not (c.size == 1 and is_isolated[c[0]])
    ]

    def expand(cores: list[np.ndarray]) -> ExpansionResult:
        return expand_clusters(
            graph,
            cores,
            completeness_ratio,
            max_overlap,
            seed=seed,
            max_cluster_size=s_max,
            min_overlap=min_overlap,
            backup_forest=backup_forest,
        )

    expansion = expand(cores)
    recut = 0
    while True:
        full = {
            c.cluster
            for c in expansion.incomplete
            if c.reason == "bound" and expansion.cores[c.cluster].size > s_recut
        }
        if not full:
            break
        logger.info(
            "cores %s fill up to S_max=%d below C=%.2f: cut again into cores of <= %d images",
            ", ".join(f"C{k}" for k in sorted(full)),
            s_max,
            completeness_ratio,
            s_recut,
        )
        kept = [c for k, c in enumerate(expansion.cores) if k not in full]
        for k in sorted(full):
            kept.extend(_cut(graph, expansion.cores[k], s_recut, seed))
        recut += len(full)
        cores = sorted(kept, key=lambda c: int(c[0]))
        expansion = expand(cores)
    return Clustering(expansion, s_core, s_recut, recut, isolated)


def _cut(graph: ImageGraph, core: np.ndarray, s_max: int, seed: int) -> list[np.ndarray]:
    """NCut partition of the subgraph induced by ``core`` into parts of at most ``s_max``."""
    edges = sp.triu(graph.subgraph_adjacency(core), k=1, format="coo")
    sub_graph = build_image_graph(core.size, edges.row, edges.col, edges.data)
    return [core[p] for p in partition_graph(sub_graph, s_max, seed=seed)]
