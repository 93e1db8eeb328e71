"""The graph algorithms of GraphSfM: image graph, NCut, MaxST expansion, MinST, anchor.

An array library: it takes and returns numpy arrays, ints and small frozen dataclasses, uses
numpy, scipy, scikit-learn and networkx only, and never imports ``sfm`` or ``backend``, so each
algorithm can be tested and reused alone.  It knows nothing of images, features or files: an
image is a node id ``0..n-1``, a cluster an index.  ``sfm.stages.cluster`` and ``sfm.merge``
adapt the application's data to it.

Design:

- The image graph is a symmetric ``scipy.sparse`` CSR matrix of inlier counts, so the
  partition and the expansion never build a dense ``n x n`` matrix.
- Everything is deterministic: the eigensolvers' start vectors and the random choices of the
  expansion come from a seed, and ties are broken by ids.
- Departures from the paper, each argued where it is made: ``K = ceil(n / S_max)`` per
  connected component, and 2-way normalized cuts of any part still above S_max (the paper's
  ``floor`` makes the mean cluster larger than its bound); along a MaxST edge the strongest lost
  edges go to both clusters, so every MaxST edge becomes an overlap; the anchor of two remaining
  nodes is the larger cluster, ties to the smaller id; a forest of cluster graphs gives one
  merge plan per tree.  The authors' public code departs from the paper in places (no MaxST in
  the expansion, an arbitrary tie-break at the anchor, ``K = 0`` when ``n < S_max``, only the
  largest component merged); this package follows the paper and fixes those.
- Algorithm lines are cited as the paper prints them (its pseudocode has no "end while"
  lines): Algorithm 1 is line 1 (K), 2 (GraphPartition), 3 (lost edges), 4 (cluster graph),
  5 (Kruskal MaxST), 6-9 (lost edges added along the MaxST), 10-12 (random cluster edges until
  the completeness holds); Algorithm 2 is line 1 (cluster graph), 2 (Kruskal MinST), 3-12 (the
  minimum height tree: 4-7 peel the leaves, 8-11 the larger of two is the base node).

Modules, in pipeline order:

- ``graph.image_graph``: ``ImageGraph`` and ``build_image_graph``: the weighted image graph
  from verified pairs (section 3.1.1).
- ``graph.partition``: ``partition_graph``: NCut into cores of at most ``S_max`` images
  (section 3.1.1, Alg. 1, lines 1-2).
- ``graph.expansion``: ``expand_clusters``: MaxST-guided subgraph expansion into overlapping
  clusters within the size bound (section 3.1.2, Alg. 1, lines 3-12).
- ``graph.clustering``: ``cluster_images``: both, under the size and completeness constraints
  (section 3.1): cores that leave the expansion room, re-cut where a cluster fills up below C.
- ``graph.extension``: ``cluster_extension``: images added to a finished reconstruction
  clustered by Alg. 1, each cluster with overlap into the given anchor cluster.
- ``graph.merge_plan``: ``plan_merges``: the MinST of the cluster graph (section 3.2.2,
  Eq. 7-9; Alg. 2, line 2) and the minimum-height-tree anchor (section 3.2.3, Alg. 2,
  lines 3-12).

Paper: section 3.1 (Algorithm 1, Figure 2) and sections 3.2.2-3.2.3 (Algorithm 2, Figure 3).
"""
