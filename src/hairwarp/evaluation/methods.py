"""The methods the harness compares, behind one interface, and their registry.

A method proposes hair positions for scene frames: `Method.drape(frames) -> DrapeResult`
(positions (B, M, N, 3), milliseconds per drape measured after a warm-up, the optimizer's
history), and for motions `Method.simulate(scene) -> SimulationResult` (positions
(T, M, N, 3), milliseconds per frame). Built in:

- "rigid": the rigid placement P_rigid (Eq. 1), the "Initial State" row of Table 1 (no time).
- "adam", "lbfgs": direct optimization of the static energy (Section 4.3.2,
  `hairwarp.solvers.direct`), started at the rigid placement; on a motion every frame is
  draped independently (static baselines have no dynamics).
- "reference": L-BFGS run to convergence (patience 200, up to `reference_max_iterations`): the
  optimum E* of the energy gap; on a motion, the implicit-Euler physics reference
  (`hairwarp.solvers.reference.simulate_reference`).

Other methods (the networks: static, dynamic, Quaffure) plug in with
`register_method(name, factory)`, where `factory(options: MethodOptions) -> Method`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch

from hairwarp.config import EnergyConfig
from hairwarp.scene.scene import SceneFrames
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

# Iteration cap of the converged reference drape (the energy gap's optimum).
REFERENCE_MAX_ITERATIONS = 5000
# Iterations of the untimed warm-up run before a timed optimization (compiles the kernels).
WARMUP_ITERATIONS = 2


@dataclass
class MethodOptions:
    """Settings every method factory receives (each method reads what concerns it).

    Attributes:
        energy_config: weights and constants of the energy (None: `EnergyConfig()`).
        max_iterations: iteration cap of the optimizers (None: 2000, the solver's default).
        patience: optimizers stop after this many iterations without decrease (200, the paper).
        record_every: optimizers record penetration every this many iterations (0: never).
        reference_max_iterations: iteration cap of the converged reference drape.
        progress: show progress bars.
    """

    energy_config: EnergyConfig | None = None
    max_iterations: int | None = None
    patience: int = 200
    record_every: int = 0
    reference_max_iterations: int = REFERENCE_MAX_ITERATIONS
    progress: bool = False

    def config(self) -> EnergyConfig:
        return self.energy_config or EnergyConfig()


@dataclass
class DrapeResult:
    """What a method returns for a batch of frames.

    Attributes:
        positions: (B, M, N, 3) hair positions [m], detached, on the frames' device.
        time_ms: wall time per drape [ms] after a warm-up (device synchronised), None when the
            method costs nothing to time (the rigid placement).
        history: optimizers: one record per iteration (iteration, loss = total energy of the
            batch, time_s, and "penetration" when recorded); empty for one-shot methods.
        info: method facts (iterations, evaluations, stop_reason, ...).
    """

    positions: torch.Tensor
    time_ms: float | None
    history: list[dict] = field(default_factory=list)
    info: dict = field(default_factory=dict)


@dataclass
class SimulationResult:
    """What a method returns for a motion.

    Attributes:
        positions: (T, M, N, 3) hair positions per frame [m].
        time_ms: wall time per frame [ms], None when not timed.
        info: method facts.
    """

    positions: torch.Tensor
    time_ms: float | None
    info: dict = field(default_factory=dict)


class Method:
    """Base class: a method proposes hair positions for scene frames.

    Subclasses implement `drape`; `simulate` defaults to draping every frame of the motion
    independently (one batch). `prepare(scene)` is called once per scene before any drape
    (networks encode the hairstyle there).

    Attributes:
        name: the registry name.
        kind: "initial" (no work), "one-shot" (a single evaluation, e.g. a network),
            "optimizer" (iterative: its history gives a curve), or "reference".
    """

    name = "method"
    kind = "one-shot"

    def __init__(self, options: MethodOptions | None = None):
        self.options = options or MethodOptions()

    def prepare(self, scene) -> None:
        """Per-scene set-up before `drape` (default: nothing)."""

    def drape(self, frames: SceneFrames, *, metrics: Callable | None = None) -> DrapeResult:
        """Hair positions for a batch of frames (see `DrapeResult`).

        Args:
            frames: `Scene.frames(...)` of B frames.
            metrics: optional callable positions (B, M, N, 3) -> dict of floats, recorded in
                the history of iterative methods every `options.record_every` iterations.
        """
        raise NotImplementedError

    def simulate(self, scene, *, frames: SceneFrames | None = None, device="cpu",
                 dtype=torch.float32) -> SimulationResult:
        """Hair positions over a whole motion (default: every frame draped on its own).

        Args:
            scene: a `ComparisonScene` (or anything with `frames(...)`).
            frames: the scene's frames, if already computed (all frames, in order).
            device, dtype: where to compute when `frames` is None.

        Returns:
            SimulationResult with positions (T, M, N, 3).
        """
        frames = frames if frames is not None else scene.frames(device=device, dtype=dtype)
        result = self.drape(frames)
        return SimulationResult(positions=result.positions, time_ms=result.time_ms, info=dict(result.info))


class RigidMethod(Method):
    """The rigid placement of Eq. 1: Table 1's "Initial State"."""

    name = "rigid"
    kind = "initial"

    def drape(self, frames: SceneFrames, *, metrics: Callable | None = None) -> DrapeResult:
        return DrapeResult(positions=frames.rigid.positions.detach(), time_ms=None)


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

    def drape(self, frames: SceneFrames, *, metrics: Callable | None = None) -> DrapeResult:
        x0 = frames.rigid.positions.detach()
        config = self.options.config()
        warm = replace(self.solver, max_iterations=min(WARMUP_ITERATIONS, self.solver.max_iterations), record_every=0)
        optimize_drape(x0, frames.inputs, config, warm)
        result = optimize_drape(x0, frames.inputs, config, self.solver, progress=self.options.progress,
                                metrics=metrics)
        batch = x0.shape[0]
        info = {"iterations": result.iterations, "evaluations": result.evaluations,
                "stop_reason": result.stop_reason, "loss": result.loss}
        return DrapeResult(positions=result.positions, time_ms=result.time_s * 1e3 / batch,
                           history=result.history, info=info)


class ReferenceMethod(OptimizerMethod):
    """The converged optimum (static) and the implicit-Euler physics reference (motions).

    Static: L-BFGS with the paper's patience (200 iterations without a relative decrease of
    1e-9) and an iteration cap of `options.reference_max_iterations`. Motion:
    `simulate_reference` with `reference_solver_config()` per implicit-Euler step, the time
    step set to the motion's frame spacing.
    """

    kind = "reference"

    def __init__(self, options: MethodOptions | None = None):
        options = options or MethodOptions()
        Method.__init__(self, options)
        self.name = "reference"
        self.solver = DirectOptimizationConfig(method="lbfgs", max_iterations=options.reference_max_iterations,
                                               patience=200, min_decrease=1e-9, lbfgs_history=30,
                                               record_every=options.record_every)

    def simulate(self, scene, *, frames: SceneFrames | None = None, device="cpu",
                 dtype=torch.float32) -> SimulationResult:
        from hairwarp.solvers.reference import simulate_reference

        if frames is not None:
            device, dtype = frames.rigid.positions.device, frames.rigid.positions.dtype
            indices = [int(i) for i in frames.frame_indices]
        else:
            indices = list(range(scene.num_frames))
        # One frame at a time (posing one frame costs ~50 ms on the CPU, little beside a solve).
        per_frame = [scene.frames([i], device=device, dtype=dtype) for i in indices]
        config = self.options.config()
        if hasattr(scene, "energy_config"):
            config = scene.energy_config(config)
        start = time.perf_counter()
        result = simulate_reference(lambda t: per_frame[t].inputs, len(per_frame), config,
                                    progress=self.options.progress)
        elapsed = time.perf_counter() - start
        positions = result.positions[:, 0]
        info = {"iterations": result.iterations, "stop_reasons": result.stop_reasons}
        return SimulationResult(positions=positions, time_ms=elapsed * 1e3 / len(per_frame), info=info)


_REGISTRY: dict[str, Callable[[MethodOptions], Method]] = {}


def register_method(name: str, factory: Callable[[MethodOptions], Method], *, overwrite: bool = False) -> None:
    """Make a method available to the harness and the `compare` command by name.

    Args:
        name: the method's name (letters, digits, "_" and "-").
        factory: `factory(options: MethodOptions) -> Method`.
        overwrite: replace an existing registration instead of raising.
    """
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "_-" for c in name):
        raise ValueError(f"name: expected a non-empty name of letters, digits, '_' or '-', got {name!r}")
    if not callable(factory):
        raise ValueError(f"factory: expected a callable, got {type(factory).__name__}")
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"name: method {name!r} is already registered (pass overwrite=True to replace it)")
    _REGISTRY[name] = factory


def list_methods() -> list[str]:
    """Names of the registered methods."""
    return list(_REGISTRY)


def make_method(name: str, options: MethodOptions | None = None) -> Method:
    """An instance of a registered method."""
    if name not in _REGISTRY:
        raise ValueError(f"name: unknown method {name!r}; registered: {list_methods()}")
    method = _REGISTRY[name](options or MethodOptions())
    if not isinstance(method, Method):
        raise ValueError(f"name: the factory of {name!r} returned {type(method).__name__}, not a Method")
    return method


register_method("rigid", RigidMethod)
register_method("adam", lambda options: OptimizerMethod("adam", options))
register_method("lbfgs", lambda options: OptimizerMethod("lbfgs", options))
register_method("reference", ReferenceMethod)
