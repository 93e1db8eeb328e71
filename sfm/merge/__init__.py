"""sfm.merge.cluster_graph."""
