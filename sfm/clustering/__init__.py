"""Clustering: the options of image clustering (paper section 3.1, Algorithm 1).

The algorithm itself lives in ``graph`` (``graph.image_graph``, ``graph.partition``,
``graph.expansion``: arrays in, arrays out) and its stage in ``sfm.stages.cluster``, which
reads the verified pairs from the database and writes ``clusters.json``.  This room holds what
a user sets: the three parameters of Algorithm 1 with the authors' defaults.

Design (Algorithm 1, with graphsfm's departures):

- The image graph: one node per image, one edge per verified pair with at least
  ``min_inliers`` (15) inliers, weighted by their number (section 3.1.1).  Images with no such
  pair cannot be reconstructed and are listed as isolated, not clustered.
- Graph cut (lines 1-2): normalized cuts into cores of at most ``max_cluster_size`` (S_max,
  100) images.  The paper's ``K = floor(n / S_max)`` would make the mean cluster larger than
  its own bound, so graphsfm takes ``K = ceil(n / S_max)`` per connected component and cuts
  any part still above S_max again with a normalized 2-way cut.
- Subgraph expansion (lines 3-12): the cluster graph's edges are the image edges lost between
  two cores, weighted by their number; along every edge of its Kruskal maximum spanning tree
  the strongest lost edges (at most ``max_overlap``, O_max, 50) are added to both clusters, so
  every MaxST edge becomes an overlap the merge can use; then, while a cluster's completeness
  ``eta(i) = sum_j |C_i and C_j| / |C_i|`` is below ``completeness`` (C, 0.5), a non-tree
  cluster edge of it is picked at random (seeded) and added the same way.
- The authors' public code departs from the paper (no MaxST in the expansion, ``K = 0`` when
  ``n < S_max``); graphsfm follows the paper and fixes those.

Modules:

- ``sfm.clustering.options``: ``ClusterOptions`` (S_max, C, O_max, the edge threshold, seed).

Paper: section 3.1 (graph cut: 3.1.1; subgraph expansion: 3.1.2), Algorithm 1, Figure 2.
"""
