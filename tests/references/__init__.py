"""numpy float64 references written from the paper's equations, one module per concept."""
