"""Warp device code of hairwarp: `@wp.func` / `@wp.kernel` only, no torch import.

One module per physics family, and one for the device L-BFGS's update (`device_lbfgs`). The host
side (torch autograd bridges, validation, launches) lives in `hairwarp.ops` (the solver's, in
`hairwarp.solvers.device_lbfgs`).
"""
