"""sfm.evaluation.metrics."""
