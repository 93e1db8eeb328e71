"""sfm.stages.extract."""
