"""fsjax.render (placeholder for later issues)."""
