"""A physics reference for dynamics: implicit Euler over a whole motion.

Each frame t solves one implicit-Euler step, the incremental potential
    x_t = argmin_x  L_inertia(x; x_{t-1}, x_{t-2}) + L_static(x; frame t),
i.e. the dynamic objective of Eq. 6 (inertia, Eq. 16, plus the static energy, Eq. 5) without the
network's functional regularization, minimised by L-BFGS with a strong-Wolfe line search until
the loss stops decreasing (relative change below `min_decrease` for `patience` iterations).
It is the same objective the dynamic network is trained on, solved per frame to convergence:
the ground truth that the dynamic network and any fast method are measured against.

The two fixed vertices of each strand follow the rigid placement of each frame; the moving
vertices start from the inertial prediction 2 x_{t-1} - x_{t-2}. Before the first frame the
hair rests at the static drape of frame 0 (x_{-1} = x_{-2} = x_0).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape


def reference_solver_config() -> DirectOptimizationConfig:
    """The tight L-BFGS settings of the reference (per implicit-Euler step)."""
    return DirectOptimizationConfig(method="lbfgs", max_iterations=1000, patience=25, min_decrease=1e-9,
                                    lbfgs_history=30)


@dataclass
class ReferenceResult:
    """A simulated motion.

    Attributes:
        positions: (T, B, M, N, 3) hair positions per frame [m].
        iterations: L-BFGS iterations per frame.
        stop_reasons: why each frame's solve stopped.
        time_s: total wall time [s].
    """

    positions: torch.Tensor
    iterations: list[int]
    stop_reasons: list[str]
    time_s: float


def simulate_reference(
    frame_inputs: Callable[[int], EnergyInputs],
    num_frames: int,
    energy_config: EnergyConfig | None = None,
    solver: DirectOptimizationConfig | None = None,
    *,
    initial: torch.Tensor | None = None,
    progress: bool = False,
) -> ReferenceResult:
    """Implicit-Euler simulation of the hair over `num_frames` frames.

    Args:
        frame_inputs: t -> EnergyInputs of frame t (rest lengths, rigid placement (B, M, N, 3),
            scalp normals, posed body); `prev`/`prev2` are filled in here.
        num_frames: T >= 1.
        energy_config: weights and constants; `time_step` is the frame spacing [s].
        solver: per-step solver settings (default `reference_solver_config()`).
        initial: (B, M, N, 3) state at frame 0; default: the static drape of frame 0.
        progress: show a progress bar over frames.

    Returns:
        ReferenceResult.
    """
    from tqdm.auto import tqdm

    if num_frames < 1:
        raise ValueError(f"num_frames: expected >= 1, got {num_frames}")
    energy_config = energy_config or EnergyConfig()
    solver = solver or reference_solver_config()
    start = time.perf_counter()
    inputs0 = frame_inputs(0)
    if initial is None:
        initial = optimize_drape(inputs0.rigid, inputs0, energy_config, solver).positions
    states = [initial.detach()]
    iterations, reasons = [0], ["initial"]
    prev2 = prev = states[0]
    for t in tqdm(range(1, num_frames), desc="reference", disable=not progress, leave=False):
        inputs = replace(frame_inputs(t), prev=prev, prev2=prev2)
        k = NUM_FIXED_VERTICES
        guess = torch.cat([inputs.rigid[:, :, :k], (2 * prev - prev2)[:, :, k:]], dim=2)
        result = optimize_drape(guess, inputs, energy_config, solver, dynamic=True)
        states.append(result.positions)
        iterations.append(result.iterations)
        reasons.append(result.stop_reason)
        prev2, prev = prev, result.positions
    return ReferenceResult(
        positions=torch.stack(states),
        iterations=iterations,
        stop_reasons=reasons,
        time_s=time.perf_counter() - start,
    )
