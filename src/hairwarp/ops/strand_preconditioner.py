"""Torch side of the physics steps' per-strand preconditioner; device code in
`hairwarp.kernels.strand_preconditioner`.

An implicit-Euler step at full size took ~100-180 L-BFGS iterations, and fewer strands converged
faster per iteration (docs/physics.md). The strand terms' weights are means over the M strands
(Eq. 7, 9, 10, 15, 16) while gravity (Eq. 11) is a sum: at 1 024 strands a vertex's inertia is
16x weaker against its weight than at 64, and a hanging strand's tension, lambda / l across each
segment (up to ~100x the inertia near the root), makes each strand a stiff chain whose slow
pendulum modes the L-BFGS memory learns a few at a time. Here the step's stiffness along each
strand is built once at the step's start and factored, P = U U^T (block-banded, bandwidth two),
and the solver's variables become z = U^T t (t the free targets): L-BFGS on z starts from
H0 = P^-1, the strand's own Newton step. An option of the physics solver
(`PhysicsConfig.strand_preconditioner`), off by default: on 64 strands 10-30x closer to the tight
step after 8 iterations; at 512 strands closer after 16 and 32 iterations and mixed at 64; at full
size on the GPU fewer iterations on torso_bend (62 against 85) but each ~2x the cost, and more on
whiplash: slower than the diagonal scaling (docs/physics.md, section 2, "Thirteenth session" and
"Fourteenth session").

P is assembled from the energy's gradient in the positions without contact (a contact's
curvature at the step's start models the step badly: measured worse whether differenced or as
Gauss-Newton blocks, and hair-hair contact couples strands), by one-sided differences in five
vertex colours x three coordinates (15 gradients: a vertex couples with the two on each side),
plus each segment's tension and stretch stiffness (stretch's k_s, ~10^5 x the inertia, is not
differenced: in float32 its rounding would drown the soft terms), divided by the inertia's
stiffness (so that z is in metres where the inertia dominates).
"""

from __future__ import annotations

import math

import torch

from hairwarp import _warp
from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.kernels import strand_preconditioner as kernels

# Vertex colours of the differences: the strand terms couple a vertex with two on each side.
COLOURS = 5
# The difference step [m]: wide enough for float32 positions of ~1 m (ulp 1.2e-7), narrow against
# a millimetre segment; across bending's kink (Eq. 8) a secant is what a preconditioner wants.
DIFFERENCE_STEP = 1.0e-5


class _SolveTransposed(torch.autograd.Function):
    """t = U^-T z; its adjoint w = U^-1 a."""

    @staticmethod
    def forward(ctx, z, preconditioner):
        t = torch.empty_like(z)
        preconditioner._walk(kernels.strand_band_solve_transposed_kernel, z, t)
        ctx.preconditioner = preconditioner
        return t

    @staticmethod
    def backward(ctx, grad_t):
        w = torch.empty_like(grad_t)
        ctx.preconditioner._walk(kernels.strand_band_solve_kernel, grad_t.contiguous(), w)
        return w, None


class StrandPreconditioner:
    """The factor U of each strand's step stiffness (fixed buffers: a CUDA graph can hold `build`).

    Args:
        strands: strands in all (B * M).
        num_vertices: N, vertices a strand (the first `NUM_FIXED_VERTICES` fixed).
        device, dtype: the solver's.
    """

    def __init__(self, strands: int, num_vertices: int, device: torch.device, dtype: torch.dtype):
        self.strands, self.num_vertices = int(strands), int(num_vertices)
        self.moving = self.num_vertices - NUM_FIXED_VERTICES
        rows = self.strands * self.moving
        self.device, self.dtype = torch.device(device), dtype
        # P's bands: P_ii, P_{i,i+1}, P_{i,i+2}; U: U_ii, U_ii^-1, U_{i,i+1}, U_{i,i+2}. P and its
        # factorisation are float64 whatever the solver's type: stretch makes P's condition ~10^5,
        # and a float32 factorisation of a full-size strand lost its pivots within 30 vertices of
        # the tip (clamped to the floor, then overflowed); the walks run in the solver's type.
        self.bands = torch.zeros(3, rows, 3, 3, device=self.device, dtype=torch.float64)
        self._factor64 = torch.zeros(4, rows, 3, 3, device=self.device, dtype=torch.float64)
        self.factor = torch.zeros(4, rows, 3, 3, device=self.device, dtype=dtype)
        self.factor[0] = torch.eye(3, device=self.device, dtype=dtype)
        self.factor[1] = torch.eye(3, device=self.device, dtype=dtype)  # U = I until `build`
        index = torch.arange(self.moving, device=self.device)
        # For colour c, vertex i reads the perturbed vertex i + offset (offset in -2..2).
        self._offsets = []
        for colour in range(COLOURS):
            offset = (colour - index) % COLOURS
            self._offsets.append(torch.where(offset > 2, offset - COLOURS, offset))
        self._masks = torch.zeros(COLOURS, 3, self.moving, 3, device=self.device, dtype=dtype)
        for colour in range(COLOURS):
            for k in range(3):
                self._masks[colour, k, index % COLOURS == colour, k] = DIFFERENCE_STEP

    # -- the change of variables --------------------------------------------------------------
    def _walk(self, kernel, source: torch.Tensor, out: torch.Tensor) -> None:
        device = _warp.warp_device(self.device)
        with _warp.launch_scope(self.device):
            _warp.launch(kernel, dim=self.strands,
                         inputs=[_warp.as_warp(self.factor[1], mat33=True), _warp.as_warp(self.factor[2], mat33=True),
                                 _warp.as_warp(self.factor[3], mat33=True), _warp.as_warp(source, vec3=True),
                                 self.moving],
                         outputs=[_warp.as_warp(out, vec3=True)], device=device)

    def targets(self, z: torch.Tensor) -> torch.Tensor:
        """T = U^-T z (differentiable): z (..., M, V, 3) -> free targets of the same shape [m]."""
        return _SolveTransposed.apply(z.contiguous(), self)

    def variables(self, t: torch.Tensor) -> torch.Tensor:
        """Z = U^T t of free targets t (..., M, V, 3) (no gradient)."""
        t = t.detach().contiguous()
        z = torch.empty_like(t)
        device = _warp.warp_device(self.device)
        with _warp.launch_scope(self.device):
            _warp.launch(kernels.strand_band_multiply_transposed_kernel, dim=self.strands * self.moving,
                         inputs=[_warp.as_warp(self.factor[0], mat33=True), _warp.as_warp(self.factor[2], mat33=True),
                                 _warp.as_warp(self.factor[3], mat33=True), _warp.as_warp(t, vec3=True), self.moving],
                         outputs=[_warp.as_warp(z, vec3=True)], device=device)
        return z

    # -- the stiffness and its factor ----------------------------------------------------------
    def build(self, x: torch.Tensor, gradient, stiffness: float, stretch: float) -> None:
        """P at positions x on the rest lengths, divided by `stiffness` [J/m^2], and its factor.

        Args:
            x: (B, M, N, 3) positions [m] on the rest lengths.
            gradient: positions (B, M, N, 3) -> the energy's gradient there (B, M, N, 3) [J/m],
                without stretch and without contact.
            stiffness: the inertia's stiffness per vertex [J/m^2] (the eigenvalues' floor after
                the division is 1).
            stretch: stretch's stiffness along a segment, 2 k_s / (M (N-1)) [J/m^2] (Eq. 7).
        """
        m, v = self.strands, self.moving
        x = x.detach()
        g0 = gradient(x)
        full = torch.zeros(m, v, COLOURS, 3, 3, device=self.device, dtype=torch.float64)  # P_{i, i+offset}[:, k]
        rows = torch.arange(v, device=self.device)
        for colour in range(COLOURS):
            slot = self._offsets[colour] + 2
            for k in range(3):
                step = torch.zeros_like(x)
                step[..., NUM_FIXED_VERTICES:, :] = self._masks[colour, k]
                column = (gradient(x + step) - g0)[..., NUM_FIXED_VERTICES:, :].reshape(m, v, 3) / DIFFERENCE_STEP
                full[..., k][:, rows, slot] = column.double()
        full = full / stiffness
        diag = 0.5 * (full[:, :, 2] + full[:, :, 2].transpose(-1, -2))
        off1 = torch.zeros_like(diag)
        off2 = torch.zeros_like(diag)
        # P_{i,i+1} read from both sides: column i+1 at row i, and (column i at row i+1)^T.
        off1[:, :-1] = 0.5 * (full[:, :-1, 3] + full[:, 1:, 1].transpose(-1, -2))
        off2[:, :-2] = 0.5 * (full[:, :-2, 4] + full[:, 2:, 0].transpose(-1, -2))
        self.bands[0].copy_(diag.reshape(-1, 3, 3))
        self.bands[1].copy_(off1.reshape(-1, 3, 3))
        self.bands[2].copy_(off2.reshape(-1, 3, 3))
        device = _warp.warp_device(self.device)
        scalar = _warp.scalar
        with _warp.launch_scope(self.device):
            _warp.launch(kernels.segment_tension_stiffness_kernel, dim=m,
                         inputs=[_warp.as_warp(x.double().contiguous(), vec3=True),
                                 _warp.as_warp(g0.double().contiguous(), vec3=True),
                                 self.num_vertices, scalar(1.0 / stiffness, torch.float64),
                                 scalar(stretch / stiffness, torch.float64)],
                         outputs=[_warp.as_warp(self.bands[0], mat33=True), _warp.as_warp(self.bands[1], mat33=True)],
                         device=device)
        self.factor_bands(1.0)

    def factor_bands(self, floor: float) -> None:
        """U from the bands as they are, each pivot's eigenvalues held at `floor` at least."""
        device = _warp.warp_device(self.device)
        with _warp.launch_scope(self.device):
            _warp.launch(kernels.strand_band_factor_kernel, dim=self.strands,
                         inputs=[_warp.as_warp(self.bands[i], mat33=True) for i in range(3)]
                         + [self.moving, _warp.scalar(floor, torch.float64)],
                         outputs=[_warp.as_warp(self._factor64[i], mat33=True) for i in range(4)], device=device)
        self.factor.copy_(self._factor64)

    def dense(self) -> torch.Tensor:
        """(M, 3V, 3V) float64 P from the bands (tests, small strands)."""
        m, v = self.strands, self.moving
        b = self.bands.double().reshape(3, m, v, 3, 3)
        P = torch.zeros(m, v, 3, v, 3, dtype=torch.float64, device=self.device)
        i = torch.arange(v, device=self.device)
        P[:, i, :, i, :] = b[0].permute(1, 0, 2, 3)
        P[:, i[:-1], :, i[1:], :] = b[1][:, :-1].permute(1, 0, 2, 3)
        P[:, i[1:], :, i[:-1], :] = b[1][:, :-1].transpose(-1, -2).permute(1, 0, 2, 3)
        P[:, i[:-2], :, i[2:], :] = b[2][:, :-2].permute(1, 0, 2, 3)
        P[:, i[2:], :, i[:-2], :] = b[2][:, :-2].transpose(-1, -2).permute(1, 0, 2, 3)
        return P.reshape(m, 3 * v, 3 * v)


def hanging_tension(rest_lengths: torch.Tensor, time_step: float, gravity: float) -> torch.Tensor:
    """The tension of a strand hanging under its weight over a vertex's inertia: (M, N-1), per segment.

    A segment carries the weight of the vertices below it, T = m g (L - s) / l for rest length l,
    arc length s at its top end and strand length L; its transverse stiffness T / l over a
    vertex's inertia m / h^2 is w = h^2 g (L - s) / l^2 (a 0.5 m strand of 5 mm segments at 60
    frames/s: 54 at the root).

    Args:
        rest_lengths: (M, N-1) rest segment lengths [m].
        time_step: h [s].
        gravity: |g| [m/s^2].
    """
    rest = rest_lengths.to(torch.float64)
    s = torch.cat([torch.zeros_like(rest[:, :1]), rest.cumsum(dim=1)], dim=1)  # (M, N) arc length
    below = s[:, -1:] - s[:, :-1]  # the length below each segment's top end
    return gravity * time_step ** 2 * below / rest.clamp_min(1e-9) ** 2


def chain_matrix(diagonal: torch.Tensor, tension: torch.Tensor) -> torch.Tensor:
    """(M, n, n) float64 diag(diagonal) + L_w: a chain of n free vertices whose segment above
    vertex i has the tension weight w_i (the first one's ties it to a fixed vertex), each vertex
    with its own `diagonal` stiffness.

    Args:
        diagonal: (M, n) per-vertex stiffness (dimensionless: over a vertex's inertia).
        tension: (M, n) w >= 0 of the segment above each free vertex.
    """
    w = tension.double()
    below = torch.cat([w[:, 1:], torch.zeros_like(w[:, :1])], dim=1)  # the segment below each vertex
    return (torch.diag_embed(diagonal.double() + w + below) - torch.diag_embed(w[:, 1:], 1)
            - torch.diag_embed(w[:, 1:], -1))


class ChainPreconditioner:
    """A constant change of variables per strand: P = diag(k / k_min)^(2a) + L_w, the stiffness
    scaling's diagonal (`PhysicsConfig.stiffness_scaling`, a) plus the tension Laplacian of the
    strand hanging under its weight (`hanging_tension` times `tension`), over the inertia's
    stiffness; P = L L^T, and the solver's variables are z = L^T (t - t_0): L-BFGS with H0 = P^-1.

    Why: a step's ~80 L-BFGS iterations at full size are full steps (93 % of the trials
    accepted) that a larger memory does not shorten (docs/physics.md, "Twenty-ninth session"):
    each iteration carries the head's move one neighbourhood further down a strand of ~100
    vertices. P^-1 is the hanging chain's direct solve, so one direction reaches the tip. Unlike
    `StrandPreconditioner` (each step's Newton matrix, differenced and factored at every step's
    start) P depends on the rest lengths alone: made once per solver, two dense (M, n, n) products
    an evaluation (n = N - 2; 79 MB at 1 024 x 100 in float32).

    Args:
        rest_lengths: (M, N-1) rest segment lengths [m].
        stiffness: (M, N-2) the step Hessian's diagonal per free vertex [J/m^2]
            (`hairwarp.solvers.physics.vertex_stiffness`).
        energy_config: the step's weights (`time_step` its h).
        exponent: a of the diagonal (k / k_min)^(2a).
        tension: the hanging tension's factor (0: the diagonal alone, the stiffness scaling's H0).
        device, dtype: the solver's.
    """

    def __init__(self, rest_lengths: torch.Tensor, stiffness: torch.Tensor, energy_config, *, exponent: float,
                 tension: float, device: torch.device, dtype: torch.dtype):
        rest = rest_lengths.detach().to(device=device, dtype=torch.float64)
        stiffness = stiffness.detach().to(device=device, dtype=torch.float64)
        k_min = stiffness.min()
        inertia = energy_config.inertia_stiffness(rest.shape[0], rest.shape[1] + 1)
        g = math.hypot(*energy_config.gravity) * energy_config.gravity_weight
        w = tension * hanging_tension(rest, energy_config.time_step, g) * (inertia / k_min)
        self.matrix = chain_matrix((stiffness / k_min) ** (2.0 * exponent), w[:, NUM_FIXED_VERTICES - 1:])
        lower = torch.linalg.cholesky(self.matrix)
        eye = torch.eye(lower.shape[-1], dtype=torch.float64, device=lower.device).expand_as(lower)
        self.inverse_factor = torch.linalg.solve_triangular(lower.transpose(-1, -2), eye, upper=True).to(dtype)
        self.factor_transposed = lower.transpose(-1, -2).to(dtype).contiguous()

    def targets(self, z: torch.Tensor) -> torch.Tensor:
        """T = L^-T z (differentiable): z (..., M, n, 3) -> free targets less the origin [m]."""
        return torch.matmul(self.inverse_factor, z)

    def variables(self, t: torch.Tensor) -> torch.Tensor:
        """Z = L^T t of free targets less the origin t (..., M, n, 3) (no gradient)."""
        return torch.matmul(self.factor_transposed, t.detach())


__all__ = ["StrandPreconditioner", "ChainPreconditioner", "chain_matrix", "hanging_tension", "COLOURS",
           "DIFFERENCE_STEP"]
