"""hairwarp.models."""
