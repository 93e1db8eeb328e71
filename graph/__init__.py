"""Combinatorial graph algorithms of GraphSfM (numpy, scipy, scikit-learn, networkx only).

Modules, in pipeline order (paper Sec. 3.1-3.2):

- ``graph.image_graph``: the weighted image graph built from verified pairs.
- ``graph.partition``: NCut partition into cores of at most ``S_max`` images (Alg. 1, l. 1-2).
- ``graph.expansion``: MaxST-guided subgraph expansion to overlapping clusters (Alg. 1, l. 3-14).
- ``graph.clustering``: both, under the size and completeness constraints (Alg. 1, Sec. 3.1).
- ``graph.merge_plan``: MinST over the cluster graph and minimum-height-tree anchor (Alg. 2).

This package never imports ``sfm`` or ``backend``.
"""
