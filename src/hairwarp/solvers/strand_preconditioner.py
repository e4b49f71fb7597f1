"""The per-strand banded Hessian of the strand terms as an L-BFGS preconditioner.

`StrandPreconditioner.factor(x)` assembles and factors, one thread per strand, the Hessian of
stretch (Gauss-Newton, with the tension's transverse stiffness), root alignment's transverse
stiffness, smoothness and a diagonal (inertia, auxiliary) over each strand's moving vertices
(`hairwarp.kernels.strand_preconditioner`); `apply(v)` returns P^-1 v. Both are a single Warp
launch over fixed buffers, so a CUDA graph can hold them. The physics solver
(`hairwarp.solvers.physics`) factors once per time step and applies the factor in every L-BFGS
direction (two-loop recursion with H0 = P^-1).
"""

from __future__ import annotations

import torch
import warp as wp

from hairwarp import _warp
from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.kernels import strand_preconditioner as kernels


def strand_hessian_coefficients(config: EnergyConfig, num_strands: int, num_vertices: int, *,
                                dynamic: bool) -> dict[str, float]:
    """The preconditioner's three coefficients from the energy's term scales
    (`hairwarp.ops.strand_energies`: the same normalisations).

    Args:
        config: the energy's weights (stretch, smoothness, auxiliary, inertia, mass, time step).
        num_strands, num_vertices: M and N of one batch item.
        dynamic: include the inertia term's mass / dt^2 (Eq. 16).

    Returns:
        {"stretch": 2 s_stretch, "smoothness": 2 s_smooth, "diagonal": c} [J/m^2],
        "root": s_root [J] and "root_segments": k' (Eq. 15's edges 1..k').
    """
    m, n = num_strands, num_vertices
    stretch = 2.0 * config.stretch_weight / (m * (n - 1))
    smooth = 2.0 * config.smoothness_weight / (m * (n - 2))
    diagonal = 2.0 * config.auxiliary_weight / (3 * m * n)
    if dynamic:
        diagonal += inertia_stiffness(config, m, n)
    k_align = min(config.root_alignment_segments, n - 2)
    root = config.root_alignment_weight / (m * k_align) if k_align else 0.0
    return {"stretch": stretch, "smoothness": smooth, "diagonal": diagonal, "root": root, "root_segments": k_align}


def inertia_stiffness(config: EnergyConfig, num_strands: int, num_vertices: int) -> float:
    """The inertia term's Hessian per moving vertex, lambda_inertia m / (M (N-2) dt^2) [J/m^2]."""
    return config.inertia_weight * config.vertex_mass / (num_strands * (num_vertices - 2) * config.time_step ** 2)


class StrandPreconditioner:
    """Factor of the strands' banded Hessian for hair of one shape (B, M, N, 3) (float32 inside).

    Args:
        shape: (B, M, N, 3) of the hair.
        rest_lengths: (M, N-1) rest segment lengths [m] (held by reference).
        coefficients: `strand_hessian_coefficients(...)`.
        device: torch device.
    """

    def __init__(self, shape: tuple, rest_lengths: torch.Tensor, coefficients: dict[str, float],
                 device: torch.device):
        batch, strands, vertices, _ = shape
        if vertices < NUM_FIXED_VERTICES + 1:
            raise ValueError(f"shape: expected N >= 3 vertices per strand, got {vertices}")
        if rest_lengths.shape != (strands, vertices - 1) or not rest_lengths.is_floating_point():
            raise ValueError(f"rest_lengths: expected ({strands}, {vertices - 1}) floats, "
                             f"got {tuple(rest_lengths.shape)} {rest_lengths.dtype}")
        if not coefficients["diagonal"] > 0.0:
            raise ValueError(f"coefficients: the diagonal must be positive, got {coefficients['diagonal']}")
        self.shape, self.device = tuple(shape), torch.device(device)
        self.coefficients = dict(coefficients)
        self.rest_lengths = rest_lengths.detach().to(torch.float32).contiguous()
        rows, n = batch * strands, 3 * (vertices - NUM_FIXED_VERTICES)
        self.rows, self.size = rows, n
        self.band = torch.zeros(rows, n, int(kernels.BAND) + 1, dtype=torch.float64, device=self.device)
        self.work = torch.zeros(rows, n, dtype=torch.float64, device=self.device)
        self.out = torch.zeros(rows, n, dtype=torch.float32, device=self.device)
        self.rhs = torch.zeros(rows, n, dtype=torch.float32, device=self.device)
        _warp.init()
        self._w = {name: wp.from_torch(getattr(self, name)) for name in ("band", "work", "out", "rhs")}
        self._rest = wp.from_torch(self.rest_lengths)

    def factor(self, x: torch.Tensor) -> None:
        """Assemble and factor the Hessian at positions `x` (B, M, N, 3) float32 [m]."""
        if tuple(x.shape) != self.shape or x.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"x: expected {self.shape} float32 or float64, got {tuple(x.shape)} {x.dtype}")
        x = x.float() if x.dtype != torch.float32 else x
        c = self.coefficients
        _, strands, vertices, _ = self.shape
        with _warp.launch_scope(self.device):
            _warp.launch(kernels.strand_band_cholesky_kernel, dim=self.rows,
                         inputs=[_warp.as_warp(x, vec3=True), self._rest, strands, vertices,
                                 wp.float64(c["stretch"]), wp.float64(c["smoothness"]), wp.float64(c["root"]),
                                 int(c["root_segments"]), wp.float64(c["diagonal"])],
                         outputs=[self._w["band"]], device=_warp.warp_device(self.device))

    def apply(self, v: torch.Tensor) -> torch.Tensor:
        """P^-1 v for v the moving vertices' values, any shape of B M (N-2) 3 elements; returns
        the same shape (the preconditioner's own buffer: copy it to keep it past the next call).
        """
        self.rhs.view(-1).copy_(v.reshape(-1))
        with _warp.launch_scope(self.device):
            _warp.launch(kernels.strand_band_solve_kernel, dim=self.rows,
                         inputs=[self._w["band"], self._w["rhs"]], outputs=[self._w["out"], self._w["work"]],
                         device=_warp.warp_device(self.device))
        return self.out.view(v.shape) if v.dtype == torch.float32 else self.out.view(v.shape).to(v.dtype)
