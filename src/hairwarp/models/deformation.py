"""From a deformation map to hair positions: nearest lookup by root UV and tapering.

Eq. 2: p_static[s, v] = p_rigid[s, v] + N(D, uv_s) * T_taper(v), with N the nearest-cell lookup
of strand s's root UV on the coarse M_H0 x M_W0 grid (8x8 for HairFormer, 32x32 for the
Quaffure baseline) and T_taper the linear taper of Section 4.2.3.

Grid convention: the map is indexed [row, col] with row = floor(v * M_H0) and
col = floor(u * M_W0) for root UV (u, v) in [0, 1]^2, clamped to the grid: the cell whose centre
((col + 0.5) / M_W0, (row + 0.5) / M_H0) is nearest to the root. UVs outside [0, 1] take the
nearest edge cell.

Taper choice: Section 4.2.3 scales vertex v = 1..N by (v - 1) / (N - 1), so the root (v = 1,
index 0) gets 0 and the second vertex (index 1) 1 / (N - 1). The paper also fixes vertices 0 and
1 of every strand (Section 4.3.2: "all hair vertices except the first two" move), so we zero
the factor of index 1 too and keep the paper's linear values k / (N - 1) for indices k >= 2.
Vertices 0 and 1 then stay exactly at their rigid positions (rigid + 0 * D is exact for finite
D), and the root segment keeps its rigid direction, which the root alignment loss (Eq. 15)
assumes.
"""

from __future__ import annotations

import torch

from hairwarp._validate import FLOAT_DTYPES, check_tensor
from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.ops.strand_projection import follow_the_leader
from hairwarp.models.config import LENGTH_PROJECTION_FOLLOW_THE_LEADER, LENGTH_PROJECTIONS


def taper_weights(
    num_vertices: int, *, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> torch.Tensor:
    """Per-vertex taper factors T_taper (Section 4.2.3), with vertex 1 held fixed too.

    Args:
        num_vertices: N, vertices per strand (>= 3).
        dtype: float32 or float64.
        device: where the result lives.

    Returns:
        (N,) tensor: 0 for indices 0 and 1, k / (N - 1) for index k >= 2 (1 at the tip).
    """
    if not isinstance(num_vertices, int) or num_vertices < NUM_FIXED_VERTICES + 1:
        raise ValueError(f"num_vertices: expected an int >= {NUM_FIXED_VERTICES + 1}, got {num_vertices!r}")
    if dtype not in FLOAT_DTYPES:
        raise ValueError(f"dtype: expected float32 or float64, got {dtype}")
    weights = torch.arange(num_vertices, dtype=dtype, device=device) / (num_vertices - 1)
    weights[:NUM_FIXED_VERTICES] = 0.0
    return weights


def nearest_cell(root_uv: torch.Tensor, grid_height: int, grid_width: int) -> torch.Tensor:
    """The deformation-map cell of each strand: the nearest lookup N of Eq. 2.

    Args:
        root_uv: (..., M, 2) root UV coordinates (u, v) in [0, 1]^2 (outside: nearest edge cell).
        grid_height: M_H0, rows (follow v).
        grid_width: M_W0, columns (follow u).

    Returns:
        (..., M) int64 flat cell index row * grid_width + col.
    """
    check_tensor("root_uv", root_uv, shape=["...", None, 2])
    for name, value in (("grid_height", grid_height), ("grid_width", grid_width)):
        if not isinstance(value, int) or value <= 0:
            raise ValueError(f"{name}: expected a positive int, got {value!r}")
    # floor(x * n) picks the cell whose centre (k + 0.5) / n is nearest to x; x = 1 belongs to
    # the last cell, hence the clamp.
    col = torch.floor(root_uv[..., 0] * grid_width).long().clamp_(0, grid_width - 1)
    row = torch.floor(root_uv[..., 1] * grid_height).long().clamp_(0, grid_height - 1)
    return row * grid_width + col


def _check_root_uv(root_uv, batch: int, device: torch.device) -> None:
    check_tensor("root_uv", root_uv, dtypes=None, device=device, allow_empty=False)
    if root_uv.dim() not in (2, 3) or root_uv.shape[-1] != 2:
        raise ValueError(f"root_uv: expected shape (M, 2) or (B, M, 2), got {tuple(root_uv.shape)}")
    if root_uv.dim() == 3 and root_uv.shape[0] != batch:
        raise ValueError(f"root_uv: expected batch size {batch} like deformation_map, got {root_uv.shape[0]}")
    if not root_uv.is_floating_point():
        raise ValueError(f"root_uv: expected a floating-point tensor, got {root_uv.dtype}")


def sample_deformation(deformation_map: torch.Tensor, root_uv: torch.Tensor) -> torch.Tensor:
    """Raw per-strand deformations N(D, uv_s) of Eq. 2, before tapering.

    Args:
        deformation_map: (B, M_H0, M_W0, N, 3) deformations [m].
        root_uv: (M, 2) root UVs shared by the batch, or (B, M, 2) per batch entry.

    Returns:
        (B, M, N, 3) the deformation of each strand's cell [m], differentiable w.r.t. the map.
    """
    check_tensor("deformation_map", deformation_map, shape=[None, None, None, None, 3])
    b, gh, gw, n, _ = deformation_map.shape
    _check_root_uv(root_uv, b, deformation_map.device)
    cells = nearest_cell(root_uv, gh, gw)  # (M,) or (B, M)
    flat = deformation_map.reshape(b, gh * gw, n, 3)
    batch_index = torch.arange(b, device=flat.device)[:, None]
    return flat[batch_index, cells if cells.dim() == 2 else cells[None, :]]


def length_projection_of(model) -> str:
    """The `length_projection` a network's drapes use (a DDP wrapper, a dynamic network's static
    settings and a config without the field, "none", are all understood).
    """
    model = getattr(model, "module", model)
    config = model.config
    config = getattr(config, "static", config)
    return getattr(config, "length_projection", "none")


def apply_deformation(
    rigid: torch.Tensor, deformation_map: torch.Tensor, root_uv: torch.Tensor, length_projection: str = "none"
) -> torch.Tensor:
    """Hair positions from the rigid placement and a deformation map (Eq. 2 with Section 4.2.3).

    p[b, s, v] = rigid[b, s, v] + D[b, cell(uv_s)][v] * taper(v), where cell is the nearest
    lookup and taper is `taper_weights` (0 for vertices 0 and 1, which stay exactly fixed).
    With `length_projection="follow_the_leader"` these positions are then projected onto the
    rigid placement's segment lengths (`hairwarp.ops.follow_the_leader`): the map only bends
    strands, never stretches them.

    Args:
        rigid: (B, M, N, 3) rigidly posed hair P_rigid [m] (Eq. 1), float32 or float64.
        deformation_map: (B, M_H0, M_W0, N, 3) network output [m], same dtype and device.
        root_uv: (M, 2) or (B, M, 2) root UVs in [0, 1]^2.
        length_projection: "none" (Eq. 2 as the paper) or "follow_the_leader"
            (`StaticConfig.length_projection`).

    Returns:
        (B, M, N, 3) deformed hair positions [m], differentiable w.r.t. the map (and `rigid`
        without a projection).

    Raises:
        ValueError: on a wrong shape, dtype, device, N < 3, mismatched sizes, NaN or Inf.
    """
    check_tensor("rigid", rigid, shape=[None, None, None, 3], allow_empty=False)
    check_tensor(
        "deformation_map", deformation_map, shape=[None, None, None, None, 3],
        dtypes=(rigid.dtype,), device=rigid.device, allow_empty=False,
    )
    b, m, n, _ = rigid.shape
    if deformation_map.shape[0] != b:
        raise ValueError(f"deformation_map: expected batch size {b} like rigid, got {deformation_map.shape[0]}")
    if deformation_map.shape[3] != n:
        raise ValueError(f"deformation_map: expected {n} vertices per strand like rigid, got {deformation_map.shape[3]}")
    _check_root_uv(root_uv, b, rigid.device)
    if root_uv.shape[-2] != m:
        raise ValueError(f"root_uv: expected {m} strands like rigid, got shape {tuple(root_uv.shape)}")
    if length_projection not in LENGTH_PROJECTIONS:
        raise ValueError(f"length_projection: expected one of {list(LENGTH_PROJECTIONS)}, got {length_projection!r}")
    taper = taper_weights(n, dtype=rigid.dtype, device=rigid.device)
    positions = rigid + sample_deformation(deformation_map, root_uv) * taper[:, None]
    if length_projection == LENGTH_PROJECTION_FOLLOW_THE_LEADER:
        positions = follow_the_leader(rigid, positions)
    return positions
