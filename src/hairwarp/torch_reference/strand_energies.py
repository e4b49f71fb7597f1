"""The strand energy terms of HairFormer Section 3.4 (Eq. 7-11, 15, 16) in plain, vectorized torch.

What a user without this library would write: autograd gives the gradient. Same signatures,
shapes and conventions as `hairwarp.ops.strand_energies` (less the `layout` argument), used to
cross-check the Warp kernels and as their benchmark peer. Vertices 0 and 1 of every strand are
detached, so their gradient is zero as in the fused kernels; p(t-1), p(t-2), the rigid placement,
rest lengths and normals are detached too (constants).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

from hairwarp.config import NUM_FIXED_VERTICES, STRAND_TERMS, EnergyConfig

_DEFAULTS = EnergyConfig()


def _fix_roots(x: torch.Tensor) -> torch.Tensor:
    """X with vertices 0 and 1 detached: fixed in the paper, excluded from the gradient."""
    return torch.cat([x[..., :2, :].detach(), x[..., 2:, :]], dim=-2)


def _check_x(x) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() not in (3, 4) or x.shape[-1] != 3:
        raise ValueError(f"x: expected a (B, M, N, 3) or (M, N, 3) tensor, got {getattr(x, 'shape', x)!r}")
    if x.shape[-3] < 1 or x.shape[-2] < 3:
        raise ValueError(f"x: expected M >= 1 strands of N >= 3 vertices, got shape {tuple(x.shape)}")


def _mass(x: torch.Tensor, vertex_mass) -> torch.Tensor:
    """Masses of the moving vertices, broadcastable to x[..., 2:, 0]."""
    if isinstance(vertex_mass, torch.Tensor):
        return vertex_mass.detach()[..., NUM_FIXED_VERTICES:]
    return x.new_tensor(float(vertex_mass))


def stretch_energy(
    x: torch.Tensor, rest_lengths: torch.Tensor, weight: float = _DEFAULTS.stretch_weight
) -> torch.Tensor:
    """Eq. 7: k_s / (M (N-1)) sum (|p_{i+1} - p_i| - l0_i)^2; `(B,)` or `()`."""
    _check_x(x)
    p = _fix_roots(x)
    m, n = x.shape[-3], x.shape[-2]
    length = torch.linalg.vector_norm(p[..., 1:, :] - p[..., :-1, :], dim=-1)
    return (weight / (m * (n - 1))) * ((length - rest_lengths.detach()) ** 2).sum(dim=(-2, -1))


def bending_energy(
    x: torch.Tensor, weight: float = _DEFAULTS.bending_weight, eps: float = _DEFAULTS.bending_eps
) -> torch.Tensor:
    """Eq. 8: k_b sum arccos(clamp(theta, -1 + eps, 1 - eps)) over valid joints; `(B,)` or `()`."""
    _check_x(x)
    p = _fix_roots(x)
    e = p[..., 1:, :] - p[..., :-1, :]
    length = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
    u = e / (length + eps)
    theta = (u[..., :-1, :] * u[..., 1:, :]).sum(dim=-1)
    valid = (length[..., :-1, 0] > eps) & (length[..., 1:, 0] > eps)
    # Invalid joints read a harmless 0 so that no NaN gradient leaks through torch.where.
    theta = torch.where(valid, theta.clamp(-1.0 + eps, 1.0 - eps), torch.zeros_like(theta))
    alpha = torch.where(valid, torch.acos(theta), torch.zeros_like(theta))
    return weight * alpha.sum(dim=(-2, -1))


def auxiliary_energy(
    x: torch.Tensor, rigid: torch.Tensor, weight: float = _DEFAULTS.auxiliary_weight
) -> torch.Tensor:
    """Eq. 9: lambda_aux / (3 M N) sum |p - p_rigid|^2; `(B,)` or `()`."""
    _check_x(x)
    p = _fix_roots(x)
    m, n = x.shape[-3], x.shape[-2]
    return (weight / (3 * m * n)) * ((p - rigid.detach()) ** 2).sum(dim=(-3, -2, -1))


def smoothness_energy(x: torch.Tensor, weight: float = _DEFAULTS.smoothness_weight) -> torch.Tensor:
    """Eq. 10: lambda_smooth / (M (N-2)) sum |p_{v+1} - 2 p_v + p_{v-1}|^2; `(B,)` or `()`."""
    _check_x(x)
    p = _fix_roots(x)
    m, n = x.shape[-3], x.shape[-2]
    r = p[..., 2:, :] - 2.0 * p[..., 1:-1, :] + p[..., :-2, :]
    return (weight / (m * (n - 2))) * (r**2).sum(dim=(-3, -2, -1))


def gravity_energy(
    x: torch.Tensor,
    vertex_mass: float | torch.Tensor = _DEFAULTS.vertex_mass,
    gravity: Sequence[float] = _DEFAULTS.gravity,
    weight: float = _DEFAULTS.gravity_weight,
) -> torch.Tensor:
    """Eq. 11: -weight sum_{v>=2} m_v g . p_v [J]; `(B,)` or `()`."""
    _check_x(x)
    g = x.new_tensor(tuple(float(c) for c in gravity))
    height = (x[..., 2:, :] * g).sum(dim=-1)
    return -weight * (_mass(x, vertex_mass) * height).sum(dim=(-2, -1))


def root_alignment_energy(
    x: torch.Tensor,
    scalp_normals: torch.Tensor,
    weight: float = _DEFAULTS.root_alignment_weight,
    segments: int = _DEFAULTS.root_alignment_segments,
    eps: float = _DEFAULTS.root_alignment_eps,
) -> torch.Tensor:
    """Eq. 15: lambda_root (1 - 1/(M k') sum_{i=1}^{k'} d_hat_i . n); k' = min(segments, N-2)."""
    _check_x(x)
    m, n = x.shape[-3], x.shape[-2]
    k = min(int(segments), n - 2)
    if k == 0:
        return (x * 0.0).sum(dim=(-3, -2, -1))
    p = _fix_roots(x)
    e = p[..., 2 : k + 2, :] - p[..., 1 : k + 1, :]
    d_hat = e / (torch.linalg.vector_norm(e, dim=-1, keepdim=True) + eps)
    cosines = (d_hat * scalp_normals.detach().unsqueeze(-2)).sum(dim=-1)
    return weight * (1.0 - cosines.sum(dim=(-2, -1)) / (m * k))


def inertia_energy(
    x: torch.Tensor,
    prev: torch.Tensor,
    prev2: torch.Tensor,
    vertex_mass: float | torch.Tensor = _DEFAULTS.vertex_mass,
    time_step: float = _DEFAULTS.time_step,
    weight: float = _DEFAULTS.inertia_weight,
) -> torch.Tensor:
    """Eq. 16: lambda / (M N_mov) sum_{v>=2} m / (2 dt^2) |p - (2 p^{t-1} - p^{t-2})|^2 (stop-gradient)."""
    _check_x(x)
    m, n = x.shape[-3], x.shape[-2]
    projected = (2.0 * prev - prev2).detach()[..., 2:, :]
    sq = ((x[..., 2:, :] - projected) ** 2).sum(dim=-1)
    scale = weight / (m * (n - 2) * 2.0 * time_step * time_step)
    return scale * (_mass(x, vertex_mass) * sq).sum(dim=(-2, -1))


def strand_energies(
    x: torch.Tensor,
    rest_lengths: torch.Tensor | None,
    config: EnergyConfig | None = None,
    *,
    rigid: torch.Tensor | None = None,
    scalp_normals: torch.Tensor | None = None,
    prev: torch.Tensor | None = None,
    prev2: torch.Tensor | None = None,
    vertex_mass: torch.Tensor | None = None,
    terms: Iterable[str] | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """All strand terms, as `hairwarp.ops.strand_energies` (same skipping rules).

    Returns:
        (total, per_term): total `(B,)` or `()` with autograd graph; per_term detached values.
    """
    config = config or EnergyConfig()
    w = config.weights()
    # The means over strands divide by R = `reference_strand_count` instead of M: their weights
    # times M / R.
    share = x.shape[-3] / config.strand_normalization(x.shape[-3])
    for name in ("stretch", "auxiliary", "smoothness", "root_alignment", "inertia"):
        w[name] *= share
    mass = vertex_mass if vertex_mass is not None else config.vertex_mass
    names = STRAND_TERMS if terms is None else tuple(terms)
    available = {
        "stretch": rest_lengths is not None,
        "bending": True,
        "auxiliary": rigid is not None,
        "smoothness": True,
        "gravity": True,
        "root_alignment": scalp_normals is not None
        and min(config.root_alignment_segments, x.shape[-2] - 2) > 0,
        "inertia": prev is not None and prev2 is not None,
    }
    evaluate = {
        "stretch": lambda: stretch_energy(x, rest_lengths, w["stretch"]),
        "bending": lambda: bending_energy(x, w["bending"], config.bending_eps),
        "auxiliary": lambda: auxiliary_energy(x, rigid, w["auxiliary"]),
        "smoothness": lambda: smoothness_energy(x, w["smoothness"]),
        "gravity": lambda: gravity_energy(x, mass, config.gravity, w["gravity"]),
        "root_alignment": lambda: root_alignment_energy(
            x, scalp_normals, w["root_alignment"], config.root_alignment_segments, config.root_alignment_eps
        ),
        "inertia": lambda: inertia_energy(x, prev, prev2, mass, config.time_step, w["inertia"]),
    }
    values = {
        name: evaluate[name]() for name in STRAND_TERMS if name in names and available[name] and w[name] != 0
    }
    total = sum(values.values()) if values else (x * 0.0).sum(dim=(-3, -2, -1))
    return total, {name: v.detach() for name, v in values.items()}
