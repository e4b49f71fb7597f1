"""Direct optimization of hair positions (HairFormer Section 4.3.2): the Adam and L-BFGS baselines.

Parameters are every hair vertex except the first two of each strand, initialised at the rigid
placement; the loss is the static total energy (Eq. 5), or Eq. 6 when previous states are given
(that is one implicit-Euler step: see `hairwarp.solvers.reference`). Optimization stops when the
loss has not decreased for `patience` iterations (200 in the paper), at `max_iterations`, or
when it diverges; a non-finite loss never comes back as a drape: the best finite iterate does,
with the reason recorded.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from hairwarp.config import EnergyConfig
from hairwarp.energy import EnergyInputs, total_energy


@dataclass
class DirectOptimizationConfig:
    """Settings of the direct-optimization baselines.

    Attributes:
        method: "adam" or "lbfgs".
        max_iterations: iteration cap (an L-BFGS iteration may evaluate the energy several
            times inside its line search).
        patience: stop after this many iterations without a decrease of the best loss (200 in
            the paper).
        min_decrease: a relative decrease smaller than this does not count as a decrease.
        adam_lr: Adam step size [m].
        lbfgs_lr: L-BFGS step scale (1 with the strong-Wolfe line search).
        lbfgs_history: L-BFGS memory.
        tolerance_grad: L-BFGS stops when the max gradient entry falls below this.
        record_every: record metrics in the history every this many iterations (0: never).
    """

    method: str = "lbfgs"
    max_iterations: int = 2000
    patience: int = 200
    min_decrease: float = 1e-7
    adam_lr: float = 1e-3
    lbfgs_lr: float = 1.0
    lbfgs_history: int = 20
    tolerance_grad: float = 1e-12
    record_every: int = 0

    def __post_init__(self):
        if self.method not in ("adam", "lbfgs"):
            raise ValueError(f"method: expected 'adam' or 'lbfgs', got {self.method!r}")
        if self.max_iterations < 0 or self.patience < 1:
            raise ValueError("max_iterations must be >= 0 and patience >= 1")


@dataclass
class OptimizationResult:
    """Outcome of a direct optimization.

    Attributes:
        positions: (B, M, N, 3) the best iterate [m] (detached).
        loss: the best total loss (sum over the batch).
        iterations: iterations run.
        stop_reason: "patience", "max_iterations", "tolerance", or "diverged: ...".
        time_s: wall time of the optimization loop [s] (device synchronised).
        history: one dict per iteration: iteration, loss, time_s (and metrics when recorded).
    """

    positions: torch.Tensor
    loss: float
    iterations: int
    stop_reason: str
    time_s: float
    history: list[dict] = field(default_factory=list)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def optimize_drape(
    x0: torch.Tensor,
    inputs: EnergyInputs,
    energy_config: EnergyConfig | None = None,
    solver: DirectOptimizationConfig | None = None,
    *,
    dynamic: bool = False,
    progress: bool = False,
    metrics=None,
) -> OptimizationResult:
    """Minimise the total energy over the moving hair vertices, starting from `x0`.

    Args:
        x0: (B, M, N, 3) initial positions [m] (the rigid placement for the Table 1 baselines).
        inputs: the energy's inputs (rest lengths, rigid placement, normals, body, states).
        energy_config: weights and constants.
        solver: method and stopping rule.
        dynamic: minimise Eq. 6 (with inertia) instead of Eq. 5.
        progress: show a progress bar.
        metrics: optional callable positions -> dict of floats, recorded every
            `solver.record_every` iterations.

    Returns:
        OptimizationResult.
    """
    from tqdm.auto import tqdm

    energy_config = energy_config or EnergyConfig()
    solver = solver or DirectOptimizationConfig()
    if x0.dim() == 3:
        x0 = x0.unsqueeze(0)
    fixed = x0[:, :, :2].detach()
    free = x0[:, :, 2:].detach().clone().requires_grad_(True)

    def assemble(free_part):
        return torch.cat([fixed, free_part], dim=2)

    def loss_fn():
        return total_energy(assemble(free), inputs, energy_config, dynamic=dynamic).total.sum()

    if solver.method == "adam":
        opt = torch.optim.Adam([free], lr=solver.adam_lr)
    else:
        opt = torch.optim.LBFGS(
            [free],
            lr=solver.lbfgs_lr,
            max_iter=1,
            history_size=solver.lbfgs_history,
            tolerance_grad=solver.tolerance_grad,
            tolerance_change=0.0,
            line_search_fn="strong_wolfe",
        )

    def closure():
        opt.zero_grad(set_to_none=False)
        loss = loss_fn()
        loss.backward()
        return loss

    best_loss = math.inf
    best_free = free.detach().clone()
    since_best = 0
    history: list[dict] = []
    stop_reason = "max_iterations"
    _sync(x0.device)
    start = time.perf_counter()
    bar = tqdm(total=solver.max_iterations, desc=f"drape ({solver.method})", disable=not progress, leave=False)
    iteration = 0
    for iteration in range(1, solver.max_iterations + 1):
        try:
            loss = opt.step(closure)
        except (RuntimeError, ValueError) as exc:  # e.g. a line search that met a NaN
            stop_reason = f"diverged: {exc}"
            break
        value = float(loss.detach())
        bad_state = not bool(torch.isfinite(free).all())
        if not math.isfinite(value) or bad_state:
            stop_reason = "diverged: non-finite loss or positions"
            break
        if value < best_loss - solver.min_decrease * abs(best_loss if math.isfinite(best_loss) else value):
            best_loss = value
            best_free.copy_(free.detach())
            since_best = 0
        else:
            since_best += 1
        record = {"iteration": iteration, "loss": value, "time_s": time.perf_counter() - start}
        if metrics is not None and solver.record_every and iteration % solver.record_every == 0:
            record.update(metrics(assemble(free.detach())))
        history.append(record)
        bar.update(1)
        bar.set_postfix(loss=f"{value:.4e}")
        if since_best >= solver.patience:
            stop_reason = "patience"
            break
        if solver.method == "lbfgs":
            grad = free.grad
            if grad is not None and float(grad.abs().max()) <= solver.tolerance_grad:
                stop_reason = "tolerance"
                break
    bar.close()
    _sync(x0.device)
    elapsed = time.perf_counter() - start
    if not math.isfinite(best_loss):  # not even the first step was finite: return the start
        best_free = x0[:, :, 2:].detach().clone()
        with torch.no_grad():
            best_loss = float(total_energy(x0, inputs, energy_config, dynamic=dynamic).total.sum())
    return OptimizationResult(
        positions=assemble(best_free).detach(),
        loss=best_loss,
        iterations=iteration,
        stop_reason=stop_reason,
        time_s=elapsed,
        history=history,
    )
