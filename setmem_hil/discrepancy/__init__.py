"""discrepancy."""
