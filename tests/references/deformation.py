"""numpy float64 reference of Eq. 2 (nearest lookup by root UV) and the taper of Section 4.2.3.

Written loop by loop from the paper, independent of the torch implementation:
p[b, s, v] = rigid[b, s, v] + D[b, row(uv_s), col(uv_s), v] * T(v), with the cell whose centre
is nearest to the root UV and T(v) = (v - 1) / (N - 1) for 1-based v, except that the second
vertex (fixed in the paper) gets 0 too.
"""

from __future__ import annotations

import numpy as np


def taper_weights(num_vertices: int) -> np.ndarray:
    """(N,) taper factors: (v - 1) / (N - 1) for 1-based v, and 0 for the two fixed vertices."""
    weights = np.empty(num_vertices)
    for v in range(1, num_vertices + 1):  # the paper's 1-based index
        weights[v - 1] = (v - 1) / (num_vertices - 1)
    weights[1] = 0.0
    return weights


def nearest_cell(uv: np.ndarray, grid_height: int, grid_width: int) -> tuple[int, int]:
    """(row, col) of the cell whose centre ((col + 0.5) / W, (row + 0.5) / H) is nearest to uv."""
    u, v = float(uv[0]), float(uv[1])
    best, best_d = None, np.inf
    for row in range(grid_height):
        for col in range(grid_width):
            d = abs(u - (col + 0.5) / grid_width) + abs(v - (row + 0.5) / grid_height)
            # Ties (a root exactly on a cell border) go to the upper cell, as floor() does.
            if d < best_d - 1e-12 or (abs(d - best_d) <= 1e-12 and (row, col) > best):
                best, best_d = (row, col), d
    return best


def apply_deformation(rigid: np.ndarray, deformation_map: np.ndarray, root_uv: np.ndarray) -> np.ndarray:
    """Eq. 2 with the taper: rigid (B, M, N, 3), map (B, H, W, N, 3), root_uv (M, 2) or (B, M, 2)."""
    b, m, n, _ = rigid.shape
    gh, gw = deformation_map.shape[1:3]
    taper = taper_weights(n)
    out = np.array(rigid, dtype=np.float64, copy=True)
    for i in range(b):
        uv = root_uv[i] if root_uv.ndim == 3 else root_uv
        for s in range(m):
            row, col = nearest_cell(uv[s], gh, gw)
            for v in range(n):
                out[i, s, v] += deformation_map[i, row, col, v] * taper[v]
    return out
