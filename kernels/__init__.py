"""Warp device code of hairwarp: `@wp.func` / `@wp.kernel` only, no torch import.

One module per physics family, one for the device L-BFGS's update (`device_lbfgs`), and one for
the energies' row sums (`reductions`). The host
side (torch autograd bridges, validation, launches) lives in `hairwarp.ops` (the solver's, in
`hairwarp.solvers.device_lbfgs`).
"""
