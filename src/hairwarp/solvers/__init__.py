"""hairwarp.solvers."""
