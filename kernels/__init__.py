"""Warp device code of hairwarp: `@wp.func` / `@wp.kernel` only, no torch import.

One module per physics family. The host side (torch autograd bridges, validation, launches)
lives in `hairwarp.ops`.
"""
