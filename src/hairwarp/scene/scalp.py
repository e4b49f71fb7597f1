"""The scalp: a 32x32 UV grid of hair roots over the head of the rest body (Section 3.1)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Scalp:
    """Hair roots on the rest body's head.

    Attributes:
        uv: (M, 2) float32 root UV coordinates in [0, 1]^2 on the scalp grid.
        positions: (M, 3) float32 rest root positions on the head surface [m], y up.
        normals: (M, 3) float32 outward unit scalp normals at the roots.
        resolution: grid size per side (32 in the paper, so M <= 1024).
    """

    uv: torch.Tensor
    positions: torch.Tensor
    normals: torch.Tensor
    resolution: int = 32

    @property
    def num_roots(self) -> int:
        return int(self.uv.shape[0])
