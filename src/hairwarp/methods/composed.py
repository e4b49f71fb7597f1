"""Composed methods: a network's output finished by the physics, and "auto".

- "<network>+refine" (`RefinedMethod`): the network's positions, then `options.refine`
  L-BFGS iterations of the same static energy started from them (neural start, physics
  finish). With `refine` 0 it is the network alone; L-BFGS keeps its best iterate, so the
  refined energy is never above the network's.
- "<method>+settle" (`SettledMethod`): the method's positions, then `options.settle` (default
  `SETTLE_STEPS`) damped physics steps with each frame's pose held (`settle_drapes`): a
  physics finish that brings a drape to where the physics rests it (the static network's drape
  of long hair 14.2 -> 3.5 mm from the physics' rest in 20 steps at 256 x 100, where 100 L-BFGS
  iterations of "+refine" moved it 0.1 mm; docs/network_diagnosis.md, T18, T19). On a motion
  every frame is settled on its own, as "+refine" refines it: a drape of every pose.
- "auto" (`AutoMethod`): what the command line and `hairwarp.drape` use by default. A drape
  runs the static network with `AUTO_REFINE` refine iterations. A motion runs the physics
  simulation (`physics`) where it meets its speed goal (`physics_is_interactive`: on a CPU up to
  256 x 100 vertices, 1.5 s a frame, measured 0.97 s on whiplash and 1.38 s on torso_bend on the
  2-core CPU; no GPU size meets its 30 ms yet): no network meets the fidelity goals on motions (docs/network_diagnosis.md),
  the physics is what the others are measured against. Elsewhere a motion runs the inertial
  step (`hairwarp.methods.inertial`: the static network's drapes carried in time by the learned
  step, nearer the physics than the paper's dynamic network on all six held-out motions,
  docs/network_diagnosis.md, eighteenth session), or the paper's dynamic network where the step
  cannot run (a motion at another frame rate), with `AUTO_REFINE_MOTION` refine iterations (none
  by default: every frame of a motion is one more drape to refine, tens of seconds an iteration
  for a second of 1024 x 100 hair on a CPU; pass `refine=K` to ask for them). It never leaves a
  frame with more vertices inside the body, or a higher energy, than the rigid placement: such a
  frame is draped again by L-BFGS from the rigid placement (together with the other such frames
  of its chunk, `SceneFrames.chunks`: a motion's frames are checked and redone `FRAME_CHUNK` at a
  time), and should that still be worse, the rigid placement is kept. Without a usable network
  (none shipped, a body without SMPL pose parameters) it is L-BFGS alone (on a motion, a chunk at
  a time).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch

from hairwarp.methods.base import Method, MethodOptions, MethodResult
from hairwarp.methods.optimizers import OptimizerMethod
from hairwarp.models.inertial import InertialConfig

# Damped physics steps "<method>+settle" runs after the method (when `options.settle` is None),
# and the share of each step's velocity the next inherits: the shipped inertial step's settle
# (`InertialConfig.settle_steps`, `settle_momentum`; docs/network_diagnosis.md, T19).
SETTLE_STEPS = 20
SETTLE_MOMENTUM = InertialConfig.settle_momentum
# L-BFGS iterations "auto" runs after the network (when `options.refine` is 0).
AUTO_REFINE = 20
# ... and after the network on a motion (frames worse than the rigid placement are
# still redone, see `AutoMethod`).
AUTO_REFINE_MOTION = 0
# L-BFGS iterations of a frame that "auto" redoes from the rigid placement (at least).
AUTO_FALLBACK_ITERATIONS = 50
# L-BFGS iterations "auto" gives a drape without a network (when `options.max_iterations` is None).
AUTO_LBFGS_ITERATIONS = 200
# Hair vertices (strands x vertices) up to which the physics simulation meets its speed goal, per
# device type: 1.5 s a frame at 256 x 100 on the 2-core CPU (measured on 12 frames, 1.14 s on
# whiplash, 1.37 s on torso_bend: `benchmarks/bm_physics.py --device cpu --strand-stride 4
# --frames 12`, docs/physics.md section 2). The H100's goal, 30 ms a frame at 1024 x 100, is not
# met (92-101 ms on whiplash, 60-63 on torso_bend), so no CUDA entry.
PHYSICS_INTERACTIVE_VERTICES = {"cpu": 256 * 100}


def physics_is_interactive(frames) -> bool:
    """Whether the physics simulation of `frames`' hair meets its speed goal on their device
    (`PHYSICS_INTERACTIVE_VERTICES`).
    """
    _, strands, vertices, _ = frames.rigid.positions.shape
    limit = PHYSICS_INTERACTIVE_VERTICES.get(frames.rigid.positions.device.type, 0)
    return strands * vertices <= limit


def refine_options(options: MethodOptions, iterations: int) -> MethodOptions:
    """The options of the refine step: L-BFGS capped at `iterations`."""
    return replace(options, max_iterations=int(iterations))


def _refine(base: MethodResult, frames, options: MethodOptions, iterations: int,
            metrics: Callable | None = None) -> MethodResult:
    """`iterations` L-BFGS iterations from `base.positions`; times and histories added up."""
    if iterations <= 0:
        return base
    lbfgs = OptimizerMethod("lbfgs", refine_options(options, iterations))
    result = lbfgs.drape(frames, metrics=metrics, start=base.positions)
    batch = base.positions.shape[0]
    base_ms = base.time_ms or 0.0
    # The refine curve starts where the network ended: shift its clock by the network's time.
    history = [dict(h, time_s=h["time_s"] + base_ms * batch / 1e3) for h in result.history]
    info = dict(base.info, iterations=result.info["iterations"], stop_reason=result.info["stop_reason"],
                refine_iterations=result.info["iterations"], network_ms=base.time_ms, refine_ms=result.time_ms,
                loss=result.info["loss"])
    return MethodResult(positions=result.positions, time_ms=base_ms + result.time_ms, history=history, info=info)


class RefinedMethod(Method):
    """A method followed by `options.refine` L-BFGS iterations of the same energy."""

    kind = "composed"

    def __init__(self, base: Method, options: MethodOptions | None = None):
        super().__init__(options or base.options)
        if self.options.refine < 0:
            raise ValueError(f"refine: expected an integer >= 0, got {self.options.refine}")
        self.base = base
        self.name = f"{base.name}+refine"

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        return _refine(self.base.drape(frames), frames, self.options, self.options.refine, metrics)

    def simulate(self, frames) -> MethodResult:
        return _refine(self.base.simulate(frames), frames, self.options, self.options.refine)


class SettledMethod(Method):
    """A method followed by `options.settle` (default `SETTLE_STEPS`) damped physics steps per
    frame, its pose held (module docstring).
    """

    kind = "composed"

    def __init__(self, base: Method, options: MethodOptions | None = None):
        super().__init__(options or base.options)
        steps = self.options.settle
        if steps is not None and (not isinstance(steps, int) or isinstance(steps, bool) or steps < 0):
            raise ValueError(f"settle: expected None or an int >= 0 (physics steps), got {steps!r}")
        self.steps = SETTLE_STEPS if steps is None else steps
        self.base = base
        self.name = f"{base.name}+settle"

    def _settle(self, base: MethodResult, frames) -> MethodResult:
        from hairwarp.methods.optimizers import settle_drapes

        if self.steps == 0:
            return base
        parts, seconds, first = [], 0.0, 0
        for chunk in frames.chunks():
            rows = slice(first, first + chunk.num_frames)
            first = rows.stop
            settled, elapsed = settle_drapes(chunk, base.positions[rows], self.steps, SETTLE_MOMENTUM, self.options)
            parts.append(settled)
            seconds += elapsed
        settle_ms = seconds * 1e3 / max(first, 1)
        info = dict(base.info, settle_steps=self.steps, network_ms=base.time_ms, settle_ms=settle_ms)
        return MethodResult(positions=torch.cat(parts), time_ms=(base.time_ms or 0.0) + settle_ms, info=info)

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        return self._settle(self.base.drape(frames), frames)

    def simulate(self, frames) -> MethodResult:
        return self._settle(self.base.simulate(frames), frames)


class AutoMethod(Method):
    """The default: a refined network, never worse than the rigid placement (module docstring)."""

    name = "auto"
    kind = "composed"

    def _network(self, name: str, frames) -> Method | None:
        from hairwarp.methods.inertial import InertialMethod
        from hairwarp.methods.networks import NetworkMethod

        if name == "inertial":  # the motion's network; the paper's dynamic one where the step cannot run
            network = InertialMethod(self.options)
            try:
                network.step_for(frames)
            except ValueError:
                return self._network("dynamic", frames)
            return network
        network = NetworkMethod(name, self.options)
        try:
            network.simulator(frames)
        except ValueError:
            return None  # no checkpoint, a non-SMPL body: physics alone
        return network

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        return self._run(frames, "static", metrics)

    def simulate(self, frames) -> MethodResult:
        if frames.scene is not None and physics_is_interactive(frames):
            from hairwarp.methods.optimizers import PhysicsMethod

            result = PhysicsMethod(self.options).simulate(frames)
            strands, vertices = frames.rigid.positions.shape[1:3]
            chosen = f"physics ({strands} x {vertices} hair meets its speed goal on this device)"
            return MethodResult(positions=result.positions, time_ms=result.time_ms, history=result.history,
                                info=dict(result.info, chosen=chosen, fallback_frames=[]))
        return self._run(frames, "inertial", None)

    def _run(self, frames, network_name: str, metrics) -> MethodResult:
        motion = network_name != "static"
        refine = self.options.refine or (AUTO_REFINE_MOTION if motion else AUTO_REFINE)
        network = self._network(network_name, frames)
        if network is None:
            iterations = self.options.max_iterations or AUTO_LBFGS_ITERATIONS
            lbfgs = OptimizerMethod("lbfgs", refine_options(self.options, iterations))
            result = lbfgs.simulate(frames) if motion else lbfgs.drape(frames, metrics=metrics)
            chosen = f"lbfgs ({iterations} iterations; no usable network)"
        else:
            base = network.simulate(frames) if motion else network.drape(frames)
            result = _refine(base, frames, self.options, refine, metrics)
            chosen = f"{network.name} + {refine} L-BFGS iterations" if refine else network.name
        return self._never_worse_than_rigid(result, frames, max(refine, AUTO_FALLBACK_ITERATIONS), chosen)

    def _never_worse_than_rigid(self, result: MethodResult, frames, iterations: int, chosen: str) -> MethodResult:
        """`result` with every frame that has more vertices inside the body, or a higher energy,
        than the rigid placement draped again by `iterations` L-BFGS iterations from the rigid
        placement (the rigid placement kept where that is still worse). Runs over
        `frames.chunks()`: the frames redone together are those of one chunk.
        """
        from hairwarp.energy import total_energy
        from hairwarp.metrics import penetration_percent

        config = self.options.config()
        lbfgs = OptimizerMethod("lbfgs", refine_options(self.options, iterations))

        def penetration_and_energy(x, sub_frames):
            with torch.no_grad():
                energy = total_energy(x, sub_frames.inputs, config).total
            return penetration_percent(x, sub_frames.body_mesh), energy

        positions, fallback, extra_ms = result.positions, [], 0.0
        start = 0
        for chunk in frames.chunks():
            rows = slice(start, start + chunk.num_frames)
            start = rows.stop
            rigid = chunk.rigid.positions
            pen_rigid, energy_rigid = penetration_and_energy(rigid, chunk)
            pen, energy = penetration_and_energy(positions[rows], chunk)
            worse = (pen > pen_rigid) | (energy > energy_rigid)
            if not bool(worse.any()):
                continue
            idx = torch.nonzero(worse)[:, 0]
            sub = chunk.select(idx.cpu())
            again = lbfgs.drape(sub)
            pen, energy = penetration_and_energy(again.positions, sub)
            still = (pen > pen_rigid[idx]) | (energy > energy_rigid[idx])
            if positions is result.positions:
                positions = positions.clone()
            positions[rows.start + idx] = torch.where(still[:, None, None, None], rigid[idx], again.positions)
            fallback += (rows.start + idx).tolist()
            extra_ms += (again.time_ms or 0.0) * len(idx)
        info = dict(result.info, chosen=chosen, fallback_frames=fallback)
        if not fallback:
            return MethodResult(positions=positions, time_ms=result.time_ms, history=result.history, info=info)
        return MethodResult(positions=positions, time_ms=(result.time_ms or 0.0) + extra_ms / start,
                            history=result.history, info=info)
