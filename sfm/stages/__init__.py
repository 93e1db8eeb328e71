"""sfm.io.ledger."""
