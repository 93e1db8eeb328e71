"""sfm.stages.match."""
