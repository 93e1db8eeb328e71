"""sfm.execution."""
