"""sfm.clustering."""
