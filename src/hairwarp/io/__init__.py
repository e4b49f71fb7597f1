"""hairwarp.io."""
