"""sfm.core."""
