"""Torch autograd bridges over the Warp kernels. Every function takes and returns torch tensors."""

from hairwarp.ops.barrier import barrier

__all__ = ["barrier"]
