"""sfm.mapper."""
