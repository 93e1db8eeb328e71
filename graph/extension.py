"""Clusters of images added to a finished reconstruction (paper section 3.1, Alg. 1, with one
cluster given).

The images already reconstructed form one cluster that is never cut nor re-run: the anchor.
The new images are clustered as Alg. 1 clusters any image graph, and every new cluster also
gets overlap with the anchor, so its local model can be aligned to the anchor directly:

1. the new images' own graph is cut into cores of at most ``S_max`` images by normalized cuts
   (Alg. 1, lines 1-2; ``graph.partition.partition_graph``);
2. the cores are expanded among themselves along their cluster graph's MaxST and until the
   completeness holds (Alg. 1, lines 3-12; ``graph.expansion.expand_clusters``);
3. between every core and the anchor, the strongest lost image edges (at most ``O_max``) give
   the core their anchor ends (Alg. 1, lines 6-9, for the edge between the core and the anchor
   cluster, with the anchor gaining nothing: it is already reconstructed).  Every core with such
   an edge gets it, not only the MaxST's: a new cluster aligned to the anchor through other new
   clusters would carry their alignment errors.

New images with no image edge at all are isolated: nothing can register them.  A core with no
edge to the anchor still becomes a cluster; its model cannot be aligned to the anchor and
stays a model of its own (new photos of another scene).

A finished reconstruction may be in several models (``other_nodes``: the workspace's models
besides the anchor): each is one more given cluster, and the cores get overlap with each the
same way, so that new images joining two models of the old scene let the merge join them.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from graph.expansion import expand_clusters, lost_edges_by_pair
from graph.image_graph import ImageGraph, build_image_graph, edge_arrays
from graph.partition import partition_graph

logger = logging.getLogger(__name__)

__all__ = ["ExtensionClusters", "cluster_extension"]


@dataclass(frozen=True, eq=False)
class ExtensionClusters:
    """Result of :func:`cluster_extension`; node ids are those of the input graph.

    Attributes:
        cores: the new images of each cluster (sorted int64 arrays, disjoint).
        clusters: each cluster's members: its core, the new images the expansion added, and its
            anchor overlap (sorted int64 arrays).
        anchor_overlap: the given clusters' images (the anchor's and the other given clusters')
            of each cluster (sorted int64 arrays; empty when the core has no image edge to any).
        isolated: new images with no image edge (sorted int64 array).
    """

    cores: tuple[np.ndarray, ...]
    clusters: tuple[np.ndarray, ...]
    anchor_overlap: tuple[np.ndarray, ...]
    isolated: np.ndarray


def cluster_extension(
    graph: ImageGraph,
    new_nodes: np.ndarray,
    anchor_nodes: np.ndarray,
    max_cluster_size: int,
    completeness_ratio: float = 0.5,
    max_overlap: int = 50,
    seed: int = 0,
    other_nodes: Sequence[np.ndarray] = (),
) -> ExtensionClusters:
    """Cluster ``new_nodes`` with overlap among themselves and with the anchor cluster
    ``anchor_nodes`` (module docstring; paper section 3.1, Alg. 1, lines 1-12, the anchor being
    one more cluster that is given, not cut).  Edges touching other nodes are ignored.

    Args:
        graph: the image graph over all images.
        new_nodes: the images to cluster (distinct node ids).
        anchor_nodes: the images of the existing reconstruction (disjoint from ``new_nodes``).
        max_cluster_size, completeness_ratio, max_overlap, seed: ``S_max``, ``C``, ``O_max``
            and the seed of Alg. 1.
        other_nodes: the images of other given clusters (the reconstruction's other models),
            disjoint from the rest; ``anchor_overlap`` also holds the overlap with them.
    """
    new = np.unique(np.asarray(new_nodes, dtype=np.int64))
    given = [np.unique(np.asarray(g, dtype=np.int64)) for g in (anchor_nodes, *other_nodes)]
    anchor = np.concatenate(given)
    if np.unique(anchor).size != anchor.size or np.intersect1d(new, anchor).size:
        raise ValueError("new_nodes, anchor_nodes and other_nodes must be disjoint")
    empty = np.zeros(0, np.int64)
    if new.size == 0:
        return ExtensionClusters((), (), (), empty)
    i, j, w = edge_arrays(graph)
    is_new = np.zeros(graph.num_nodes, dtype=bool)
    is_new[new] = True
    is_anchor = np.zeros(graph.num_nodes, dtype=bool)
    is_anchor[anchor] = True
    local = np.full(graph.num_nodes, -1, dtype=np.int64)
    local[new] = np.arange(new.size)
    inner = is_new[i] & is_new[j]
    sub = build_image_graph(new.size, local[i[inner]], local[j[inner]], w[inner])
    to_anchor = (is_new[i] & is_anchor[j]) | (is_anchor[i] & is_new[j])
    seen = np.zeros(graph.num_nodes, dtype=bool)
    seen[i[inner | to_anchor]] = True
    seen[j[inner | to_anchor]] = True
    isolated = new[~seen[new]]

    # Alg. 1, lines 1-2 on the new images' graph; images without any edge are left out.
    parts = partition_graph(sub, max_cluster_size, seed=seed)
    cores_local = [p[seen[new[p]]] for p in parts]
    cores_local = [c for c in cores_local if c.size]
    if not cores_local:
        return ExtensionClusters((), (), (), isolated)
    # Alg. 1, lines 3-12 among the new cores.
    expansion = expand_clusters(sub, cores_local, completeness_ratio, max_overlap, seed=seed)
    cores = tuple(new[c] for c in expansion.cores)
    members = [set(new[c].tolist()) for c in expansion.clusters]

    # Alg. 1, lines 6-9 along every edge between a core and a given cluster.
    labels = np.full(graph.num_nodes, -1, dtype=np.int64)
    for k, core in enumerate(cores):
        labels[core] = k
    for g, nodes in enumerate(given):
        labels[nodes] = len(cores) + g
    lost = lost_edges_by_pair(graph, labels)
    overlap = []
    for k in range(len(cores)):
        gained = empty
        for g in range(len(given)):
            ends = lost.get((k, len(cores) + g), (np.zeros((0, 2), np.int64), None))[0][:max_overlap]
            gained = np.union1d(gained, ends[:, 1]) if ends.size else gained
        members[k].update(gained.tolist())
        overlap.append(gained.astype(np.int64))
    clusters = tuple(np.array(sorted(m), dtype=np.int64) for m in members)
    logger.info("extension: %d new images -> %d clusters (cores %s), anchor overlap %s, %d isolated",
                new.size, len(cores), [c.size for c in cores], [o.size for o in overlap], isolated.size)
    return ExtensionClusters(cores, clusters, tuple(overlap), isolated)
