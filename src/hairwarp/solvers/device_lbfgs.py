"""L-BFGS that never reads the device inside an iteration, so a CUDA graph can hold one.

torch.optim.LBFGS runs its strong-Wolfe line search in Python: every trial step reads the loss
and a directional derivative back to the host, and each iteration is ~100 small torch launches.
On one H100 that host work cost ~7 ms per iteration of full-size Table 1 against ~1 ms of
energy (docs/contact.md, section 6). Here an iteration is one energy evaluation at a trial
point and a masked update, all device tensors:

- trial: x + t d, every vertex moved at most `max_step` (a far trial point would make the
  hair-hair broad phase walk huge boxes); Armijo test f(x + t d) <= f(x) + c1 t g.d, which a
  non-finite trial fails.
- accepted: x, f, g move; the pair (s, y) enters the memory when s.y > `curvature_eps` |s|^2
  (the cautious update of Li & Fukushima 2001: scale-free, so tiny late steps still update); the
  next trial is t = 1 (L-BFGS's direction is scaled by the newest s.y / y.y).
- rejected: x stays; t shrinks to the minimiser of the quadratic through f(x), g.d and the
  trial's f, clamped to [0.1 t, 0.5 t] (Nocedal & Wright, Section 3.5); after `restart`
  rejections in a row the memory is cleared (a stale curvature pair after a contact switches
  on or off can point nowhere).
- direction: the two-loop recursion in closed form (Byrd, Nocedal & Schnabel 1994): with the
  memory's pairs newest first, the first loop's coefficients solve a unit lower-triangular
  system and the second loop's a unit upper-triangular one (m x m, float64), so a direction is
  four (m, n) products and two single-thread solves whatever the memory m. The memory is a ring
  buffer (a new pair overwrites the oldest row; s_i . y_j kept as pairs enter). With no memory
  (the start, after a clear, or when the memory's direction is not a descent direction) it is
  -g scaled by min(1, 1 / |g|_1), torch's first step.

The loss never increases (only Armijo steps are taken), so the current iterate is the best.
The drivers live with their callers (`hairwarp.solvers.direct.optimize_drape_on_device`, the
physics solver `hairwarp.solvers.physics`); this module imports neither.

On CUDA one iteration is captured in a graph (after a real first iteration has warmed it up)
and replayed `chunk` times back to back; per chunk the host reads the chunk's losses (stopping
rule, history, progress bar) and the largest hair-hair pair count; a pair count beyond the
buffer restores the chunk's starting state and captures again with a buffer twice the count.
On the CPU the same iterations run eagerly (with the hair-hair pair cache). An iteration here
is one energy evaluation; a rejected trial counts as one. Besides the energy an iteration is
~25 kernels: the n-sized products by torch (cuBLAS), the decisions and the solves in Warp
kernels (`hairwarp.kernels.device_lbfgs`).

Measured (docs/contact.md, sections 7-14): full-size Table 1 on one H100 reaches the accuracy of
300 strong-Wolfe iterations (2.1-2.2 s with its energy in a CUDA graph) in 0.45-0.55 s, every run
(0.25-0.28 s in two runs of three before the body's self-intersections were cut, when the third
stopped short at a sign error of the armpits).
"""

from __future__ import annotations

import torch
import warp as wp

from hairwarp import _warp
from hairwarp.kernels import device_lbfgs as lbfgs_kernels

# Armijo's sufficient-decrease constant (Nocedal & Wright's usual 1e-4).
ARMIJO_C1 = 1e-4


def lbfgs_direction(g: torch.Tensor, S: torch.Tensor, Y: torch.Tensor, rho: torch.Tensor,
                    gamma: torch.Tensor, SY: torch.Tensor | None = None,
                    order: torch.Tensor | None = None) -> torch.Tensor:
    """The L-BFGS search direction -H g by the two-loop recursion, in closed form (torch ops).

    `DeviceLBFGS.iterate` computes the same in Warp kernels; this form is the one its tests
    check them against.

    Args:
        g: (n,) gradient.
        S, Y: (m, n) the memory's steps s_k and gradient changes y_k.
        rho: (m,) 1 / (s_k . y_k); zero marks an unused row (its S, Y rows are then ignored).
        gamma: () the initial inverse-Hessian scale (s.y / y.y of the newest pair).
        SY: (m, m) float64 s_i . y_j if the caller keeps it (else computed here).
        order: (m,) int64 the rows newest first (a ring buffer's); default: row 0 newest.

    Returns:
        (n,) the direction d = -H g, equal to the two-loop recursion's.
    """
    m = S.shape[0]
    work = torch.float64
    SY = (S @ Y.T).to(work) if SY is None else SY  # SY[i, j] = s_i . y_j
    if order is None:
        order = torch.arange(m, device=g.device)
    # Everything of size m in newest-first order k; the (m, n) rows stay where they are.
    Sg = (S @ g).to(work)[order]
    SYo = SY[order][:, order]
    rho_o = rho.to(work)[order]
    eye = torch.eye(m, dtype=work, device=g.device)
    # First loop, newest (k = 0) to oldest: a_k = rho_k s_k.(g - sum_{j<k} a_j y_j).
    lower = eye + rho_o[:, None] * torch.tril(SYo, diagonal=-1)
    a = torch.linalg.solve_triangular(lower, (rho_o * Sg)[:, None], upper=False, unitriangular=True)[:, 0]
    a_rows = torch.zeros_like(a).index_copy(0, order, a).to(g.dtype)
    r = gamma * (g - Y.T @ a_rows)
    # Second loop, oldest to newest: c_k = a_k - rho_k y_k.(r + sum_{j>k} c_j s_j).
    Yr = (Y @ r).to(work)[order]
    upper = eye + rho_o[:, None] * torch.triu(SYo.T, diagonal=1)
    c = torch.linalg.solve_triangular(upper, (a - rho_o * Yr)[:, None], upper=True, unitriangular=True)[:, 0]
    c_rows = torch.zeros_like(c).index_copy(0, order, c).to(g.dtype)
    return -(r + S.T @ c_rows)


class DeviceLBFGS:
    """The solver's state and one iteration of it (torch ops only, nothing read back).

    The memory is a ring buffer: a new pair overwrites the oldest row (no (m, n) shift), the
    products s_i . y_j are kept as pairs enter (two (m, n) products per step), and a cleared
    memory is rho = 0 (the rows stay, ignored).

    Args:
        energy: `energy(x, graph_safe) -> (f, g, pair_count)`: the loss () and its gradient (n,)
            at the flat parameters x (n,), and a device tensor (or int) the caller wants the
            largest of (the hair-hair pair count; 0 when none). With `graph_safe` it must read
            nothing back to the host.
        x0: (n,) the start.
        solver: a `DirectOptimizationConfig` (lbfgs_history, lbfgs_max_step, lbfgs_restart,
            lbfgs_curvature_eps).
        chunk: length of `trace`: the losses of the last `chunk` iterations, in the order they
            ran since `start_chunk()`.
        point_size: components per point of x (3: a step moves no point of x farther than
            `lbfgs_max_step`).
        graph_safe: evaluate with `graph_safe=True` in the iterations (CUDA graphs).

    A caller that knows its problem's scales passes scaled variables instead of a preconditioner
    (`hairwarp.solvers.physics`: x = S z): L-BFGS on z is L-BFGS with H0 = gamma S^2, gamma still
    fitted to the newest pair.
    """

    def __init__(self, energy, x0: torch.Tensor, solver, *, chunk: int, point_size: int = 3,
                 graph_safe: bool = False):
        self.energy, self.solver, self.point_size, self.graph_safe = energy, solver, point_size, graph_safe
        self.device, self.dtype = x0.device, x0.dtype
        x = x0.detach().reshape(-1).clone()
        n, m = x.numel(), solver.lbfgs_history
        zeros = dict(device=self.device, dtype=self.dtype)
        index = dict(device=self.device, dtype=torch.int64)
        self.x = x
        f, g, self.first_count = energy(x, False)
        self.f, self.g = f.detach().reshape(()).clone(), g.detach().reshape(-1).clone()
        self.S = torch.zeros(m, n, **zeros)
        self.Y = torch.zeros(m, n, **zeros)
        self.rho = torch.zeros(m, **zeros)
        self.SY = torch.zeros(m, m, device=self.device, dtype=torch.float64)  # s_i . y_j, kept as rows enter
        self.head = torch.full((1,), m - 1, **index)  # the newest row
        self.steps_back = torch.arange(m, **index)
        self.gamma = self._first_scale(self.g)
        self.d = -self.gamma * self.g
        self.t = torch.ones((), **zeros)
        self.rejections = torch.zeros((), device=self.device, dtype=torch.int32)
        self.trace = torch.zeros(chunk, **zeros)
        self.position = torch.zeros((1,), **index)  # where the next loss goes in trace
        self.pairs = torch.zeros((), **index)  # largest pair count met
        self.gmax = self.g.abs().max().clone()
        # Scratch of an iteration (`iterate`).
        self.t_trial = torch.ones((), **zeros)
        self.first = torch.ones((), **zeros)
        self.flags = torch.zeros(2, device=self.device, dtype=torch.int32)  # accepted, stored
        self.a = torch.zeros(m, device=self.device, dtype=torch.float64)
        self.c = torch.zeros(m, device=self.device, dtype=torch.float64)
        self.a_rows = torch.zeros(m, **zeros)
        self.c_rows = torch.zeros(m, **zeros)
        self.fallback = torch.zeros_like(self.g)  # the direction's fallback, before its sign and scale
        # Warp views of the state and scratch, made once (the tensors keep their addresses).
        self._warp = {name: _warp.as_warp(getattr(self, name)) for name in (
            "x", "f", "g", "d", "t", "S", "Y", "rho", "SY", "gamma", "head", "rejections", "trace", "position",
            "t_trial", "first", "flags", "a", "c", "a_rows", "c_rows", "fallback")}

    def restart_at(self, x: torch.Tensor, *, keep_memory: bool = False) -> None:
        """Start again from `x` (n,), in place and graph-safe: evaluates the energy there (f, g),
        the first direction, t = 1, no rejections; the memory cleared unless `keep_memory` (its
        curvature pairs then serve the new start, as a warm start across similar problems).
        """
        self.x.copy_(x.reshape(-1))
        f, g, count = self.energy(self.x, self.graph_safe)
        if isinstance(count, torch.Tensor):
            self.pairs.copy_(torch.maximum(self.pairs, count.reshape(()).to(torch.int64)))
        self.f.copy_(f.reshape(()))
        self.g.copy_(g.reshape(-1))
        if not keep_memory:
            self.rho.zero_()
        self.t.fill_(1.0)
        self.rejections.zero_()
        self.gamma.copy_(self._first_scale(self.g))
        self.d.copy_(self.g).mul_(-self.gamma)
        torch.linalg.vector_norm(self.g, float("inf"), out=self.gmax)

    @staticmethod
    def _first_scale(g: torch.Tensor) -> torch.Tensor:
        """min(1, 1 / |g|_1): torch's first L-BFGS step, and ours after a clear."""
        return torch.clamp(1.0 / g.abs().sum().clamp_min(1e-30), max=1.0)

    def state(self) -> list[torch.Tensor]:
        """The tensors an iteration changes (saved and restored around a chunk)."""
        return [self.x, self.f, self.g, self.d, self.t, self.S, self.Y, self.rho, self.SY, self.head, self.gamma,
                self.rejections]

    def start_chunk(self) -> None:
        """The next iteration's loss goes to trace[0]."""
        self.position.zero_()

    def iterate(self) -> None:
        """One trial step and the masked update; appends the new loss to `trace`.

        About 25 kernels: the n-sized products through torch (cuBLAS), the decisions and the
        memory's m x m solves in single-thread Warp kernels (`kernels.device_lbfgs`), the masked
        updates in one kernel over n. The same steps as torch ops were ~180 operations, most on
        0-d tensors, each its own kernel (docs/contact.md 13).
        """
        s_cfg = self.solver
        m, n = self.rho.shape[0], self.x.numel()
        w = self._warp
        device = _warp.warp_device(self.device)
        with _warp.launch_scope(self.device):
            # The trial step, every point moved at most max_step.
            step_max = torch.linalg.vector_norm(self.d.view(-1, self.point_size), dim=1).max()
            _warp.launch(lbfgs_kernels.lbfgs_trial_scale_kernel, dim=1,
                         inputs=[w["t"], _warp.as_warp(step_max), wp.float64(s_cfg.lbfgs_max_step)],
                         outputs=[w["t_trial"]], device=device)
            trial = torch.addcmul(self.x, self.t_trial, self.d)
        f_t, g_t, count = self.energy(trial, self.graph_safe)
        if isinstance(count, torch.Tensor):
            self.pairs.copy_(torch.maximum(self.pairs, count.reshape(()).to(torch.int64)))
        g_t = g_t.reshape(-1)
        with _warp.launch_scope(self.device):
            y = g_t - self.g
            products = torch.stack([self.g, y, self.d])
            gram = products @ products.T  # g.d, y.d, y.y, d.d among them
            _warp.launch(lbfgs_kernels.lbfgs_accept_kernel, dim=1,
                         inputs=[_warp.as_warp(f_t.reshape(1)), _warp.as_warp(gram), w["t_trial"], m, wp.float64(ARMIJO_C1),
                                 wp.float64(s_cfg.lbfgs_curvature_eps), int(s_cfg.lbfgs_restart or 0),
                                 w["f"], w["t"], w["rho"], w["gamma"], w["head"], w["rejections"], w["trace"],
                                 w["position"]],
                         outputs=[w["flags"]], device=device)
            _warp.launch(lbfgs_kernels.lbfgs_update_kernel, dim=n,
                         inputs=[w["flags"], w["t_trial"], w["d"], _warp.as_warp(y), _warp.as_warp(trial),
                                 _warp.as_warp(g_t), w["head"], n, w["x"], w["g"], w["S"], w["Y"]], device=device)
            # The stored row's products with every pair, then the direction from the new g.
            Yd, Sy, Sg = self.Y @ self.d, self.S @ y, self.S @ self.g
            g_norm1 = torch.linalg.vector_norm(self.g, 1)
            _warp.launch(lbfgs_kernels.lbfgs_first_loop_kernel, dim=1,
                         inputs=[w["flags"], w["t_trial"], _warp.as_warp(Yd), _warp.as_warp(Sy), _warp.as_warp(Sg),
                                 _warp.as_warp(g_norm1), w["rho"], w["head"], m, w["SY"], w["gamma"]],
                         outputs=[w["first"], w["a"], w["a_rows"]], device=device)
            r = torch.addmv(self.g, self.Y.T, self.a_rows, alpha=-1.0)
            r.mul_(self.gamma)
            self.fallback.copy_(self.g)
            Yr = self.Y @ r
            _warp.launch(lbfgs_kernels.lbfgs_second_loop_kernel, dim=1,
                         inputs=[w["a"], _warp.as_warp(Yr), w["rho"], w["SY"], w["head"], m],
                         outputs=[w["c_rows"], w["c"]], device=device)
            candidate = torch.addmv(r, self.S.T, self.c_rows, beta=-1.0, alpha=-1.0)  # -(r + S^T c)
            _warp.launch(lbfgs_kernels.lbfgs_direction_kernel, dim=n,
                         inputs=[_warp.as_warp(candidate), _warp.as_warp(torch.dot(self.g, candidate)), w["fallback"],
                                 w["first"], m],
                         outputs=[w["d"], w["rho"]], device=device)
            torch.linalg.vector_norm(self.g, float("inf"), out=self.gmax)
