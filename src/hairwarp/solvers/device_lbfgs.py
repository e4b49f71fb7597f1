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
  four (m, n) products and a few tiny kernels whatever the memory m. The memory is a ring
  buffer (a new pair overwrites the oldest row; s_i . y_j kept as pairs enter). With no memory
  (the start, after a clear, or when the memory's direction is not a descent direction) it is
  -g scaled by min(1, 1 / |g|_1), torch's first step.

The loss never increases (only Armijo steps are taken), so the current iterate is the best.
On CUDA one iteration is captured in a graph (after a real first iteration has warmed it up)
and replayed `chunk` times back to back; per chunk the host reads the chunk's losses (stopping
rule, history, progress bar) and the largest hair-hair pair count; a pair count beyond the
buffer restores the chunk's starting state and captures again with a buffer twice the count.
On the CPU the same iterations run eagerly (with the hair-hair pair cache). An iteration here
is one energy evaluation; a rejected trial counts as one.

Measured (docs/contact.md, sections 7-8): full-size Table 1 on one H100 reaches the accuracy of
300 strong-Wolfe iterations (1.7-1.9 s with its energy in a CUDA graph) in 0.37 s (0.45-0.46 s
before the contact terms ran on side streams).
"""

from __future__ import annotations

import math
import time

import torch

from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs, total_energy
from hairwarp.runtime import synchronize

# Armijo's sufficient-decrease constant (Nocedal & Wright's usual 1e-4).
ARMIJO_C1 = 1e-4


def lbfgs_direction(g: torch.Tensor, S: torch.Tensor, Y: torch.Tensor, rho: torch.Tensor,
                    gamma: torch.Tensor, SY: torch.Tensor | None = None,
                    order: torch.Tensor | None = None) -> torch.Tensor:
    """The L-BFGS search direction -H g by the two-loop recursion, in closed form.

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
        """One trial step and the masked update; appends the new loss to `trace`."""
        s_cfg = self.solver
        m = self.rho.shape[0]
        # The trial step, every vertex moved at most max_step.
        move = (self.t * self.d).reshape(-1, self.point_size).norm(dim=1).max()
        t = self.t * torch.clamp(s_cfg.lbfgs_max_step / move.clamp_min(1e-30), max=1.0)
        trial = self.x + t * self.d
        f_t, g_t, count = self.energy(trial, self.graph_safe)
        f_t = f_t.reshape(())
        if isinstance(count, torch.Tensor):
            self.pairs.copy_(torch.maximum(self.pairs, count.reshape(()).to(torch.int64)))
        gd = torch.dot(self.g, self.d)
        accept = torch.isfinite(f_t) & torch.isfinite(g_t).all() & (f_t <= self.f + ARMIJO_C1 * t * gd)
        # The curvature pair of an accepted step, stored over the oldest row.
        s = t * self.d
        y = g_t - self.g
        sy, yy = torch.dot(s, y), torch.dot(y, y)
        store = accept & (sy > s_cfg.lbfgs_curvature_eps * torch.dot(s, s))  # the cautious update
        row = torch.where(store, (self.head + 1) % m, self.head)
        self.S.index_copy_(0, row, torch.where(store, s, self.S.index_select(0, row)[0])[None])
        self.Y.index_copy_(0, row, torch.where(store, y, self.Y.index_select(0, row)[0])[None])
        self.rho.index_copy_(0, row, torch.where(store, 1.0 / sy.clamp_min(1e-30), self.rho.index_select(0, row)[0])[None])
        # The row's products with every pair (a stored pair's own: s.y); unchanged rows give
        # back what SY held.
        s_row = self.S.index_select(0, row)[0]
        y_row = self.Y.index_select(0, row)[0]
        self.SY.index_copy_(0, row, (self.Y @ s_row).to(torch.float64)[None])  # s_row . y_j
        self.SY.index_copy_(1, row, (self.S @ y_row).to(torch.float64)[:, None])  # s_i . y_row
        self.head.copy_(row)
        self.gamma.copy_(torch.where(store, sy / yy.clamp_min(1e-30), self.gamma))
        # The next step length after a rejected trial: the safeguarded quadratic's minimiser.
        curvature = 2.0 * (f_t - self.f - gd * t)
        quadratic = -gd * t * t / curvature
        shrunk = torch.where(torch.isfinite(quadratic) & (curvature > 0),
                             torch.minimum(torch.maximum(quadratic, 0.1 * t), 0.5 * t), 0.25 * t)
        # Move on an accepted trial.
        self.x.copy_(torch.where(accept, trial, self.x))
        self.f.copy_(torch.where(accept, f_t, self.f))
        self.g.copy_(torch.where(accept, g_t, self.g))
        self.t.copy_(torch.where(accept, torch.ones_like(t), shrunk))
        self.rejections.copy_(torch.where(accept, torch.zeros_like(self.rejections), self.rejections + 1))
        clear = self.rejections >= s_cfg.lbfgs_restart if s_cfg.lbfgs_restart else torch.zeros_like(accept)
        # The direction from the (possibly new) gradient and memory; -g scaled when the memory is
        # empty or cleared, or its direction does not descend (the memory is then dropped).
        self.rho.mul_((~clear).to(self.dtype))
        empty = self.rho.index_select(0, self.head)[0] == 0
        first = self._first_scale(self.g)
        self.gamma.copy_(torch.where(empty, first, self.gamma))
        order = (self.head - self.steps_back) % m
        d = lbfgs_direction(self.g, self.S, self.Y, self.rho, self.gamma, self.SY, order)
        descent = torch.dot(self.g, d) < 0
        self.d.copy_(torch.where(descent, d, -first * self.g))
        self.rho.mul_(descent.to(self.dtype))
        self.t.copy_(torch.where(clear, torch.ones_like(t), self.t))
        self.rejections.copy_(torch.where(clear, torch.zeros_like(self.rejections), self.rejections))
        self.trace.index_copy_(0, self.position, self.f[None])
        self.position.add_(1).remainder_(self.trace.shape[0])
        self.gmax.copy_(self.g.abs().max())


def optimize_drape_on_device(x0: torch.Tensor, inputs: EnergyInputs, energy_config: EnergyConfig, solver, *,
                             dynamic: bool = False, progress: bool = False, metrics=None):
    """`optimize_drape` with method "lbfgs" and the backtracking line search (see the module).

    Args and returns as `hairwarp.solvers.direct.optimize_drape`; `iterations` and
    `evaluations` both count energy evaluations, and the history holds the iterate at the end of
    every chunk (`solver.lbfgs_chunk` iterations, or `record_every` when recording).
    """
    from tqdm.auto import tqdm

    from hairwarp.solvers.direct import OptimizationResult

    chunk = solver.record_every or solver.lbfgs_chunk
    synchronize(x0.device)
    start = time.perf_counter()
    recording = 0.0

    def clock() -> float:
        return time.perf_counter() - start - recording

    on_cuda = x0.device.type == "cuda"
    fixed = x0[:, :, :NUM_FIXED_VERTICES].detach().clone()
    free_shape = x0[:, :, NUM_FIXED_VERTICES:].shape
    capacity = [None]  # the hair-hair pair buffer of the graph-safe evaluations (CUDA)
    pair_cache = None
    if not on_cuda and solver.pair_cache and energy_config.hair_hair_weight != 0.0:
        from hairwarp.ops.hair_hair_contact import HairHairPairCache

        pair_cache = HairHairPairCache()

    def assemble(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([fixed, x.reshape(free_shape)], dim=2)

    def energy(x: torch.Tensor, graph_safe: bool):
        xg = assemble(x.detach()).requires_grad_(True)
        with torch.enable_grad():
            result = total_energy(xg, inputs, energy_config, dynamic=dynamic, graph_safe=graph_safe,
                                  hair_hair_capacity=capacity[0] if graph_safe else None,
                                  hair_hair_cache=pair_cache)
            f = result.total.sum()
            (grad,) = torch.autograd.grad(f, xg)
        info = result.hair_hair_info
        return f.detach(), grad[:, :, NUM_FIXED_VERTICES:].reshape(-1), 0 if info is None else info.device_count

    lbfgs = DeviceLBFGS(energy, x0[:, :, NUM_FIXED_VERTICES:], solver, chunk=chunk, graph_safe=on_cuda)
    if on_cuda:
        first = lbfgs.first_count
        segments = x0.shape[0] * x0.shape[1] * (x0.shape[2] - 1)
        # Four times the start's pairs (at least two per segment): the first steps crumple the hair
        # and an overflow costs a chunk and a capture.
        capacity[0] = max(4 * (int(first) if isinstance(first, torch.Tensor) else first), 2 * segments, 1)
    initial = float(lbfgs.f)
    history: list[dict] = []
    captures = [0]  # graphs captured so far (a pair overflow captures again)

    def record(iteration: int, loss: float) -> None:
        nonlocal recording
        entry = {"iteration": iteration, "loss": loss, "time_s": clock(), "captures": captures[0]}
        if metrics is not None and solver.record_every:
            t0 = time.perf_counter()
            entry.update(metrics(assemble(lbfgs.x)))
            synchronize(x0.device)
            recording += time.perf_counter() - t0
        history.append(entry)

    record(0, initial)
    if not math.isfinite(initial):
        return OptimizationResult(positions=x0.detach().clone(), loss=initial, iterations=0,
                                  stop_reason=f"diverged: non-finite loss ({initial}) at the start",
                                  time_s=clock(), history=history, evaluations=1)

    graphs: dict = {}  # "one": the captured iteration

    def run(k: int) -> int:
        """K iterations, eager or replayed from a one-iteration graph on CUDA; returns how many ran
        (1 when this call captured the graph: a real first iteration warms it up).
        """
        lbfgs.start_chunk()
        if not on_cuda or not solver.cuda_graph:
            for _ in range(k):
                lbfgs.iterate()
            return k
        if "one" in graphs:
            for _ in range(k):  # queued at once: the host does not wait between replays
                graphs["one"]()
            return k
        from hairwarp.runtime import CapturedCall

        # One real iteration warms the allocator, cuBLAS and the kernels (it counts); the
        # capture itself runs nothing.
        with torch.cuda.device(lbfgs.device):  # CapturedCall without inputs captures on the current device
            graphs["one"] = CapturedCall(lbfgs.iterate, warmup=1)
        captures[0] += 1
        return 1

    best = initial
    since_best = 0
    done = 0
    stop_reason = "max_iterations"
    bar = tqdm(total=solver.max_iterations, desc="drape (lbfgs)", disable=not progress, leave=False)
    while done < solver.max_iterations:
        saved = [t.clone() for t in lbfgs.state()] if on_cuda else None
        k = run(min(chunk, solver.max_iterations - done))
        if on_cuda and int(lbfgs.pairs) > capacity[0]:
            # Pairs were dropped: back to the chunk's start, a larger buffer, a new capture.
            for tensor, value in zip(lbfgs.state(), saved):
                tensor.copy_(value)
            capacity[0] = 2 * int(lbfgs.pairs)
            graphs.clear()
            continue
        losses = lbfgs.trace[:k].tolist()
        for value in losses:
            if value < best - solver.min_decrease * abs(best):
                best, since_best = value, 0
            else:
                since_best += 1
        done += k
        bar.update(k)
        bar.set_postfix(loss=f"{losses[-1]:.4e}")
        record(done, losses[-1])
        if since_best >= solver.patience:
            stop_reason = "patience"
            break
        if float(lbfgs.gmax) <= solver.tolerance_grad:
            stop_reason = "tolerance"
            break
    bar.close()
    synchronize(x0.device)
    elapsed = clock()
    return OptimizationResult(positions=assemble(lbfgs.x).detach().clone(), loss=float(lbfgs.f),
                              iterations=done, stop_reason=stop_reason, time_s=elapsed, history=history,
                              evaluations=done + 1)
