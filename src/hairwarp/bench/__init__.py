"""hairwarp.bench."""
