"""fsjax.fit (placeholder for later issues)."""
