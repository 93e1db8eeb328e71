"""sfm.matching."""
