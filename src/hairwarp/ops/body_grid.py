"""A hashed grid of a body's faces for short closest-face queries (`hairwarp.kernels.body_grid`).

The guides' walk (`follow_guides`) makes long chains of queries a few millimetres from the
surface, one after the other in one thread; a query within the grid's reach reads one bucket
instead of descending the BVH from its root. The grid is refilled from the body's current
vertices at every call (`fill`): a few tens of microseconds on a GPU, no host synchronisation,
so a CUDA graph can hold it.
"""

from __future__ import annotations

import torch
import warp as wp

from hairwarp import _warp
from hairwarp.kernels import body_grid as kernels

# Cell edge and reach [m]: a query of radius up to the reach is answered from the grid. The walk's
# hinted queries (the distance to the strand's last face) are ~1-3 mm near the surface.
DEFAULT_CELL = 3.0e-3
DEFAULT_REACH = 4.0e-3
# The face list's capacity over the entries counted on the body at construction: a pose may put
# more faces near more cells (a bucket past the capacity asks the BVH).
CAPACITY_FACTOR = 1.5


class BodyFaceGrid:
    """The buckets of one body mesh's faces (batch 1), refilled by `fill` as the body moves.

    Args:
        body: a `BodyMesh` of one mesh.
        cell: cell edge [m].
        reach: the largest query radius answered from the grid [m].

    The hash table has a bucket per entry (face in a cell's list) counted on the body as it is
    at construction (rounded up to a power of two), so that few cells share a bucket; the face
    list holds `CAPACITY_FACTOR` x those entries. Memory: 12 bytes a bucket, 4 an entry (the
    default body: ~2 million entries, ~30 MB).
    """

    def __init__(self, body, cell: float = DEFAULT_CELL, reach: float = DEFAULT_REACH):
        if body.batch_size != 1:
            raise ValueError(f"body: BodyFaceGrid takes a body of one mesh, got {body.batch_size}")
        if not (cell > 0 and reach > 0):
            raise ValueError(f"cell, reach: expected positive lengths [m], got {cell}, {reach}")
        self.body, self.cell, self.reach = body, float(cell), float(reach)
        device = body.device
        # Count the entries once into a provisional table, then size the real one.
        self.buckets, self.capacity = 1 << 16, 0
        self._allocate(device)
        self._launch(write=False)
        entries = int(self.count.sum())
        self.buckets = 1 << max(10, (max(entries, 1) - 1).bit_length())
        self.capacity = int(CAPACITY_FACTOR * entries) + 1024
        self._allocate(device)

    def _allocate(self, device: torch.device) -> None:
        self.count = torch.zeros(self.buckets, dtype=torch.int32, device=device)
        self.start = torch.zeros(self.buckets, dtype=torch.int32, device=device)
        self.faces = torch.empty(max(self.capacity, 1), dtype=torch.int32, device=device)

    def _launch(self, write: bool) -> None:
        body = self.body
        arrays = body._kernel_arrays(torch.float32)
        self.count.zero_()
        with _warp.launch_scope(body.device):
            _warp.launch(kernels.body_grid_fill_kernel, dim=body.num_faces,
                         inputs=[arrays[1], arrays[2], 0, 1.0 / self.cell, self.cell, self.reach, self.buckets,
                                 self.capacity, int(write), _warp.as_warp(self.start)],
                         outputs=[_warp.as_warp(self.count), _warp.as_warp(self.faces)],
                         device=_warp.warp_device(body.device))

    def fill(self) -> None:
        """Rebuild the buckets from the body's current vertices (after `BodyMesh.update`); no
        host synchronisation.
        """
        self._launch(write=False)
        torch.cumsum(self.count, 0, dtype=torch.int32, out=self.start)
        self.start.sub_(self.count)
        self._launch(write=True)

    def kernel_args(self) -> list:
        """The walk's grid arguments: 1 / cell, reach, buckets, capacity, starts, counts, faces."""
        return [1.0 / self.cell, self.reach, self.buckets, self.capacity, _warp.as_warp(self.start),
                _warp.as_warp(self.count), _warp.as_warp(self.faces)]

    def overflowed(self) -> int:
        """Buckets past the list's capacity (their queries go to the BVH); reads back."""
        return int((self.start + self.count > self.capacity).sum())


def no_grid_args(device: torch.device) -> list:
    """The walk's grid arguments when there is no grid (every query goes to the BVH)."""
    empty = wp.empty(0, dtype=wp.int32, device=_warp.warp_device(device))
    return [1.0, 0.0, 0, 0, empty, empty, empty]


__all__ = ["BodyFaceGrid", "no_grid_args"]
