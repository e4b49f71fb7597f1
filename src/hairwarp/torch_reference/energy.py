"""The total energy (Eq. 5 / Eq. 6 without L_func_reg) in plain torch: the peer of
`hairwarp.energy.total_energy` in benchmarks and cross-checks.

What a user without this library would write: vectorised torch for the strand terms
(autograd for the gradient), the hair-hair pairs from a uniform grid built with torch sorts
(`torch_reference.hair_hair_contact`, method "grid"), and for hair-body contact either the exact
brute-force point-triangle signed distance (`hair_body="exact"`, O(P F), for small checks) or
the nearest-vertex-and-normal query of neural cloth simulators (`hair_body="nearest_vertex"`,
the default for full-size scenes).
"""

from __future__ import annotations

import torch

from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs, EnergyResult
from hairwarp.torch_reference import barrier as _barrier
from hairwarp.torch_reference import hair_body_contact as _hb
from hairwarp.torch_reference import hair_hair_contact as _hh
from hairwarp.torch_reference import strand_energies as _strand


def hair_body_energy(x4: torch.Tensor, body, config: EnergyConfig, method: str) -> torch.Tensor:
    """Eq. 12 hair-body term, weight * sum over moving vertices of B(d), per batch item."""
    if method == "exact":
        return _hb.hair_body_contact_energy(x4, body.vertices, body.faces, config.hair_body_xi,
                                            config.hair_body_dhat, config.barrier_join_fraction,
                                            weight=config.hair_body_weight, variant=config.barrier_variant)
    if method != "nearest_vertex":
        raise ValueError(f"hair_body: expected 'exact' or 'nearest_vertex', got {method!r}")
    d = _hb.nearest_vertex_signed_distance(x4[:, :, NUM_FIXED_VERTICES:], body.vertices, body.faces)
    b = _barrier.barrier(d, config.hair_body_xi, config.hair_body_dhat, config.barrier_join_fraction,
                         config.barrier_variant)
    return config.hair_body_weight * b.sum(dim=(1, 2))


def total_energy(x: torch.Tensor, inputs: EnergyInputs, config: EnergyConfig | None = None, *,
                 dynamic: bool = False, hair_body: str = "nearest_vertex") -> EnergyResult:
    """Plain-torch total energy; same arguments and result type as `hairwarp.energy.total_energy`."""
    config = config or EnergyConfig()
    x4 = x if x.dim() == 4 else x.unsqueeze(0)
    total, parts = _strand.strand_energies(
        x4, inputs.rest_lengths, config, rigid=inputs.rigid, scalp_normals=inputs.scalp_normals,
        prev=inputs.prev if dynamic else None, prev2=inputs.prev2 if dynamic else None)
    result = EnergyResult(total=total, terms=dict(parts))
    if inputs.body is not None and config.hair_body_weight != 0.0:
        e = hair_body_energy(x4, inputs.body, config, hair_body)
        result.total = result.total + e
        result.terms["hair_body_contact"] = e.detach()
    if config.hair_hair_weight != 0.0:
        e, pairs = _hh.hair_hair_contact_energy(x4, config.hair_diameter, config.hair_hair_dhat,
                                                config.barrier_join_fraction, config.hair_hair_weight,
                                                config.barrier_variant, method="grid")
        result.total = result.total + e
        result.terms["hair_hair_contact"] = e.detach()
        result.hair_hair_info = int(pairs.shape[0])
    return result
