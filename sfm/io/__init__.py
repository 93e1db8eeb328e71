"""sfm.io."""
