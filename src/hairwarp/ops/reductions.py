"""Row sums of the energy kernels' partial sums (`hairwarp.kernels.reductions` on CUDA, torch on
the CPU, where Warp's kernels run on one thread).
"""

from __future__ import annotations

import torch

from hairwarp import _warp
from hairwarp.kernels import reductions as kernels

# Threads a block, and the most blocks a row (each thread then strides over ~length / (chunks *
# block) entries).
_BLOCK_DIM = 256
_MAX_CHUNKS = 32


def row_sums(values: torch.Tensor) -> torch.Tensor:
    """(R,) the sums over the last dimension of a contiguous (R, L) tensor, in its dtype (float64
    accumulation on CUDA, in no fixed order). Graph-safe.
    """
    rows, length = values.shape
    if values.device.type != "cuda" or rows == 0 or length == 0:
        return values.sum(dim=1)
    return kernel_row_sums(values, max(1, min(_MAX_CHUNKS, -(-length // (_BLOCK_DIM * 8)))))


def kernel_row_sums(values: torch.Tensor, chunks: int) -> torch.Tensor:
    """`row_sums` by `row_sums_kernel`, each row in `chunks` blocks (any device; the tests run it
    on the CPU, one thread a block).
    """
    rows, length = values.shape
    sums = torch.zeros(rows, dtype=values.dtype, device=values.device)
    with _warp.launch_scope(values.device):
        _warp.launch(kernels.row_sums_kernel, dim=rows * chunks,
                     inputs=[_warp.as_warp(values.contiguous().reshape(-1)), length, chunks],
                     outputs=[_warp.as_warp(sums)], device=_warp.warp_device(values.device), block_dim=_BLOCK_DIM)
    return sums
