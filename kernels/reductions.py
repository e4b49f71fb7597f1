"""Sums over the rows of a (rows, length) array in blocks: the energies' per-term and per-item
totals on CUDA (`hairwarp.ops.reductions`).

torch's row sums of the energy kernels' partials (7 x 102 400 floats a call at full size, the
strand terms' per-vertex energies; 102 400 doubles, the contact terms' per-vertex or per-segment
ones) took 32 and 19 us of a 500 us physics iteration on one H100 (docs/physics.md, section 2):
few outputs, long rows. Here a row is summed by `chunks` blocks, each thread striding over it, a
block's float64 sum added to the row's total by one atomic (in no fixed order).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def row_chunk_start(block: int, lane: int, chunks: int):
    """(row, first index, stride) of a thread of a launch of rows * chunks blocks: block b serves
    row b // chunks and its chunk b % chunks, each thread striding over the row by chunks *
    block_dim (`row_sums_kernel`, the L-BFGS's row products).
    """
    row = block // chunks
    return row, (block - row * chunks) * wp.block_dim() + lane, chunks * wp.block_dim()


@wp.kernel
def row_sums_kernel(
    # In:
    values: wp.array(dtype=Any),
    row_length: int,
    chunks: int,
    # Out (zeroed by the caller):
    sums_out: wp.array(dtype=Any),
):
    """sums_out[r] += sum of values[r * row_length:(r + 1) * row_length] (blocks rows * chunks)."""
    block, lane = wp.tid()
    row, i, stride = row_chunk_start(block, lane, chunks)
    base = row * row_length
    acc = wp.float64(0.0)
    while i < row_length:
        acc += wp.float64(values[base + i])
        i += stride
    total = wp.tile_sum(wp.tile(acc))
    if lane == 0:
        wp.atomic_add(sums_out, row, type(sums_out[0])(total[0]))
