"""The Method protocol: scene frames in; positions, timings and facts out.

A method proposes hair positions for a batch of frames of one scene (`Scene.frames(...)`,
which carries its scene: the networks read the hairstyle and the motion from it):

- `drape(frames) -> MethodResult`: each frame on its own (a static drape);
- `simulate(frames) -> MethodResult`: the frames as one motion, in time order (the default
  drapes every frame on its own, a chunk of frames at a time; the dynamic network and the
  physics reference carry state).

Positions are (B, M, N, 3) [m], detached, on the frames' device; `time_ms` is the wall time
per frame after a warm-up with the device synchronised (None for the rigid placement, which
costs nothing); `history` holds an iterative method's per-iteration record (its curve on the
speed/accuracy chart); `info` the method's facts (iterations, stop reason, ...).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from hairwarp.config import EnergyConfig

# Iteration cap of the converged reference drape (the energy gap's optimum).
REFERENCE_MAX_ITERATIONS = 5000
# Each extra start of the reference drape moves every vertex of the rigid placement by a seeded
# Gaussian of this standard deviation [m] (`MethodOptions.reference_starts`).
REFERENCE_START_NOISE = 1.0e-4
# Iterations of the untimed warm-up run before a timed optimization (compiles the kernels).
WARMUP_ITERATIONS = 2
# What a method is, for tables and charts.
KINDS = ("initial", "network", "optimizer", "reference", "composed")


@dataclass
class MethodOptions:
    """Settings every method factory receives (each method reads what concerns it).

    Attributes:
        energy_config: weights and constants of the energy (None: `EnergyConfig()`; the time
            step is set from the scene's frame rate where a method needs it).
        max_iterations: iteration cap of the optimizers (None: 2000, the solver's default).
        patience: optimizers stop after this many iterations without decrease (200, the paper).
        record_every: optimizers record penetration every this many iterations (0: never).
        reference_max_iterations: iteration cap of the converged reference drape.
        reference_starts: the reference drape is the lowest-energy of this many solves, one from
            the rigid placement and the others from it moved by `REFERENCE_START_NOISE` (seeded):
            dense hair settles in resting states some per cent apart from starts that differ by
            a tenth of a millimetre, or by the order of a GPU's sums (docs/network_diagnosis.md,
            "The yardstick moved"). 1: the rigid placement's alone.
        checkpoint: network methods: a checkpoint file written by `hairwarp train` (None: the
            one shipped with the package).
        refine: composed methods ("<network>+refine", "auto"): L-BFGS iterations of the same
            energy run from the network's output (0: the network alone).
        keep_out: network methods ("static", "dynamic", "quaffure"): their output shown through
            the inertial step's body pass (`hairwarp.methods.keep_out`): vertices inside the body
            or within 0.5 mm of it pushed out to 1 mm, the rest lengths kept. On by default since
            the eighteenth session: the shipped static network's drape may cut the body where the
            rigid placement does not, a default worse than doing nothing. One H100, full size:
            long straight hair grown on the body at rest 1.07 % inside, 3.38 x E* -> 0.00 %, 1.031
            x E*; long curly hair at nod 5.3 %, 23.1 x E* -> 0 %, 1.036 x E*; the pass took 4-27 ms
            a drape (docs/network_diagnosis.md, eighteenth session). False: the network's output.
        settle: the inertial step's settle at a motion's start, in physics steps
            (`InertialConfig.settle_steps`; None: the step's own, 20 for the shipped one; 0: none).
            It runs once a motion: 1.3-2.6 s on one H200 at 1 024 x 100, 35-39 s on the 2-core
            CPU at 600 x 100 (docs/network_diagnosis.md, T19).
        progress: show progress bars.
    """

    energy_config: EnergyConfig | None = None
    max_iterations: int | None = None
    patience: int = 200
    record_every: int = 0
    reference_max_iterations: int = REFERENCE_MAX_ITERATIONS
    reference_starts: int = 1
    checkpoint: str | None = None
    refine: int = 0
    keep_out: bool = True
    settle: int | None = None
    progress: bool = False

    def config(self) -> EnergyConfig:
        return self.energy_config or EnergyConfig()


@dataclass
class MethodResult:
    """What a method returns for a batch of frames (a drape) or a motion (a simulation).

    Attributes:
        positions: (B, M, N, 3) hair positions [m], detached, on the frames' device.
        time_ms: wall time per frame [ms] after a warm-up (device synchronised), None when the
            method costs nothing to time (the rigid placement).
        history: iterative methods: one record per iteration (iteration, loss = total energy of
            the batch, time_s since the start, and "penetration" when recorded); else empty.
        info: method facts (iterations, evaluations, stop_reason, ...).
    """

    positions: torch.Tensor
    time_ms: float | None
    history: list[dict] = field(default_factory=list)
    info: dict = field(default_factory=dict)


class Method:
    """Base class of every method (see the module docstring).

    Attributes:
        name: the registry name.
        kind: one of `KINDS`.
        options: the `MethodOptions` it was made with.
    """

    name = "method"
    kind = "network"

    def __init__(self, options: MethodOptions | None = None):
        self.options = options or MethodOptions()

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        """Hair positions for a batch of frames, each on its own.

        Args:
            frames: `Scene.frames(...)` of B frames.
            metrics: optional callable positions (B, M, N, 3) -> dict of floats, recorded in
                the history of iterative methods every `options.record_every` iterations.
        """
        raise NotImplementedError

    def simulate(self, frames) -> MethodResult:
        """Hair positions over a motion: `frames` are consecutive frames in time order.

        The default drapes every frame on its own (static methods have no dynamics), a chunk
        of frames at a time (`drape_in_chunks`).
        """
        return drape_in_chunks(self.drape, frames)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


def drape_in_chunks(drape: Callable, frames) -> MethodResult:
    """`drape` run on `frames.chunks()` one after the other, so that a few frames' bodies and
    drapes are held at a time, not a whole motion's; the results joined in frame order.

    A batch of at most `hairwarp.scene.scene.FRAME_CHUNK` frames is one chunk: `drape(frames)`
    itself. Otherwise the time per frame is over all chunks, each chunk's info is listed under
    `info["chunks"]` (with its "frames": [first, last] positions in the batch) and the history
    records carry their "chunk". A drape that couples the frames of a batch (one L-BFGS line
    search over their summed energy) couples those of a chunk only.
    """
    results, spans = [], []
    start = 0
    for chunk in frames.chunks():
        results.append(drape(chunk))
        spans.append((start, start + chunk.num_frames))
        start += chunk.num_frames
    if len(results) == 1:
        return results[0]
    times = [r.time_ms for r in results]
    time_ms = None if all(t is None for t in times) else \
        sum((t or 0.0) * (b - a) for t, (a, b) in zip(times, spans)) / start
    history = [dict(h, chunk=i) for i, r in enumerate(results) for h in r.history]
    info = {"chunks": [dict(r.info, frames=[a, b - 1]) for r, (a, b) in zip(results, spans)]}
    return MethodResult(positions=torch.cat([r.positions for r in results]), time_ms=time_ms, history=history,
                        info=info)
