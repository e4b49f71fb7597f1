"""What the rigid placement looks like against the body, per deformation-map cell.

The paper's static network sees the body only through (beta, Theta): it must learn from the
pose alone where a posed body cuts through the rigidly placed hair, which the learning curves
show it does not generalise (docs/training_diagnosis.md). With `StaticConfig.contact_samples`
= K > 0 the network also reads, for each cell of its map, the mean over the cell's strands of
K sampled vertices of the rigid placement (Eq. 1):

    signed distance to the body        clamp(d, -s, s) / s                          (1)
    push-out vector                    clamp(-d, 0, s) / s * n   (n: outward direction)  (3)
    offset from the strand's root      (p - p_root) / r                             (3)

with s = `DISTANCE_SCALE` and r = `OFFSET_SCALE`: 7 K numbers per cell, zero for a cell without
strands. They are inputs (no gradient), computed by the body's signed-distance query.
"""

from __future__ import annotations

import torch

from hairwarp.models.deformation import nearest_cell
from hairwarp.ops.hair_body_contact import hair_body_signed_distance_and_normal

# Distances beyond +-10 cm say no more than "far" [m].
DISTANCE_SCALE = 0.1
# Strand offsets from the root are divided by half a metre [m].
OFFSET_SCALE = 0.5
# Numbers per sampled vertex.
FEATURES_PER_SAMPLE = 7


def sample_indices(num_vertices: int, samples: int, device=None) -> torch.Tensor:
    """K vertex indices spread from the first moving vertex (2) to the tip, (K,) int64."""
    return torch.linspace(2, num_vertices - 1, samples, device=device).round().long()


@torch.no_grad()
def contact_features(rigid: torch.Tensor, root_uv: torch.Tensor, body, grid_height: int, grid_width: int,
                     samples: int) -> torch.Tensor:
    """Per-cell features of the rigid placement against the body (see the module docstring).

    Args:
        rigid: (B, M, N, 3) rigidly placed hair [m].
        root_uv: (M, 2) or (B, M, 2) root UVs in [0, 1]^2.
        body: a `hairwarp.ops.BodyMesh` of the posed body (batch 1 or B).
        grid_height, grid_width: the deformation map's grid (M_H0, M_W0).
        samples: K vertices per strand.

    Returns:
        (B, M_H0 * M_W0, 7 K) features in the dtype of `rigid`, cell l = row * M_W0 + col.

    Raises:
        ValueError: on a missing body or bad shapes (naming the argument).
    """
    if body is None:
        raise ValueError("body: the network reads contact features (contact_samples > 0) and needs the posed body")
    b, m, n, _ = rigid.shape
    idx = sample_indices(n, samples, rigid.device)
    points = rigid[:, :, idx].contiguous()  # (B, M, K, 3)
    distance, direction = hair_body_signed_distance_and_normal(points, body, max_distance=DISTANCE_SCALE)
    scaled = distance.clamp(-DISTANCE_SCALE, DISTANCE_SCALE) / DISTANCE_SCALE
    push = ((-distance).clamp(0.0, DISTANCE_SCALE) / DISTANCE_SCALE)[..., None] * direction
    offset = (points - rigid[:, :, :1]) / OFFSET_SCALE
    per_strand = torch.cat([scaled[..., None], push, offset], dim=-1).reshape(b, m, samples * FEATURES_PER_SAMPLE)
    cells = nearest_cell(root_uv.to(rigid.device), grid_height, grid_width)
    cells = cells.expand(b, m) if cells.dim() == 1 else cells
    num_cells = grid_height * grid_width
    sums = torch.zeros(b, num_cells, per_strand.shape[-1], dtype=rigid.dtype, device=rigid.device)
    sums.scatter_add_(1, cells[..., None].expand_as(per_strand), per_strand.to(rigid.dtype))
    counts = torch.zeros(b, num_cells, dtype=rigid.dtype, device=rigid.device)
    counts.scatter_add_(1, cells, torch.ones_like(cells, dtype=rigid.dtype))
    return sums / counts.clamp(min=1.0)[..., None]


def network_deformation(model, z, beta, theta, rigid, root_uv, body, clip=None) -> torch.Tensor:
    """A one-shot network's map D for a batch, with its contact features when it reads them.

    Args:
        model: a StaticNetwork or QuaffureNetwork (or a DistributedDataParallel around one).
        z, beta, theta: (B, d_z), (B, 16), (B, 66) network inputs.
        rigid: (B, M, N, 3) rigid placement [m]; root_uv: (M, 2) or (B, M, 2).
        body: the posed `BodyMesh` (used only by a network with contact features).
        clip: optional clamp of each deformation component [m].

    Returns:
        (B, M_H0, M_W0, N, 3) deformations [m].
    """
    inner = getattr(model, "module", model)
    reader = getattr(inner, "contact_features", None)
    contact = None if reader is None else reader(rigid, root_uv, body)
    if contact is None:
        return model(z, beta, theta, clip=clip)
    return model(z, beta, theta, clip=clip, contact=contact)


__all__ = [
    "DISTANCE_SCALE",
    "FEATURES_PER_SAMPLE",
    "OFFSET_SCALE",
    "contact_features",
    "network_deformation",
    "sample_indices",
]
