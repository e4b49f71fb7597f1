"""hairwarp.scene."""
