"""fsjax.evolve (placeholder for later issues)."""
