"""sfm.features."""
