"""Composed methods: a network's output finished by the physics, and "auto".

- "<network>+refine" (`RefinedMethod`): the network's positions, then `options.refine`
  L-BFGS iterations of the same static energy started from them (neural start, physics
  finish). With `refine` 0 it is the network alone; L-BFGS keeps its best iterate, so the
  refined energy is never above the network's.
- "auto" (`AutoMethod`): what the command line and `hairwarp.drape` use by default. A drape
  runs the static network with `AUTO_REFINE` refine iterations; a motion the dynamic network
  with `AUTO_REFINE_MOTION` (none by default: every frame of a motion is one more drape to
  refine, tens of seconds an iteration for a second of 1024 x 100 hair on a CPU; pass
  `refine=K` to ask for them). It never leaves a frame with more vertices inside the body, or a
  higher energy, than the rigid placement: such a frame is draped again by L-BFGS from the
  rigid placement, and should that still be worse, the rigid placement is kept. Without a usable network (none
  shipped, a body without SMPL pose parameters, another vertex count) it is L-BFGS alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch

from hairwarp.methods.base import Method, MethodOptions, MethodResult
from hairwarp.methods.optimizers import OptimizerMethod

# L-BFGS iterations "auto" runs after the network (when `options.refine` is 0).
AUTO_REFINE = 20
# ... and after the dynamic network on a motion (frames worse than the rigid placement are
# still redone, see `AutoMethod`).
AUTO_REFINE_MOTION = 0
# L-BFGS iterations of a frame that "auto" redoes from the rigid placement (at least).
AUTO_FALLBACK_ITERATIONS = 50
# L-BFGS iterations "auto" gives a drape without a network (when `options.max_iterations` is None).
AUTO_LBFGS_ITERATIONS = 200


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


class AutoMethod(Method):
    """The default: a refined network, never worse than the rigid placement (module docstring)."""

    name = "auto"
    kind = "composed"

    def _network(self, name: str, frames) -> Method | None:
        from hairwarp.methods.networks import NetworkMethod

        network = NetworkMethod(name, self.options)
        try:
            network.simulator(frames)
        except ValueError:
            return None  # no checkpoint, a non-SMPL body, another vertex count: physics alone
        return network

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        return self._run(frames, "static", metrics)

    def simulate(self, frames) -> MethodResult:
        return self._run(frames, "dynamic", None)

    def _run(self, frames, network_name: str, metrics) -> MethodResult:
        from hairwarp.energy import total_energy
        from hairwarp.metrics import penetration_percent

        config = self.options.config()

        def worse_than_rigid(x, sub_frames, pen_rigid, energy_rigid):
            with torch.no_grad():
                energy = total_energy(x, sub_frames.inputs, config).total
            return (penetration_percent(x, sub_frames.body_mesh) > pen_rigid) | (energy > energy_rigid)

        refine = self.options.refine or (AUTO_REFINE_MOTION if network_name == "dynamic" else AUTO_REFINE)
        network = self._network(network_name, frames)
        if network is None:
            iterations = self.options.max_iterations or AUTO_LBFGS_ITERATIONS
            result = OptimizerMethod("lbfgs", refine_options(self.options, iterations)).drape(frames, metrics=metrics)
            chosen = f"lbfgs ({iterations} iterations; no usable network)"
        else:
            base = network.simulate(frames) if network_name == "dynamic" else network.drape(frames)
            result = _refine(base, frames, self.options, refine, metrics)
            chosen = f"{network_name} + {refine} L-BFGS iterations" if refine else network_name
        rigid = frames.rigid.positions
        pen_rigid = penetration_percent(rigid, frames.body_mesh)
        with torch.no_grad():
            energy_rigid = total_energy(rigid, frames.inputs, config).total
        worse = worse_than_rigid(result.positions, frames, pen_rigid, energy_rigid)
        fallback = []
        if bool(worse.any()):
            idx = torch.nonzero(worse)[:, 0]
            sub = _select_frames(frames, idx)
            again = OptimizerMethod("lbfgs", refine_options(self.options, max(refine, AUTO_FALLBACK_ITERATIONS))).drape(sub)
            still = worse_than_rigid(again.positions, sub, pen_rigid[idx], energy_rigid[idx])
            positions = result.positions.clone()
            positions[idx] = torch.where(still[:, None, None, None], rigid[idx], again.positions)
            fallback = idx.tolist()
            extra_ms = (again.time_ms or 0.0) * len(idx) / rigid.shape[0]
            result = MethodResult(positions=positions, time_ms=(result.time_ms or 0.0) + extra_ms,
                                  history=result.history, info=dict(result.info))
        result.info.update(chosen=chosen, fallback_frames=fallback)
        return result


def _select_frames(frames, idx: torch.Tensor):
    """The frames `idx` of a batch (their own body meshes, inputs and rigid placement)."""
    return frames.scene.frames(frames.frame_indices[idx.cpu()], device=frames.rigid.positions.device,
                               dtype=frames.rigid.positions.dtype)
