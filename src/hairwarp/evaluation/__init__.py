"""hairwarp.evaluation."""
