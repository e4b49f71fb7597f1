"""The method "inertial": the static network's drape of every frame, carried in time by the learned
inertial step (`hairwarp.models.inertial`), so that the hair keeps a state of its own and swings.

- On a motion: E(t) = the static network's drape of frame t; x(t) = the step from x(t-1), x(t-2),
  starting at rest on the first frame's drape. The time per frame is the static network's plus
  the step's.
- The body pass (`keep_out_of_body`: vertices inside or within half of `KEEP_OUT_MARGIN` of
  the surface pushed out to it along the distance's gradient, the rest lengths restored by
  follow-the-leader) acts where the shipped step asks (`InertialConfig.keep_out_equilibrium`,
  `keep_out_state`, both on): on each chunk's equilibrium before the rollout reads it, and on
  each frame's state before the next frame's step reads it, on one body moved through the
  motion (`Scene.moving_body`). The hair then never swings deep into the body, where the pass
  had to push it out anew every frame and flung strands up to 17 cm a frame at full size
  (docs/network_diagnosis.md, T12). A step with neither passes the rollout's output, a chunk of
  frames at a time (`SceneFrames.chunks`).
- The settle (`InertialConfig.settle_steps`, 20 in the shipped step): at a motion's start the
  physics' own implicit-Euler steps, damped (`settle_momentum` 0.8), from the first frame's
  equilibrium with its pose held (`hairwarp.solvers.physics.settle_with_pose_held`); the
  settled drape's offset from that equilibrium, turned with the head, moves every frame's
  equilibrium, and the rollout starts at rest on the settled drape. The static network rests
  long hair a centimetre above the physics' (docs/network_diagnosis.md, T18, T19): on the six
  held-out motions at full size the mean distance to the physics fell on five (the arm raise
  15.2 -> 8.9 mm). It runs once a motion (1.3-2.6 s on one H200 at full size, 21 s at 256 x 100
  on the 2-core CPU), reported as `info["settle_ms"]` and shared out over the frames' time;
  `MethodOptions.settle` (`--settle K`) overrides the count.
- On independent poses (a drape): the step at rest is its equilibrium, so this is the static
  network's drape (no settle).

The step's checkpoint is `MethodOptions.checkpoint` (a file written by `InertialTrainer`), else
the shipped `hairformer_inertial.pt`: the chain step (`InertialConfig(coupling="chain")`) with
constants, not trained weights: G = 0.995, beta = 0.97 damping the velocity relative to the head's,
half a hanging strand's tension, the equilibrium's offset from the rigid placement followed at
0.12 m/s at most (the static network's drape can jump between frames, which flung strands out),
and a bending term of 3e4 (`InertialConfig.bending`: the strand keeps its shape while it swings,
which lets a weak pull swing without overshooting), and dynamic follow-the-leader's velocity
correction at 0.9 (`InertialConfig.projection_damping`, the thirty-second session: without it the
step amplifies a kick on long curly hair, docs/network_diagnosis.md, T23). Curled strands (rest
curliness past 0.1, all of the long curls) keep none of the bending and take G = 0.99
(`InertialConfig.curl_bending`, `curl_gate`, the thirty-third session: a curl then bounces as the
physics' does; on the held-out curly walk the swing correlation 0.46 -> 0.60, amplitude 0.67 ->
0.84, T24). The rest is the setting of a 48-point grid that
meets the most goals (swing correlation and amplitude, worst strands no farther from the physics
than the rigid placement's) on eight full-size training clips (`tools/inertial_sweep.py`; training
by rollouts never moved the step at full size). On the held-out motions at full size it meets 13
of the 15 swing goals (correlation, amplitude, distance) where the twentieth session's constants
met 11, the nineteenth session's 9 and the first ones 6 (docs/network_diagnosis.md, "Twenty-first
session"). With the body pass on its state and equilibrium, on the six held-out motions re-run
against the physics of the twenty-third session's body it meets 12 of the 18 (the pass after the
rollout 13: the curly walk's amplitude is lost), and its largest move a frame falls from 33-137 mm
to 12-73 mm (T12). The static network is the shipped one. The step is trained
at one frame rate (`InertialConfig.fps`, 60 1/s): a motion at another rate is refused with the
resampling to use.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import replace

import torch

from hairwarp.methods.base import Method, MethodOptions, MethodResult, drape_in_chunks
from hairwarp.methods.keep_out import KEEP_OUT_EAGER_CALLS, KEEP_OUT_MARGIN, keep_out_of_body
from hairwarp.methods.networks import NetworkMethod, shipped_checkpoint
from hairwarp.models.inertial import RolloutCarry
from hairwarp.ops import hair_body_signed_distance_and_normal
from hairwarp.runtime import timed

INERTIAL_CHECKPOINT = "hairformer_inertial.pt"
# Relative difference of frame rates the step accepts as its own.
FPS_TOLERANCE = 1e-3

_LOADED: dict[tuple, object] = {}


def load_inertial_step(checkpoint: str | None, device: torch.device):
    """The `InertialStep` of `checkpoint` (None: the shipped file), cached per device.

    Raises:
        ValueError: no file shipped, an unreadable file, or one holding another kind of model.
    """
    from hairwarp.models.checkpoint import load_checkpoint
    from hairwarp.models.inertial import InertialStep

    path = checkpoint if checkpoint is not None else shipped_checkpoint(INERTIAL_CHECKPOINT)
    if path is None:
        raise ValueError("checkpoint: no inertial step is shipped with this build; train one "
                         "(`python tools/train_inertial.py`) and pass it as the checkpoint")
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint: no such file {path!r}")
    key = (os.path.abspath(path), str(device))
    if key not in _LOADED:
        try:
            model = load_checkpoint(path, device=device).model
        except Exception as exc:  # a foreign or truncated file: one line saying which and why
            first = (str(exc).strip() or type(exc).__name__).splitlines()[0]
            raise ValueError(f"checkpoint: cannot load {path!r} ({first})") from None
        if not isinstance(model, InertialStep):
            raise ValueError(f"checkpoint: {path} holds a {type(model).__name__}, not an inertial step")
        _LOADED[key] = model
    return _LOADED[key]


class InertialMethod(Method):
    """The static network plus the learned inertial step (module docstring)."""

    name = "inertial"
    kind = "network"

    def __init__(self, options: MethodOptions | None = None):
        super().__init__(options)
        # The equilibrium: the shipped static network (the checkpoint option is the step's), as
        # the network returns it: the step's own body pass follows the rollout.
        self.equilibrium = NetworkMethod("static", MethodOptions(keep_out=False))

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        # The step at rest is its equilibrium: the static network's drape, through the body pass
        # as every frame of a motion is.
        out = NetworkMethod("static", replace(self.equilibrium.options, keep_out=True)).drape(frames)
        out.info["equilibrium"] = "static"
        return out

    def step_for(self, frames):
        """The step for `frames`, after checking that it and the static network can run them.

        Raises:
            ValueError: no usable checkpoint, a motion at another frame rate than the step's, or
                frames the static network refuses (a body without SMPL pose parameters).
        """
        self.equilibrium.simulator(frames)
        step = load_inertial_step(self.options.checkpoint, frames.rigid.positions.device)
        fps = float(frames.scene.motion.fps)
        if abs(fps - step.config.fps) > FPS_TOLERANCE * step.config.fps:
            raise ValueError(f"scene: the inertial step is trained at {step.config.fps:g} frames/s and this motion "
                             f"runs at {fps:g}; resample it (hairwarp.scene.motion.resample_motion(motion, "
                             f"{step.config.fps:g}))")
        return step

    def simulate(self, frames) -> MethodResult:
        device = frames.rigid.positions.device
        step = self.step_for(frames)
        # A chunk of frames at a time (`drape_in_chunks`): the equilibrium, the step's rollout
        # going on from the chunk before (`RolloutCarry`) and the body pass, all on the chunk's one
        # body (a whole motion's rollout before its pass built every body twice; the demo's scene
        # on the 2-core CPU 18 -> 11 s, the same positions, twenty-second session).
        carry = RolloutCarry()
        warmed = []
        # The state's pass moves one body through the whole motion (built here, not timed, as the
        # chunks' bodies are not): a body built per chunk cost the H200 60-120 ms a frame.
        moving = _moving_body(frames) if step.config.keep_out_state else None
        # The settle (`InertialConfig.settle_steps`): the physics' offset from the first frame's
        # equilibrium, in the head's frame; timed, and shared out over the motion's frames.
        steps = self.settle_steps(step)
        settle, settle_ms = self._settled_offset(frames, step.config, steps) if steps else (None, 0.0)

        def run(chunk, target, carry):
            rigid = chunk.rigid.positions
            if step.config.keep_out_equilibrium:
                # Pulled to the drape as the static method shows it, not to vertices inside the body.
                target = keep_out_of_body(target, rigid, chunk.body_mesh)
            hold = None
            if step.config.body_hold:
                # Where the equilibrium lies on the body, and the body's outward direction there:
                # the chain is held along it (`InertialConfig.body_hold`); queries capped at the distance.
                hold = hair_body_signed_distance_and_normal(target, chunk.body_mesh,
                                                            max_distance=step.config.body_hold_distance)
            if step.config.keep_out_state:
                # The pass inside the rollout: each frame pushed before the next step reads it.
                return step.rollout(target, rigid, project=_FrameBodyPass(chunk, moving), carry=carry, hold=hold)
            return keep_out_of_body(step.rollout(target, rigid, carry=carry, hold=hold), rigid, chunk.body_mesh)

        def piece(chunk) -> MethodResult:
            equilibrium = self.equilibrium.drape(chunk)
            target = equilibrium.positions.to(chunk.rigid.positions.dtype)
            if settle is not None:
                rotations = chunk.posed.head_transform[:, :3, :3].to(target.dtype)
                target = target + torch.einsum("tij,mnj->tmni", rotations, settle)
            chunk.body_mesh.prepare()  # built by the equilibrium's contact features, or now: not timed
            # The first chunk warms up on its first frame (its own body) and a copy of the carry:
            # the same kernels. Every chunk run twice cost the 2-core CPU 2x the time, and a
            # motion whose body is built already (the demo's, after the physics) is one chunk.
            # With the state's pass, the warm-up runs as many frames as the pass takes before it
            # replays from CUDA graphs (`KEEP_OUT_EAGER_CALLS`): the one capture a motion's body
            # costs is set-up, as a network's compilation is, not a frame's time.
            first = min(chunk.num_frames, KEEP_OUT_EAGER_CALLS + 1 if moving is not None else 1)
            with torch.no_grad():
                positions, seconds = timed(lambda: run(chunk, target, carry), device, warmup=0 if warmed else 1,
                                           warmup_fn=lambda: run(chunk.select(slice(0, first)), target[:first],
                                                                 carry.copy()))
            warmed.append(True)
            step_ms = seconds * 1e3 / chunk.num_frames
            return MethodResult(positions=positions.detach(), time_ms=step_ms + (equilibrium.time_ms or 0.0),
                                info={**equilibrium.info, "equilibrium": "static", "step_ms": step_ms})

        out = drape_in_chunks(piece, frames)
        if settle is not None:
            out.time_ms = (out.time_ms or 0.0) + settle_ms / frames.num_frames
            out.info["settle_ms"] = settle_ms
        if "chunks" in out.info:
            chunks = out.info["chunks"]
            spans = [c["frames"][1] - c["frames"][0] + 1 for c in chunks]
            out.info["step_ms"] = sum(c["step_ms"] * n for c, n in zip(chunks, spans)) / sum(spans)
            out.info["equilibrium"] = "static"
        return out

    def settle_steps(self, step) -> int:
        """The settle's physics steps: `MethodOptions.settle`, else the step's `settle_steps`.

        Raises:
            ValueError: a `settle` option that is not an int >= 0.
        """
        settle = self.options.settle
        if settle is None:
            return step.config.settle_steps
        if not isinstance(settle, int) or isinstance(settle, bool) or settle < 0:
            raise ValueError(f"settle: expected None or an int >= 0 (physics steps), got {settle!r}")
        return settle

    def _settled_offset(self, frames, config, steps: int) -> tuple[torch.Tensor, float]:
        """(M, N, 3) the settled drape's offset from the first frame's equilibrium [m] in the head's
        rest frame, R_0^T (S_0 - E_0) (R_0 the rotation of the first frame's M_head), and the
        settle's wall time [ms] (the equilibrium's drape included).
        """
        from hairwarp.methods.optimizers import settle_drapes
        from hairwarp.runtime import synchronize

        first = frames.select(slice(0, 1))
        synchronize(first.rigid.positions.device)
        start = time.perf_counter()
        equilibrium = self.equilibrium.drape(first).positions.detach().to(first.rigid.positions.dtype)
        settled, _ = settle_drapes(first, equilibrium, steps, config.settle_momentum, self.options)
        seconds = time.perf_counter() - start
        rotation = first.posed.head_transform[0, :3, :3].to(equilibrium.dtype)
        return (settled - equilibrium)[0] @ rotation, seconds * 1e3


def _moving_body(frames):
    """`Scene.moving_body` of `frames`, its trees built (not timed)."""
    body = frames.scene.moving_body(frames.frame_indices, device=frames.rigid.positions.device,
                                    dtype=frames.posed.vertices.dtype)
    return body.prepare()


class _FrameBodyPass:
    """`keep_out_of_body` of frame t's state (`InertialStep.rollout(project=...)`) on `body` (the
    motion's `Scene.moving_body`) moved to frame t in place: the state pushed frame by frame on
    bodies of each frame's own (`SceneFrames.select`) cost a body built a frame, ~110 ms of ~200
    on the 2-core CPU (256 x 100, the demo's scene).
    """

    def __init__(self, frames, body):
        self._frames, self._body = frames, body

    def __call__(self, t: int, x: torch.Tensor) -> torch.Tensor:
        self._body.update(self._frames.posed.vertices[t:t + 1])
        return keep_out_of_body(x[None], self._frames.rigid.positions[t:t + 1], self._body)[0]


__all__ = ["INERTIAL_CHECKPOINT", "InertialMethod", "KEEP_OUT_MARGIN", "keep_out_of_body", "load_inertial_step"]
