"""Form factors between facets (placeholder while the quadrature is written)."""
