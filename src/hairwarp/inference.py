"""Inference with trained HairFormer checkpoints: drape one frame (static network, Eq. 2) and
simulate a motion (dynamic network, frame by frame with the GRU state), batched, CPU or CUDA.

The hairstyle enters the networks as its latent z = encode(strands) (`HairLatentBasis`), the
body as (beta, Theta); the predicted deformation map is applied to the scene's own rigid
placement by root UV (Eq. 2), so any hairstyle whose roots lie on the scalp grid works,
generated, decoded or loaded from a `.data` file.
"""

from __future__ import annotations

import importlib.resources
import os
import time
from dataclasses import dataclass

import torch

from hairwarp.bench.timing import synchronize

STATIC_CHECKPOINT = "hairformer_static.pt"
DYNAMIC_CHECKPOINT = "hairformer_dynamic.pt"


def shipped_checkpoint(name: str) -> str | None:
    """Path of a checkpoint shipped in `hairwarp/assets`, or None when this build has none."""
    path = str(importlib.resources.files("hairwarp") / "assets" / name)
    return path if os.path.exists(path) else None


@dataclass
class SimulationResult:
    """positions (T, M, N, 3) [m]; ms per frame (device synchronised, after warm-up)."""

    positions: torch.Tensor
    ms_per_frame: float


class HairFormerSimulator:
    """Static and (optionally) dynamic networks with the latent basis, ready for scenes.

    Args:
        static: a trained `StaticNetwork` (eval mode).
        dynamic: a trained `DynamicNetwork` (holds its frozen static network) or None.
        basis: the `HairLatentBasis` the networks were trained with (default: the shipped one).
    """

    def __init__(self, static, dynamic=None, basis=None):
        from hairwarp.scene.hair_latent import HairLatentBasis

        self.static = static.eval()
        self.dynamic = dynamic.eval() if dynamic is not None else None
        self.basis = basis or HairLatentBasis.load_default()

    @classmethod
    def from_checkpoints(cls, static_path: str, dynamic_path: str | None = None, device="cpu"):
        """Load checkpoints written by `hairwarp train` (or the shipped ones)."""
        from hairwarp.models.checkpoint import load_checkpoint

        static = load_checkpoint(static_path, device=device).model
        dynamic = load_checkpoint(dynamic_path, device=device).model if dynamic_path else None
        return cls(static, dynamic)

    def latent(self, scene, device, dtype=torch.float32) -> torch.Tensor:
        """z (1, 512) of the scene's hairstyle (least-squares encoding, cached on the scene)."""
        key = ("_hairformer_z", str(device))
        cached = getattr(scene, "_hairformer_latent", None)
        if cached is None or cached[0] != key:
            style = scene.hairstyle
            z = self.basis.encode(style.strands.double(), style.root_uv.double())
            cached = (key, z.reshape(1, -1).to(device=device, dtype=dtype))
            scene._hairformer_latent = cached
        return cached[1]

    @torch.no_grad()
    def drape(self, scene, frames) -> torch.Tensor:
        """Static drape of every frame in `frames` (B, M, N, 3)."""
        rigid = frames.rigid.positions
        dtype = next(self.static.parameters()).dtype
        z = self.latent(scene, rigid.device, dtype).expand(rigid.shape[0], -1)
        root_uv = scene.hairstyle.root_uv.to(rigid.device)
        out = self.static.drape(z, frames.betas.to(dtype), frames.poses.to(dtype), rigid.to(dtype), root_uv)
        return out.to(rigid.dtype)

    @torch.no_grad()
    def simulate(self, scene, frames) -> torch.Tensor:
        """Dynamic simulation over the frames (must be consecutive from frame 0): (T, M, N, 3)."""
        poses = scene.motion.poses[frames.frame_indices.cpu()]
        return self.simulate_poses(scene, poses, frames.betas[:1], frames.rigid.positions,
                                   fps=float(scene.motion.fps))

    @torch.no_grad()
    def simulate_poses(self, scene, poses: torch.Tensor, betas: torch.Tensor, rigid: torch.Tensor,
                       fps: float) -> torch.Tensor:
        """Dynamic simulation of the scene's hairstyle over a pose sequence.

        Args:
            scene: anything with `hairstyle` (its strands give z, its root UVs the lookup).
            poses: (T, 66) body poses of consecutive frames, axis-angle [rad].
            betas: (1, 16) or (16,) body shape.
            rigid: (T, M, N, 3) rigid placement of each frame [m] (Eq. 1).
            fps: frame rate of the sequence [1/s].

        Returns:
            (T, M, N, 3) positions [m].
        """
        from hairwarp.models.deformation import apply_deformation
        from hairwarp.scene.motion import motion_descriptor_windows

        if self.dynamic is None:
            raise ValueError("dynamic: this simulator has no dynamic network; use drape()")
        dtype = next(self.dynamic.parameters()).dtype
        t = rigid.shape[0]
        if poses.shape[0] != t:
            raise ValueError(f"poses: expected {t} frames (as rigid), got {poses.shape[0]}")
        z = self.latent(scene, rigid.device, dtype)
        betas = betas.reshape(1, -1)
        window = self.dynamic.config.window
        motion = motion_descriptor_windows(poses.detach().cpu().double(), betas[0].detach().cpu().double(),
                                           1.0 / fps, window, include_betas=False)
        motion = motion.to(device=rigid.device, dtype=dtype)[None]
        out = self.dynamic.simulate(z, betas.to(device=rigid.device, dtype=dtype),
                                    poses.to(device=rigid.device, dtype=dtype)[None], motion)
        maps = out.deformation_map.reshape(t, *out.deformation_map.shape[2:])
        root_uv = scene.hairstyle.root_uv.to(rigid.device)
        return apply_deformation(rigid.to(dtype), maps, root_uv).to(rigid.dtype)

    def simulate_scene(self, scene, frames):
        """(positions (T, M, N, 3), label, ms per frame) for `hairwarp demo`."""
        device = frames.rigid.positions.device
        run = self.simulate if self.dynamic is not None else self.drape
        run(scene, frames)  # warm-up (kernels, caches, the latent)
        synchronize(device)
        start = time.perf_counter()
        positions = run(scene, frames)
        synchronize(device)
        ms = (time.perf_counter() - start) * 1e3 / positions.shape[0]
        label = "HairFormer dynamic network" if self.dynamic is not None else "HairFormer static network"
        return positions, label, ms


def load_default_simulator(device="cpu") -> HairFormerSimulator | None:
    """The simulator of the shipped checkpoints, or None when this build ships none.

    The dynamic checkpoint holds its frozen static network, so a build may ship it alone
    (half precision, under the repository's 16 MiB budget); a static-only build ships
    `hairformer_static.pt`.
    """
    from hairwarp.models.checkpoint import load_checkpoint

    dynamic_path = shipped_checkpoint(DYNAMIC_CHECKPOINT)
    if dynamic_path is not None:
        dynamic = load_checkpoint(dynamic_path, device=device).model
        return HairFormerSimulator(dynamic.static, dynamic)
    static_path = shipped_checkpoint(STATIC_CHECKPOINT)
    if static_path is None:
        return None
    return HairFormerSimulator.from_checkpoints(static_path, device=device)
