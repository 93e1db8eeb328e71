"""sfm.viz."""
