"""hairwarp: differentiable hair physics in NVIDIA Warp with a PyTorch front end."""

from hairwarp._validate import set_finite_checks

__version__ = "0.1.0"

__all__ = ["set_finite_checks", "__version__"]
