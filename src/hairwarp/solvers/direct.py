"""Direct optimization of hair positions (HairFormer Section 4.3.2): the Adam and L-BFGS baselines.

Parameters are every hair vertex except the first two of each strand, initialised at the rigid
placement; the loss is the static total energy (Eq. 5), or Eq. 6 when previous states are given
(that is one implicit-Euler step: see `hairwarp.solvers.physics`). Optimization stops when the
loss has not decreased for `patience` iterations (200 in the paper), at `max_iterations`, or
when it diverges; a non-finite loss never comes back as a drape: the best finite iterate does,
with the reason recorded.

Notes on torch.optim.LBFGS as used here (one `step` per iteration, so that the stopping rule,
the history and the progress bar see every iteration):
- `max_eval` must be set: its default, `max_iter * 5 // 4`, is 1 for `max_iter=1`, which leaves
  the strong-Wolfe line search no evaluation beyond its first trial step (a rejected unit step
  then means no step at all, every iteration after).
- Each `step` re-evaluates the loss at the point the previous line search ended on; the closure
  caches the last few evaluations by exact parameter value, so that costs nothing.
- torch accepts a curvature pair only when y.s > 1e-10 (absolute): in metres with soft weights
  tiny steps may be skipped; the stiff default weights are far above it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch

from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs, total_energy
from hairwarp.runtime import synchronize


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
        lbfgs_line_search_evals: most energy evaluations of one strong-Wolfe line search.
        tolerance_grad: L-BFGS stops when the max gradient entry falls below this.
        record_every: record metrics in the history every this many iterations (0: never).
            Recording time is excluded from `time_s` and the history's times.
        lbfgs_restart: clear the L-BFGS memory after this many iterations without a decrease
            (0: never). A stale curvature pair after a contact switches on or off can leave the
            strong-Wolfe line search stepping nowhere; a fresh memory starts from the gradient.
        cuda_graph: on CUDA, evaluate the energy and its gradient by replaying a CUDA graph
            (`hairwarp.energy.CapturedEnergy`; captured again at the current point if the hair-hair
            pairs outgrow its buffer). No effect on the CPU.
        pair_cache: on the CPU, keep the hair-hair pair list across the energy evaluations
            (`hairwarp.ops.hair_hair_contact.HairHairPairCache`: the same energy and gradient,
            fewer grid queries). No effect on CUDA.
        lbfgs_line_search: "strong_wolfe": torch.optim.LBFGS's line search (reads the loss back
            at every trial step; its trial steps are unbounded: on CUDA 2 of 6 runs on Table 1
            tried steps of metres, 25-217 s before long segments walked only their tube,
            docs/contact.md 8). "backtracking": an
            Armijo backtracking search whose iterations never read the device
            (`hairwarp.solvers.device_lbfgs`: on CUDA one iteration is a CUDA graph replayed
            `lbfgs_chunk` times between host reads); there an iteration is one energy
            evaluation. "auto" (default): backtracking on CUDA with `cuda_graph` (full-size
            Table 1 to strong-Wolfe's accuracy in 0.37-0.46 s against 1.6-1.9 s on one H100,
            docs/contact.md 7-8), strong-Wolfe elsewhere (no host/device boundary to save on
            the CPU; the paper's baseline).
        lbfgs_max_step: "backtracking": the farthest a trial step moves any vertex [m].
        lbfgs_curvature_eps: "backtracking": a curvature pair enters the memory when s.y exceeds
            this times |s|^2 [J/m^2] (torch's strong-Wolfe search has its own rule: s.y > 1e-10).
        lbfgs_chunk: "backtracking": iterations per graph replay (the host reads the losses, the
            stopping rule's input, once per chunk; `record_every` replaces it when recording).
        divergence_factor: the run counts as diverged when the loss exceeds the initial loss
            by more than this factor times max(|initial loss|, 1) (an absurd step size sends
            the hair kilometres away long before float32 overflows).
    """

    method: str = "lbfgs"
    max_iterations: int = 2000
    patience: int = 200
    min_decrease: float = 1e-7
    adam_lr: float = 1e-3
    lbfgs_lr: float = 1.0
    lbfgs_history: int = 20
    lbfgs_line_search_evals: int = 25
    tolerance_grad: float = 1e-12
    record_every: int = 0
    divergence_factor: float = 1e6
    lbfgs_restart: int = 5
    cuda_graph: bool = True
    pair_cache: bool = True
    lbfgs_line_search: str = "auto"
    lbfgs_max_step: float = 0.02
    lbfgs_curvature_eps: float = 1e-10
    lbfgs_chunk: int = 10

    def __post_init__(self):
        if self.method not in ("adam", "lbfgs"):
            raise ValueError(f"method: expected 'adam' or 'lbfgs', got {self.method!r}")
        if self.lbfgs_line_search not in ("auto", "strong_wolfe", "backtracking"):
            raise ValueError("lbfgs_line_search: expected 'auto', 'strong_wolfe' or 'backtracking', "
                             f"got {self.lbfgs_line_search!r}")
        if self.lbfgs_chunk < 1:
            raise ValueError(f"lbfgs_chunk: expected >= 1, got {self.lbfgs_chunk}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations: expected >= 0, got {self.max_iterations}")
        if self.patience < 1:
            raise ValueError(f"patience: expected >= 1, got {self.patience}")
        if self.lbfgs_line_search_evals < 1:
            raise ValueError(f"lbfgs_line_search_evals: expected >= 1, got {self.lbfgs_line_search_evals}")
        if self.record_every < 0:
            raise ValueError(f"record_every: expected >= 0, got {self.record_every}")
        for name in ("adam_lr", "lbfgs_lr", "divergence_factor", "lbfgs_max_step"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a finite positive number, got {value}")


@dataclass
class OptimizationResult:
    """Outcome of a direct optimization.

    Attributes:
        positions: (B, M, N, 3) the best iterate [m] (detached).
        loss: the best total loss (sum over the batch).
        iterations: iterations run.
        stop_reason: "patience", "max_iterations", "tolerance", or "diverged: ...".
        time_s: wall time of the optimization loop [s] (device synchronised), without the
            time spent recording metrics.
        history: one dict per iteration: iteration, loss (of the iterate the step started
            from), time_s (loop time when that loss was known, recording excluded), and the
            metrics of that iterate when recorded. Iteration 0 is the start.
        evaluations: energy evaluations (gradient included) actually computed.
    """

    positions: torch.Tensor
    loss: float
    iterations: int
    stop_reason: str
    time_s: float
    history: list[dict] = field(default_factory=list)
    evaluations: int = 0


def line_search(solver: DirectOptimizationConfig, device: torch.device) -> str:
    """The L-BFGS line search `solver` runs on `device` ("auto" resolved)."""
    if solver.lbfgs_line_search != "auto":
        return solver.lbfgs_line_search
    return "backtracking" if device.type == "cuda" and solver.cuda_graph else "strong_wolfe"


# Evaluations the closure remembers (L-BFGS re-asks for the point its line search ended on).
_CACHE_SIZE = 4


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

    from hairwarp._validate import check_tensor

    energy_config = energy_config or EnergyConfig()
    solver = solver or DirectOptimizationConfig()
    check_tensor("x0", x0, shape=("...", None, None, 3), allow_empty=False)
    if x0.dim() == 3:
        x0 = x0.unsqueeze(0)
    if x0.dim() != 4:
        raise ValueError(f"x0: expected shape (B, M, N, 3) or (M, N, 3), got {tuple(x0.shape)}")
    if x0.shape[2] < 3:
        raise ValueError(f"x0: expected N >= 3 vertices per strand (0 and 1 are fixed), got {x0.shape[2]}")
    if solver.method == "lbfgs" and line_search(solver, x0.device) == "backtracking":
        return optimize_drape_on_device(x0, inputs, energy_config, solver, dynamic=dynamic, progress=progress,
                                        metrics=metrics)
    fixed = x0[:, :, :NUM_FIXED_VERTICES].detach()
    free = x0[:, :, NUM_FIXED_VERTICES:].detach().clone().requires_grad_(True)

    def assemble(free_part):
        return torch.cat([fixed, free_part], dim=2)

    if solver.method == "adam":
        opt = torch.optim.Adam([free], lr=solver.adam_lr)
    else:
        opt = torch.optim.LBFGS(
            [free],
            lr=solver.lbfgs_lr,
            max_iter=1,
            max_eval=1 + solver.lbfgs_line_search_evals,
            history_size=solver.lbfgs_history,
            tolerance_grad=solver.tolerance_grad,
            tolerance_change=0.0,
            line_search_fn="strong_wolfe",
        )

    captured = None
    if solver.cuda_graph and x0.device.type == "cuda":
        from hairwarp.energy import CapturedEnergy

        captured = CapturedEnergy(x0.detach(), inputs, energy_config, dynamic=dynamic)

    pair_cache = None
    if captured is None and solver.pair_cache and x0.device.type == "cpu" and energy_config.hair_hair_weight != 0.0:
        from hairwarp.ops.hair_hair_contact import HairHairPairCache

        pair_cache = HairHairPairCache()

    def energy_and_gradient(free_part):
        """(loss, d loss / d free_part) at free_part."""
        nonlocal captured
        if captured is None:
            part = free_part.detach().requires_grad_(True)
            loss = total_energy(assemble(part), inputs, energy_config, dynamic=dynamic,
                                hair_hair_cache=pair_cache).total.sum()
            (grad,) = torch.autograd.grad(loss, part)
            return loss.detach(), grad
        x = assemble(free_part.detach())
        energy, gradient = captured(x)
        if captured.overflowed():  # more hair-hair pairs than its buffer: capture again here
            captured = CapturedEnergy(x, inputs, energy_config, dynamic=dynamic)
            energy, gradient = captured(x)
        return energy.sum(), gradient[:, :, NUM_FIXED_VERTICES:]

    cache: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    use_cache = solver.method == "lbfgs"
    evaluations = 0

    def closure():
        nonlocal evaluations
        if use_cache:
            for point, value, grad in cache:
                if torch.equal(point, free):  # the very iterate a line search ended on
                    free.grad.copy_(grad)
                    return value
        loss, grad = energy_and_gradient(free)
        if free.grad is None:
            free.grad = grad.clone()
        else:
            free.grad.copy_(grad)
        evaluations += 1
        if use_cache:
            cache.append((free.detach().clone(), loss.detach(), free.grad.detach().clone()))
            if len(cache) > _CACHE_SIZE:
                cache.pop(0)
        return loss

    best_loss = math.inf
    best_free = free.detach().clone()
    initial_loss = None
    since_best = 0
    history: list[dict] = []
    stop_reason = "max_iterations"
    recording = 0.0  # seconds spent recording metrics, not counted as optimization time

    def record_metrics(record: dict, part: torch.Tensor, index: int) -> None:
        nonlocal recording
        if metrics is None or not solver.record_every or index % solver.record_every:
            return
        t0 = time.perf_counter()
        record.update(metrics(assemble(part)))
        synchronize(x0.device)
        recording += time.perf_counter() - t0

    synchronize(x0.device)
    start = time.perf_counter()

    def clock() -> float:
        return time.perf_counter() - start - recording

    bar = tqdm(total=solver.max_iterations, desc=f"drape ({solver.method})", disable=not progress, leave=False)
    iteration = 0
    end_of_last_step = 0.0
    diverged = False
    for iteration in range(1, solver.max_iterations + 1):
        current = free.detach().clone()  # the iterate this step starts from: its loss comes back
        try:
            loss = opt.step(closure)
        except (RuntimeError, ValueError) as exc:  # e.g. a line search that met a NaN
            stop_reason = f"diverged: {exc}"
            diverged = True
            break
        value = float(loss.detach())
        if not math.isfinite(value):
            stop_reason = f"diverged: non-finite loss ({value}) at iteration {iteration - 1}"
            diverged = True
            break
        if initial_loss is None:
            initial_loss = value
        if value < best_loss - solver.min_decrease * abs(best_loss if math.isfinite(best_loss) else value):
            best_loss = value
            best_free = current
            since_best = 0
        else:
            since_best += 1
        record = {"iteration": iteration - 1, "loss": value, "time_s": end_of_last_step}
        record_metrics(record, current, iteration - 1)
        history.append(record)
        end_of_last_step = clock()
        bar.update(1)
        bar.set_postfix(loss=f"{value:.4e}")
        if not bool(torch.isfinite(free).all()):
            stop_reason = f"diverged: non-finite positions after iteration {iteration}"
            diverged = True
            break
        if value > initial_loss + solver.divergence_factor * max(abs(initial_loss), 1.0):
            stop_reason = f"diverged: loss grew from {initial_loss:.6g} to {value:.6g}"
            diverged = True
            break
        if since_best >= solver.patience:
            stop_reason = "patience"
            break
        if solver.method == "lbfgs" and solver.lbfgs_restart and since_best and since_best % solver.lbfgs_restart == 0:
            opt.state.clear()
        if solver.method == "lbfgs":
            grad = free.grad
            if grad is not None and float(grad.abs().max()) <= solver.tolerance_grad:
                stop_reason = "tolerance"
                break
    bar.close()
    if iteration > 0 and not diverged:
        # The last step's result has not been scored yet (L-BFGS: a cache hit, no evaluation).
        value = float(closure().detach())
        if math.isfinite(value):
            record = {"iteration": iteration, "loss": value, "time_s": end_of_last_step}
            record_metrics(record, free.detach(), iteration)
            history.append(record)
            if value < best_loss:
                best_loss = value
                best_free = free.detach().clone()
    synchronize(x0.device)
    elapsed = clock()
    if not math.isfinite(best_loss):  # not even the start was finite: return the start
        best_free = x0[:, :, NUM_FIXED_VERTICES:].detach().clone()
        with torch.no_grad():
            best_loss = float(total_energy(x0, inputs, energy_config, dynamic=dynamic).total.sum())
    return OptimizationResult(
        positions=assemble(best_free).detach(),
        loss=best_loss,
        iterations=iteration,
        stop_reason=stop_reason,
        time_s=elapsed,
        history=history,
        evaluations=evaluations,
    )


def optimize_drape_on_device(x0: torch.Tensor, inputs: EnergyInputs, energy_config: EnergyConfig, solver, *,
                             dynamic: bool = False, progress: bool = False, metrics=None):
    """`optimize_drape` with method "lbfgs" and the backtracking line search
    (`hairwarp.solvers.device_lbfgs`).

    Args and returns as `hairwarp.solvers.direct.optimize_drape`; `iterations` and
    `evaluations` both count energy evaluations, and the history holds the iterate at the end of
    every chunk (`solver.lbfgs_chunk` iterations, or `record_every` when recording).
    """
    from tqdm.auto import tqdm

    from hairwarp.solvers.device_lbfgs import DeviceLBFGS

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
