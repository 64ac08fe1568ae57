"""fsjax.data (placeholder for later issues)."""
