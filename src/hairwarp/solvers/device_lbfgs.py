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
seven kernels on CUDA (`hairwarp.kernels.device_lbfgs`): four passes over the n-vectors, each
summing in blocks what the next decision needs, and three single-thread kernels for the
decisions and the m x m solves. Before, the n-sized products went through torch (cuBLAS), ~25
kernels an iteration, ~285 us of a 0.97 ms iteration at full size on one H100 (a 3 x n by n x 3
Gram product alone 71 us; docs/physics.md, section 2). On the CPU the passes stay torch
products (`DeviceLBFGS(passes=...)`).

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


# Threads a block of the reductions on CUDA, and the blocks per memory row (each thread then
# strides over ~n / (chunks * block) components; 1 024 x 98 x 3 = 301 056 of them at full size).
_REDUCE_BLOCK_DIM = 256
_ROW_CHUNKS = 64
_POINT_CHUNKS = 128


class DeviceLBFGS:
    """The solver's state and one iteration of it (Warp kernels and the caller's energy; nothing
    read back).

    The memory is a ring buffer: a new pair overwrites the oldest row (no (m, n) shift), the
    products s_i . y_j are kept as pairs enter, and a cleared memory is rho = 0 (the rows stay,
    ignored). An iteration is seven kernels besides the energy (`hairwarp.kernels.device_lbfgs`);
    the direction it leaves for the next trial is `direction()`.

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
        passes: who runs the four passes over the n-vectors: "warp" (kernels with block sums,
            the CUDA default) or "torch" (matrix products on all cores, the CPU default: Warp's
            CPU kernels run on one thread, 7.6 ms an iteration against ~2 ms at 256 x 100). The
            decisions are the same single-thread kernels either way; "torch" reads them back, so
            it runs on the CPU only.

    A caller that knows its problem's scales passes scaled variables instead of a preconditioner
    (`hairwarp.solvers.physics`: x = S z): L-BFGS on z is L-BFGS with H0 = gamma S^2, gamma still
    fitted to the newest pair.
    """

    def __init__(self, energy, x0: torch.Tensor, solver, *, chunk: int, point_size: int = 3,
                 graph_safe: bool = False, passes: str | None = None):
        self.energy, self.solver, self.point_size, self.graph_safe = energy, solver, point_size, graph_safe
        if passes not in (None, "warp", "torch"):
            raise ValueError(f"passes: expected None, 'warp' or 'torch', got {passes!r}")
        self.passes = passes or ("warp" if x0.device.type == "cuda" else "torch")
        if self.passes == "torch" and x0.device.type != "cpu":
            raise ValueError(f"passes: 'torch' runs on the CPU only (it reads the decisions back), x0 is on {x0.device}")
        self.device, self.dtype = x0.device, x0.dtype
        x = x0.detach().reshape(-1).clone()
        n, m = x.numel(), solver.lbfgs_history
        if n % point_size:
            raise ValueError(f"x0: expected a multiple of point_size={point_size} components, got {n}")
        zeros = dict(device=self.device, dtype=self.dtype)
        wide = dict(device=self.device, dtype=torch.float64)
        index = dict(device=self.device, dtype=torch.int64)
        self.x = x
        f, g, self.first_count = energy(x, False)
        self.f, self.g = f.detach().reshape(()).clone(), g.detach().reshape(-1).clone()
        self.S = torch.zeros(m, n, **zeros)
        self.Y = torch.zeros(m, n, **zeros)
        self.rho = torch.zeros(m, **zeros)
        self.SY = torch.zeros(m, m, **wide)  # s_i . y_j, kept as rows enter
        self.head = torch.full((1,), m - 1, **index)  # the newest row
        self.gamma = torch.zeros((), **zeros)
        self.t = torch.ones((), **zeros)
        self.rejections = torch.zeros((), device=self.device, dtype=torch.int32)
        self.trace = torch.zeros(chunk, **zeros)
        self.position = torch.zeros((1,), **index)  # where the next loss goes in trace
        self.pairs = torch.zeros((), **index)  # largest pair count met
        self.gmax = torch.zeros((), **zeros)  # |g|_inf
        self.g_norm1 = torch.zeros(1, **wide)  # |g|_1
        # The next direction's makings (`direction()`): the memory's candidate, its product with
        # g and the largest squared point norms of it and of g (`kernels.device_lbfgs`'s
        # CANDIDATE_* slots).
        self.candidate = torch.zeros(n, **zeros)
        self.candidate_sums = torch.zeros(3, **wide)
        self.d = torch.zeros(n, **zeros)  # the last trial's direction
        # Scratch of an iteration (`iterate`).
        self.trial = torch.zeros(n, **zeros)
        self.r = torch.zeros(n, **zeros)
        self.t_trial = torch.ones((), **zeros)
        self.flags = torch.zeros(2, device=self.device, dtype=torch.int32)  # accepted, stored
        self.products = torch.zeros(4 * (m + 2), **wide)
        self.row_sums = torch.zeros(m, **wide)
        self.a = torch.zeros(m, **wide)
        self.c = torch.zeros(m, **wide)
        self.a_rows = torch.zeros(m, **zeros)
        self.c_rows = torch.zeros(m, **zeros)
        on_cuda = self.device.type == "cuda"
        self._block = _REDUCE_BLOCK_DIM  # one thread a block on the CPU (`_warp.launch`)
        threads = _REDUCE_BLOCK_DIM if on_cuda else 1
        self._row_chunks = max(1, min(_ROW_CHUNKS, -(-n // (threads * 8)))) if on_cuda else 1
        self._point_chunks = max(1, min(_POINT_CHUNKS, -(-(n // point_size) // (threads * 4)))) if on_cuda else 1
        # Warp views of the state and scratch, made once (the tensors keep their addresses).
        self._warp = {name: _warp.as_warp(getattr(self, name)) for name in (
            "x", "f", "g", "d", "t", "S", "Y", "rho", "SY", "gamma", "head", "rejections", "trace", "position",
            "gmax", "g_norm1", "candidate", "candidate_sums", "trial", "r", "t_trial", "flags", "products",
            "row_sums", "a", "c", "a_rows", "c_rows")}
        self._first_step(self._gradient_norms())

    def restart_at(self, x: torch.Tensor, *, keep_memory: bool = False) -> None:
        """Start again from `x` (n,), in place and graph-safe: evaluates the energy there (f, g),
        the first direction, t = 1, no rejections; the memory cleared unless `keep_memory` (its
        curvature pairs then serve the new start, as a warm start across similar problems).
        """
        self.x.copy_(x.reshape(-1))
        if not keep_memory:
            # The ring starts again where a new solver's does: the sums over its rows run in row
            # order, so a solve from a reused solver then repeats a fresh one's bit for bit.
            self.rho.zero_()
            self.head.fill_(self.rho.shape[0] - 1)
        self._first_step(self._evaluate())

    def refresh(self) -> None:
        """The energy at the iterate again (f, g; the caller changed the energy a little: a pair
        list built anew) and the memory's direction from the new g, t = 1 (graph-safe). The
        memory stays: its pairs span the change.
        """
        first = self._evaluate()
        m = self.rho.shape[0]
        order = (self.head - torch.arange(m, device=self.device)) % m
        # An empty memory gives -gamma g: gamma then the first step's scale, as `iterate` has it.
        # (index_select, not rho[head[0]]: indexing by a 0-d device tensor reads it back, which a
        # CUDA graph's capture forbids.)
        newest = torch.index_select(self.rho, 0, self.head).reshape(())
        self.gamma.copy_(torch.where(newest == 0, first, self.gamma))
        # The textbook two-loop recursion, newest row first (rows with rho = 0 add nothing).
        S, Y, rho = (torch.index_select(t, 0, order) for t in (self.S, self.Y, self.rho))
        q = self.g.clone()
        a = []
        for k in range(m):
            a.append(rho[k] * torch.dot(S[k], q))
            q.sub_(a[k] * Y[k])
        q.mul_(self.gamma)
        for k in reversed(range(m)):
            q.add_((a[k] - rho[k] * torch.dot(Y[k], q)) * S[k])
        torch.neg(q, out=self.candidate)
        self._candidate_sums()

    def _evaluate(self) -> torch.Tensor:
        """f, g at x, t = 1, no rejections (graph-safe); returns `_gradient_norms()`."""
        f, g, count = self.energy(self.x, self.graph_safe)
        if isinstance(count, torch.Tensor):
            self.pairs.copy_(torch.maximum(self.pairs, count.reshape(()).to(torch.int64)))
        self.f.copy_(f.reshape(()))
        self.g.copy_(g.reshape(-1))
        self.t.fill_(1.0)
        self.rejections.zero_()
        return self._gradient_norms()

    def _gradient_norms(self) -> torch.Tensor:
        """|g|_1 and |g|_inf into the state; returns the first step's scale min(1, 1/|g|_1) ()
        in the state's dtype (graph-safe).
        """
        self.g_norm1.copy_(self.g.to(torch.float64).abs().sum().reshape(1))
        torch.linalg.vector_norm(self.g, float("inf"), out=self.gmax)
        return torch.clamp(1.0 / self.g_norm1.clamp_min(1e-30), max=1.0).to(self.dtype).reshape(())

    def _first_step(self, first: torch.Tensor) -> None:
        """The next trial's direction -first g (torch's first step), as a candidate that descends
        (so a kept memory stays, `restart_at`); gamma = first.
        """
        self.gamma.copy_(first)
        torch.mul(self.g, -first, out=self.candidate)
        self.d.copy_(self.candidate)
        self._candidate_sums()

    def _candidate_sums(self) -> None:
        """`candidate_sums` of the candidate and g: g . candidate, the largest squared point norms
        of each (what `lbfgs_candidate_kernel` sums; graph-safe).
        """
        both = torch.stack([self.candidate, self.g]).to(torch.float64)
        points = both.view(2, -1, self.point_size).square().sum(dim=2).amax(dim=1)
        self.candidate_sums.copy_(torch.cat([torch.dot(both[1], both[0]).reshape(1), points]))

    def direction(self) -> torch.Tensor:
        """(n,) the direction the next trial takes: the memory's candidate where it descends,
        else -min(1, 1/|g|_1) g (what `lbfgs_trial_kernel` chooses; a new tensor).
        """
        first = torch.clamp(1.0 / self.g_norm1.clamp_min(1e-30), max=1.0).to(self.dtype)
        return torch.where(self.candidate_sums[0] < 0, self.candidate, -first * self.g)

    def state(self) -> list[torch.Tensor]:
        """The tensors an iteration changes (saved and restored around a chunk)."""
        return [self.x, self.f, self.g, self.d, self.t, self.S, self.Y, self.rho, self.SY, self.head, self.gamma,
                self.rejections, self.gmax, self.g_norm1, self.candidate, self.candidate_sums]

    def start_chunk(self) -> None:
        """The next iteration's loss goes to trace[0]."""
        self.position.zero_()

    def iterate(self) -> None:
        """One trial step and the masked update; appends the new loss to `trace`.

        Seven kernels besides the energy: four passes over the n-vectors, each with the block
        sums the next decision needs, and three single-thread kernels for the decisions and the
        memory's m x m solves (`hairwarp.kernels.device_lbfgs`).
        """
        s_cfg = self.solver
        m, n = self.rho.shape[0], self.x.numel()
        w = self._warp
        device = _warp.warp_device(self.device)
        block = self._block
        with _warp.launch_scope(self.device):
            _warp.launch(lbfgs_kernels.lbfgs_trial_kernel, dim=n,
                         inputs=[w["x"], w["g"], w["candidate"], w["candidate_sums"], w["g_norm1"], w["t"],
                                 wp.float64(s_cfg.lbfgs_max_step), m],
                         outputs=[w["d"], w["trial"], w["t_trial"], w["rho"], w["products"]], device=device)
        f_t, g_t, count = self.energy(self.trial, self.graph_safe)
        if isinstance(count, torch.Tensor):
            self.pairs.copy_(torch.maximum(self.pairs, count.reshape(()).to(torch.int64)))
        f_wp = _warp.as_warp(f_t.reshape(1))
        g_t = g_t.reshape(-1)
        g_wp = _warp.as_warp(g_t)
        by_warp = self.passes == "warp"
        with _warp.launch_scope(self.device):
            if by_warp:
                _warp.launch(lbfgs_kernels.lbfgs_products_kernel, dim=(m + 2) * self._row_chunks,
                             inputs=[w["g"], g_wp, w["d"], w["S"], w["Y"], n, m, self._row_chunks],
                             outputs=[w["products"]], device=device, block_dim=block)
            else:
                self._products(g_t)
            _warp.launch(lbfgs_kernels.lbfgs_accept_kernel, dim=1,
                         inputs=[f_wp, w["products"], w["t_trial"], m, wp.float64(ARMIJO_C1),
                                 wp.float64(s_cfg.lbfgs_curvature_eps), int(s_cfg.lbfgs_restart or 0),
                                 w["f"], w["t"], w["rho"], w["gamma"], w["head"], w["rejections"], w["trace"],
                                 w["position"], w["SY"], w["g_norm1"], w["gmax"]],
                         outputs=[w["flags"], w["a"], w["a_rows"], w["row_sums"], w["candidate_sums"]], device=device)
            if by_warp:
                _warp.launch(lbfgs_kernels.lbfgs_update_kernel, dim=n,
                             inputs=[w["flags"], w["t_trial"], w["d"], w["trial"], g_wp, w["head"], w["a_rows"],
                                     w["gamma"], n, m, w["x"], w["g"], w["S"], w["Y"]],
                             outputs=[w["r"]], device=device)
                _warp.launch(lbfgs_kernels.lbfgs_rows_dot_kernel, dim=m * self._row_chunks,
                             inputs=[w["Y"], w["r"], n, self._row_chunks], outputs=[w["row_sums"]], device=device,
                             block_dim=block)
            else:
                self._update(g_t)
            _warp.launch(lbfgs_kernels.lbfgs_second_loop_kernel, dim=1,
                         inputs=[w["a"], w["row_sums"], w["rho"], w["SY"], w["head"], m],
                         outputs=[w["c_rows"], w["c"]], device=device)
            if by_warp:
                _warp.launch(lbfgs_kernels.lbfgs_candidate_kernel, dim=self._point_chunks,
                             inputs=[w["r"], w["g"], w["S"], w["c_rows"], n, m, self.point_size, self._point_chunks],
                             outputs=[w["candidate"], w["candidate_sums"]], device=device, block_dim=block)
            else:
                self._candidate()

    # -- the passes over n as torch ops (`passes="torch"`): the same sums as the kernels ----------
    def _products(self, g_t: torch.Tensor) -> None:
        """`lbfgs_products_kernel`'s sums (its docstring gives the layout)."""
        m = self.rho.shape[0]
        y = g_t - self.g
        rows = torch.cat([(self.Y @ self.d)[:, None], self.S @ torch.stack([y, g_t, self.g], dim=1)], dim=1)
        vectors = torch.stack([self.g, y, self.d, g_t])
        gram = vectors @ torch.stack([self.d, y]).T  # g.d, y.d, d.d, g_t.d in column 0; y.y in column 1
        trial = torch.stack([gram[0, 0], gram[1, 0], gram[1, 1], gram[2, 0]])
        gradient = torch.stack([gram[3, 0], g_t.abs().sum(), g_t.abs().max(), torch.zeros_like(gram[0, 0])])
        self.products.view(m + 2, 4).copy_(torch.cat([rows, trial[None], gradient[None]]))

    def _update(self, g_t: torch.Tensor) -> None:
        """`lbfgs_update_kernel` and `lbfgs_rows_dot_kernel` (the flags read on the host: CPU only)."""
        accepted, stored = self.flags.tolist()
        if stored:
            row = int(self.head)
            torch.mul(self.d, self.t_trial, out=self.S[row])
            torch.sub(g_t, self.g, out=self.Y[row])
        if accepted:
            self.x.copy_(self.trial)
            self.g.copy_(g_t)
        torch.addmv(self.g, self.Y.T, self.a_rows, alpha=-1.0, out=self.r)
        self.r.mul_(self.gamma)
        self.row_sums.copy_(self.Y @ self.r)

    def _candidate(self) -> None:
        """`lbfgs_candidate_kernel`: the candidate, its product with g, the largest squared point norms."""
        torch.addmv(self.r, self.S.T, self.c_rows, out=self.candidate)
        self.candidate.neg_()
        self._candidate_sums()
