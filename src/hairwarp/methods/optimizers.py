"""The physics methods: the rigid placement, direct optimization (Adam, L-BFGS), the reference.

- "rigid": the rigid placement P_rigid (Eq. 1), the "Initial State" row of Table 1 (no time).
- "adam", "lbfgs": direct optimization of the static energy (Section 4.3.2,
  `hairwarp.solvers.direct`), started at the rigid placement; on a motion every frame is
  draped on its own (the paper's static baselines have no dynamics).
- "physics": the physics simulation (`hairwarp.solvers.physics`): implicit-Euler steps on a
  motion, the static optimum on a single frame, each solve stopped at a tolerance [m].
- "reference": L-BFGS run to convergence (patience 200, up to `reference_max_iterations`): the
  optimum E* of the energy gap; on a motion, the physics simulation at a tolerance 100x
  tighter, its time step the frame spacing.

They run on any body (they need no pose parameters), and take any start: `start` positions
(the composed methods start them from a network's output).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import torch

from hairwarp.methods.base import REFERENCE_START_NOISE, WARMUP_ITERATIONS, Method, MethodOptions, MethodResult
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape


def scene_energy_config(options: MethodOptions, frames):
    """The options' energy config with the time step set to the frames' scene frame spacing."""
    config = options.config()
    scene = getattr(frames, "scene", None)
    if scene is not None:
        config = config.replace(time_step=1.0 / float(scene.motion.fps))
    return config


def settle_drapes(frames, start: torch.Tensor, steps: int, momentum: float,
                  options: MethodOptions) -> tuple[torch.Tensor, float]:
    """Each frame of `frames` brought toward rest from `start` by `steps` damped physics steps
    with its pose held (`hairwarp.solvers.physics.settle_with_pose_held`, `momentum` the share
    of each step's velocity the next inherits): the physics' finish of a network's drape
    (docs/network_diagnosis.md, T19: the static network's drape of long hair 14.2 -> 3.5 mm
    from the physics' rest in 20 steps at 0.8, where L-BFGS on the static energy moved it 0.1 mm
    in 100 iterations).

    Args:
        frames: `SceneFrames` (B frames; their body, rigid placement and scalp normals).
        start: (B, M, N, 3) the drapes to settle [m].

    Returns:
        (B, M, N, 3) the settled drapes [m] in `start`'s dtype, and the wall time [s] (device
        synchronised).
    """
    from hairwarp.runtime import synchronize
    from hairwarp.solvers.physics import PhysicsConfig, settle_with_pose_held, settling_solver

    device = frames.rigid.positions.device
    physics = PhysicsConfig()
    synchronize(device)
    t0 = time.perf_counter()
    inputs = frames.inputs
    solver = settling_solver(inputs.rest_lengths, frames.rigid.positions, inputs.scalp_normals, inputs.body,
                             scene_energy_config(options, frames), physics)
    settle_with_pose_held(solver, start.detach().to(frames.rigid.positions.dtype), steps, physics.settle_tolerance,
                          momentum)
    settled = solver.prev.detach().clone().to(start.dtype)
    synchronize(device)
    return settled, time.perf_counter() - t0


class RigidMethod(Method):
    """The rigid placement of Eq. 1: Table 1's "Initial State"."""

    name = "rigid"
    kind = "initial"

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        return MethodResult(positions=frames.rigid.positions.detach(), time_ms=None)


class OptimizerMethod(Method):
    """Direct optimization of the static energy (Section 4.3.2) with Adam or L-BFGS.

    The whole batch is one optimization (the energy is a sum of independent per-frame terms,
    so its optimum is every frame's optimum); the time per drape is the run's time divided by
    the batch size, after an untimed warm-up of `WARMUP_ITERATIONS` iterations.
    """

    kind = "optimizer"

    def __init__(self, method: str, options: MethodOptions | None = None, **solver_changes):
        super().__init__(options)
        self.name = method
        o = self.options
        solver = DirectOptimizationConfig(method=method, patience=o.patience, record_every=o.record_every)
        if o.max_iterations is not None:
            solver = replace(solver, max_iterations=o.max_iterations)
        self.solver = replace(solver, **solver_changes)

    def drape(self, frames, *, metrics: Callable | None = None, start: torch.Tensor | None = None) -> MethodResult:
        """Optimize from `start` (B, M, N, 3) [m] (default: the rigid placement)."""
        x0 = (frames.rigid.positions if start is None else start).detach()
        config = scene_energy_config(self.options, frames)
        warm = replace(self.solver, max_iterations=min(WARMUP_ITERATIONS, self.solver.max_iterations), record_every=0)
        optimize_drape(x0, frames.inputs, config, warm)
        result = optimize_drape(x0, frames.inputs, config, self.solver, progress=self.options.progress,
                                metrics=metrics)
        batch = x0.shape[0]
        info = {"iterations": result.iterations, "evaluations": result.evaluations,
                "stop_reason": result.stop_reason, "loss": result.loss}
        return MethodResult(positions=result.positions, time_ms=result.time_s * 1e3 / batch,
                            history=result.history, info=info)


class PhysicsMethod(Method):
    """The physics simulation (`hairwarp.solvers.physics`): a motion by implicit-Euler steps on
    the device L-BFGS (variables scaled by the stiffness), a single frame draped as the static optimum, each solve
    stopped at `PhysicsConfig.tolerance` (a drape: `static_tolerance`).
    """

    name = "physics"
    kind = "reference"

    def __init__(self, options: MethodOptions | None = None, config=None):
        from hairwarp.solvers.physics import PhysicsConfig

        super().__init__(options)
        self.config = config or PhysicsConfig()

    def drape(self, frames, *, metrics: Callable | None = None, start: torch.Tensor | None = None) -> MethodResult:
        """The static optimum of each frame at rest (`hairwarp.solvers.physics.drape_at_rest`: a
        static solve from `start`, default the rigid placement, then settled with the pose held).
        """
        from hairwarp.runtime import synchronize
        from hairwarp.solvers.physics import PhysicsSolver, drape_at_rest, settling_solver

        x0 = (frames.rigid.positions if start is None else start).detach()
        config = scene_energy_config(self.options, frames)
        inputs = frames.inputs
        args = (inputs.rest_lengths, frames.rigid.positions, inputs.scalp_normals, inputs.body, config)
        static = PhysicsSolver(*args, self.config, dynamic=False)
        dynamic = settling_solver(*args, self.config) if self.config.settle_time > 0 else None
        synchronize(x0.device)
        t0 = time.perf_counter()
        drape = drape_at_rest(static, dynamic, x0, self.config)
        synchronize(x0.device)
        elapsed = time.perf_counter() - t0
        report = drape.report
        info = {"iterations": report.iterations, "stop_reason": report.stop_reason, "loss": report.energy,
                "tolerance_m": self.config.static_tolerance, "settle_steps": drape.settle_steps,
                "settled": drape.settled.tolist()}
        return MethodResult(positions=drape.positions, time_ms=elapsed * 1e3 / x0.shape[0], info=info)

    def simulate(self, frames) -> MethodResult:
        from hairwarp.solvers.physics import simulate_physics

        if frames.scene is None:
            raise ValueError("frames: a simulation needs frames made by Scene.frames (they carry their scene)")
        device = frames.rigid.positions.device
        result = simulate_physics(frames.scene, frames.frame_indices.tolist(), device=device,
                                  energy_config=scene_energy_config(self.options, frames), config=self.config,
                                  progress=self.options.progress)
        steps = result.frame_ms[1:] or result.frame_ms
        info = {"iterations": result.iterations, "stop_reasons": result.stop_reasons,
                "frame_ms": result.frame_ms, "static_drape_ms": result.frame_ms[0],
                "tolerance_m": self.config.tolerance}
        # Time per frame: the implicit-Euler steps (frame 0's static drape is the set-up's).
        return MethodResult(positions=result.positions[:, 0], time_ms=sum(steps) / len(steps), info=info)


class ReferenceMethod(PhysicsMethod):
    """The ground truth: the physics at a tolerance 100x tighter: the static optimum E* of a
    frame at rest (up to `reference_max_iterations` per static solve, settled with the pose held:
    `drape_at_rest`) and, on motions, the implicit-Euler simulation.

    The static optimum is solved on the rest lengths like every physics solve: on full-size
    Table 1 (one H200) that reached 0.75x the energy of 5 000 unconstrained L-BFGS iterations,
    the optimum used before (docs/results/compare_static_physics_h200.md).
    """

    name = "reference"

    def __init__(self, options: MethodOptions | None = None):
        from hairwarp.solvers.physics import PhysicsConfig

        options = options or MethodOptions()
        if isinstance(options.reference_starts, bool) or not isinstance(options.reference_starts, int) \
                or options.reference_starts < 1:
            raise ValueError(f"reference_starts: expected an integer >= 1, got {options.reference_starts!r}")
        tight = replace(PhysicsConfig().tight(), static_max_iterations=options.reference_max_iterations)
        super().__init__(options, tight)

    def drape(self, frames, *, metrics: Callable | None = None, start: torch.Tensor | None = None) -> MethodResult:
        """The static optimum of each frame: the lowest-energy of `reference_starts` solves (per
        frame), from `start` (default: the rigid placement) and from it moved by
        `REFERENCE_START_NOISE`, seeded by the start's index. info["start_energies"]: each
        solve's energy per frame [J]; info["best_start"]: the chosen start per frame.
        """
        from hairwarp.energy import total_energy

        x0 = (frames.rigid.positions if start is None else start).detach()
        config = scene_energy_config(self.options, frames)
        best, energies, time_ms = None, [], 0.0
        for k in range(self.options.reference_starts):
            moved = x0
            if k:
                generator = torch.Generator().manual_seed(k)
                noise = torch.randn(x0.shape, generator=generator, dtype=torch.float32)
                moved = x0 + REFERENCE_START_NOISE * noise.to(device=x0.device, dtype=x0.dtype)
            result = super().drape(frames, metrics=metrics, start=moved)
            with torch.no_grad():
                energy = total_energy(result.positions, frames.inputs, config).total.reshape(-1).double().cpu()
            energies.append(energy)
            time_ms += result.time_ms
            if best is None:
                best, best_energy = result, energy
                best.info["best_start"] = [0] * energy.numel()
                continue
            better = energy < best_energy
            if bool(better.any()):
                chosen = better.to(result.positions.device)
                best.positions = torch.where(chosen[:, None, None, None], result.positions, best.positions)
                best_energy = torch.where(better, energy, best_energy)
                best.info["best_start"] = [k if b else s for b, s in zip(better.tolist(), best.info["best_start"])]
        best.time_ms = time_ms
        best.info["start_energies"] = [e.tolist() for e in energies]
        return best
