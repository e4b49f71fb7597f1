"""The trained networks as harness methods: "static", "dynamic", "quaffure".

Importing this module registers them in `hairwarp.evaluation.methods`. Each loads a checkpoint
written by `hairwarp train` (or shipped in `hairwarp/assets`), reads the scene's hairstyle as its
latent z = encode(strands) once per scene (`prepare`), and times the network forward plus the
deformation lookup and taper of Eq. 2 applied to the rigid placement, after one warm-up call,
device synchronised: the "ms/drape" of Table 1 (the rigid placement, Eq. 1, is shared by every
method and not counted).

- "static": the static network (Section 3.2), one drape per frame.
- "dynamic": the dynamic network (Section 3.3). On a motion: the whole sequence frame by frame
  with the GRU state. On a static scene (independent poses): each pose held still for
  `HOLD_FRAMES` frames from a zero GRU state, the last frame kept; the time is per frame of
  those sequences, as the network runs once per frame.
- "quaffure": the adapted Quaffure decoder (Section 4.3.1), one drape per frame.

Checkpoints: `set_checkpoint(name, path)` (the command line's `--checkpoint`), else the shipped
file: the dynamic checkpoint holds its frozen static network, so "static" falls back to it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import torch

from hairwarp.bench.timing import synchronize
from hairwarp.evaluation.methods import DrapeResult, Method, MethodOptions, SimulationResult, register_method
from hairwarp.scene.scene import SceneFrames

# Frames a static pose is held for when the dynamic network drapes it (settles the GRU state).
HOLD_FRAMES = 10

_CHECKPOINTS: dict[str, str] = {}
_LOADED: dict[tuple, object] = {}


def set_checkpoint(name: str, path: str | os.PathLike | None) -> None:
    """Use `path` for network method `name` ("static", "dynamic", "quaffure"); None: the shipped one."""
    if name not in ("static", "dynamic", "quaffure"):
        raise ValueError(f"name: expected 'static', 'dynamic' or 'quaffure', got {name!r}")
    if path is None:
        _CHECKPOINTS.pop(name, None)
        return
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint: no such file {path}")
    _CHECKPOINTS[name] = path


def _simulator(name: str, device: torch.device):
    """A `HairFormerSimulator` for network method `name` on `device` (cached)."""
    from hairwarp.inference import DYNAMIC_CHECKPOINT, STATIC_CHECKPOINT, HairFormerSimulator, shipped_checkpoint
    from hairwarp.models.checkpoint import load_checkpoint

    path = _CHECKPOINTS.get(name)
    if path is None:
        shipped = {"static": [STATIC_CHECKPOINT, DYNAMIC_CHECKPOINT], "dynamic": [DYNAMIC_CHECKPOINT],
                   "quaffure": ["hairformer_quaffure.pt"]}[name]
        path = next((p for p in map(shipped_checkpoint, shipped) if p is not None), None)
        if path is None:
            raise ValueError(f"method: no {name} checkpoint is shipped with this build; train one "
                             f"(`hairwarp train {name}`) and pass it as the checkpoint")
    key = (name, path, str(device))
    if key not in _LOADED:
        model = load_checkpoint(path, device=device).model
        kind = type(model).__name__
        if name == "dynamic":
            if kind != "DynamicNetwork":
                raise ValueError(f"checkpoint: {path} holds a {kind}, not a dynamic network")
            sim = HairFormerSimulator(model.static, model)
        elif name == "static":
            static = model.static if kind == "DynamicNetwork" else model
            if type(static).__name__ != "StaticNetwork":
                raise ValueError(f"checkpoint: {path} holds a {kind}, not a static network")
            sim = HairFormerSimulator(static)
        else:
            if kind != "QuaffureNetwork":
                raise ValueError(f"checkpoint: {path} holds a {kind}, not a Quaffure network")
            sim = HairFormerSimulator(model)
        _LOADED[key] = sim
    return _LOADED[key]


def _timed(fn: Callable[[], torch.Tensor], device: torch.device) -> tuple[torch.Tensor, float]:
    """(result, seconds) of `fn()` after one untimed warm-up call, device synchronised."""
    fn()
    synchronize(device)
    start = time.perf_counter()
    out = fn()
    synchronize(device)
    return out, time.perf_counter() - start


class NetworkMethod(Method):
    """A trained network draping scene frames in one shot (see the module docstring)."""

    kind = "one-shot"

    def __init__(self, name: str, options: MethodOptions | None = None):
        super().__init__(options)
        self.name = name
        self.scene = None

    def prepare(self, scene) -> None:
        self.scene = getattr(scene, "scene", scene)  # a ComparisonScene or a Scene

    def _require_scene(self):
        if self.scene is None:
            raise ValueError(f"scene: call prepare(scene) before {self.name}.drape")
        return self.scene

    def drape(self, frames: SceneFrames, *, metrics: Callable | None = None) -> DrapeResult:
        scene = self._require_scene()
        device = frames.rigid.positions.device
        sim = _simulator(self.name, device)
        _check_vertices(sim, frames)
        if self.name != "dynamic":
            positions, seconds = _timed(lambda: sim.drape(scene, frames), device)
            return DrapeResult(positions=positions, time_ms=seconds * 1e3 / positions.shape[0])
        return self._dynamic_hold(sim, scene, frames, device)

    def _dynamic_hold(self, sim, scene, frames: SceneFrames, device) -> DrapeResult:
        """Each pose of `frames` held still for HOLD_FRAMES frames; the last frame of each kept."""
        out, total = [], 0.0
        fps = float(scene.motion.fps)
        for b in range(frames.rigid.positions.shape[0]):
            poses = frames.poses[b].detach().cpu().expand(HOLD_FRAMES, -1)
            rigid = frames.rigid.positions[b].expand(HOLD_FRAMES, -1, -1, -1)
            positions, seconds = _timed(lambda: sim.simulate_poses(scene, poses, frames.betas[b], rigid, fps),
                                        device)
            out.append(positions[-1])
            total += seconds
        positions = torch.stack(out)
        return DrapeResult(positions=positions, time_ms=total * 1e3 / (positions.shape[0] * HOLD_FRAMES),
                           info={"hold_frames": HOLD_FRAMES})

    def simulate(self, scene, *, frames: SceneFrames | None = None, device="cpu",
                 dtype=torch.float32) -> SimulationResult:
        self.prepare(scene)
        frames = frames if frames is not None else scene.frames(device=device, dtype=dtype)
        if self.name != "dynamic":
            result = self.drape(frames)
            return SimulationResult(positions=result.positions, time_ms=result.time_ms)
        device = frames.rigid.positions.device
        sim = _simulator(self.name, device)
        _check_vertices(sim, frames)
        positions, seconds = _timed(lambda: sim.simulate(self.scene, frames), device)
        return SimulationResult(positions=positions, time_ms=seconds * 1e3 / positions.shape[0])


def _check_vertices(sim, frames: SceneFrames) -> None:
    """The network predicts N vertices per strand: the scene must have as many."""
    n = sim.static.config.num_vertices
    if frames.rigid.positions.shape[2] != n:
        raise ValueError(f"frames: the network was trained on {n} vertices per strand, the scene has "
                         f"{frames.rigid.positions.shape[2]}; build the scene with num_vertices={n}")


for _name in ("static", "dynamic", "quaffure"):
    register_method(_name, lambda options, _n=_name: NetworkMethod(_n, options), overwrite=True)
