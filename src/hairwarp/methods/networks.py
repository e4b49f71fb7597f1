"""The trained networks as methods: "static", "dynamic", "quaffure".

Each loads a checkpoint written by `hairwarp train` (`MethodOptions.checkpoint`) or shipped in
`hairwarp/assets`, reads the scene's hairstyle as its latent z = encode(strands), and times the
network forward plus the deformation lookup and taper of Eq. 2 applied to the rigid placement,
after one warm-up call, device synchronised: the "ms/drape" of Table 1 (the rigid placement,
Eq. 1, is shared by every method and not counted).

- "static": the static network (Section 3.2), one drape per frame.
- "dynamic": the dynamic network (Section 3.3). On a motion: the frames in order with the GRU
  state. On independent poses (a drape): each pose held still for `HOLD_FRAMES` frames from a
  zero GRU state, the last frame kept; the time is per network call.
- "quaffure": the adapted Quaffure decoder (Section 4.3.1), one drape per frame.

The shipped dynamic checkpoint holds its frozen static network, so "static" falls back to it.
The networks need SMPL-convention pose and shape (they read (beta, Theta)). A scene whose
strands have another vertex count than the network's is run at the network's (the hairstyle and
the rigid placement resampled by arc length, `at_network_resolution`) and the result resampled
back and projected onto the scene's rest lengths (`back_to_scene_resolution`).
"""

from __future__ import annotations

import importlib.resources
import os
import time
import weakref
from collections.abc import Callable

import torch

from hairwarp.methods.base import Method, MethodOptions, MethodResult, drape_in_chunks
from hairwarp.runtime import CapturedCall, synchronize, timed

STATIC_CHECKPOINT = "hairformer_static.pt"
DYNAMIC_CHECKPOINT = "hairformer_dynamic.pt"
QUAFFURE_CHECKPOINT = "hairformer_quaffure.pt"
# Shipped files each network method looks for, in order.
SHIPPED = {"static": (STATIC_CHECKPOINT, DYNAMIC_CHECKPOINT), "dynamic": (DYNAMIC_CHECKPOINT,),
           "quaffure": (QUAFFURE_CHECKPOINT,)}
NETWORK_METHODS = tuple(SHIPPED)
# Frames a static pose is held for when the dynamic network drapes it (settles the GRU state).
HOLD_FRAMES = 10

_LOADED: dict[tuple, HairFormerSimulator] = {}
# CUDA graphs a simulator keeps (per input shapes, and per body for a network reading contact).
MAX_GRAPHS = 8


def shipped_checkpoint(name: str) -> str | None:
    """Path of a checkpoint file shipped in `hairwarp/assets`, or None when this build has none."""
    path = str(importlib.resources.files("hairwarp") / "assets" / name)
    return path if os.path.exists(path) else None


class HairFormerSimulator:
    """A trained network (static, dynamic with its static, or Quaffure) with the latent basis.

    Args:
        static: the one-shot network (`StaticNetwork` or `QuaffureNetwork`), put in eval mode.
        dynamic: a `DynamicNetwork` (holds its frozen static network) or None.
        basis: the `HairLatentBasis` the networks were trained with (default: the shipped one).
    """

    def __init__(self, static, dynamic=None, basis=None):
        from hairwarp.scene.hair_latent import HairLatentBasis

        self.static = static.eval()
        self.dynamic = dynamic.eval() if dynamic is not None else None
        self.basis = basis or HairLatentBasis.load_default()
        # z of each hairstyle by the identity of its strands tensor (an entry is dropped with the
        # tensor), then by (device, dtype).
        self._latents: dict[int, dict] = {}
        # On CUDA the one-shot drape replays a CUDA graph per input shape (at batch 1 the
        # eager forward is launch-bound: 4.2 ms for the paper's static network on an H100).
        self.use_cuda_graphs = True
        self._graphs: dict[tuple, tuple] = {}  # key -> (CapturedCall or None, the body it queries)
        # Turn every input to face +z and the drape back (`hairwarp.models.heading`): the networks
        # were trained on bodies facing +z, and draping does not depend on the heading.
        self.canonical_heading = True

    @property
    def num_vertices(self) -> int:
        return int(self.static.config.num_vertices)

    def latent(self, hairstyle, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """Z (1, 512) of a hairstyle (least-squares encoding, computed once per hairstyle)."""
        strands = hairstyle.strands
        per_style = self._latents.get(id(strands))
        if per_style is None:
            per_style = self._latents[id(strands)] = {}
            weakref.finalize(strands, self._latents.pop, id(strands), None)
        key = (str(device), dtype)
        if key not in per_style:
            z = self.basis.encode(hairstyle.strands.double(), hairstyle.root_uv.double())
            per_style[key] = z.reshape(1, -1).to(device=device, dtype=dtype)
        return per_style[key]

    @torch.no_grad()
    def drape(self, frames) -> torch.Tensor:
        """One-shot drape of every frame: (B, M, N, 3) [m]."""
        rigid = frames.rigid.positions
        style = frames.scene.hairstyle
        dtype = next(self.static.parameters()).dtype
        z = self.latent(style, rigid.device, dtype).expand(rigid.shape[0], -1)
        root_uv = style.root_uv.to(rigid.device)
        inputs = (z, frames.betas.to(dtype), frames.poses.to(dtype), rigid.to(dtype), root_uv)
        body = frames.body_mesh if getattr(self.static.config, "contact_samples", 0) > 0 else None
        return self._one_shot(inputs, body).to(rigid.dtype)

    def _one_shot(self, inputs: tuple, body=None) -> torch.Tensor:
        """The static (or Quaffure) drape, replayed from a CUDA graph where one can be captured.

        A network that reads contact features queries `body` inside the same graph, which then
        belongs to that body (its BVH): graphs are kept per input shapes and body, the last
        `MAX_GRAPHS` of them.
        """
        from hairwarp.models.deformation import apply_deformation
        from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors

        canonical = self.canonical_heading
        projection = self.static.config.length_projection

        def fn(z, beta, theta, rigid, root_uv):
            angle = heading(theta) if canonical else torch.zeros_like(theta[:, 0])
            kwargs = {}
            if body is not None:
                contact = self.static.contact_features(rigid, root_uv, body)
                kwargs["contact"] = turn_contact_features(contact, -angle) if canonical else contact
            deformation = self.static(z, beta, turn_pose(theta, -angle) if canonical else theta, **kwargs)
            if canonical:
                deformation = turn_vectors(deformation, angle)
            return apply_deformation(rigid, deformation, root_uv, projection)

        if not (inputs[0].is_cuda and self.use_cuda_graphs):
            return fn(*inputs)
        key = (tuple((tuple(t.shape), t.dtype, str(t.device)) for t in inputs), None if body is None else id(body))
        if key not in self._graphs:
            while len(self._graphs) >= MAX_GRAPHS:
                self._graphs.pop(next(iter(self._graphs)))
            try:
                self._graphs[key] = (CapturedCall(fn, *inputs), body)  # the body lives as long as its graph
            except RuntimeError:  # an op that cannot be captured: stay eager for these shapes
                self._graphs[key] = (None, body)
        graph = self._graphs[key][0]
        return fn(*inputs) if graph is None else graph(*inputs)

    @torch.no_grad()
    def simulate_poses(self, hairstyle, poses: torch.Tensor, betas: torch.Tensor, rigid: torch.Tensor,
                       fps: float, body=None, contact: torch.Tensor | None = None) -> torch.Tensor:
        """Dynamic simulation of a hairstyle over a pose sequence.

        Args:
            hairstyle: the scene's `Hairstyle` (its strands give z, its root UVs the lookup).
            poses: (T, 66) body poses of consecutive frames, axis-angle [rad].
            betas: (1, 16) or (16,) body shape.
            rigid: (T, M, N, 3) rigid placement of each frame [m] (Eq. 1).
            fps: frame rate of the sequence [1/s].
            body: the frames' posed `BodyMesh` (T meshes, or one), for a network that reads
                contact features.
            contact: (T, L, F) those features computed already (instead of `body`).

        Returns:
            (T, M, N, 3) positions [m].
        """
        from hairwarp.models.deformation import apply_deformation
        from hairwarp.scene.motion import motion_descriptor_windows

        if self.dynamic is None:
            raise ValueError("dynamic: this checkpoint has no dynamic network")
        dtype = next(self.dynamic.parameters()).dtype
        t = rigid.shape[0]
        if poses.shape[0] != t:
            raise ValueError(f"poses: expected {t} frames (as rigid), got {poses.shape[0]}")
        from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors

        z = self.latent(hairstyle, rigid.device, dtype)
        betas = betas.reshape(1, -1)
        window = self.dynamic.config.window
        poses64 = poses.detach().cpu().double()
        # One turn for the whole sequence (the first frame's heading): a body that turns during
        # the motion keeps turning, as the dynamics need.
        angle = heading(poses64[:1]) if self.canonical_heading else torch.zeros(1, dtype=torch.float64)
        poses64 = turn_pose(poses64, -angle.expand(t))
        motion = motion_descriptor_windows(poses64, betas[0].detach().cpu().double(), 1.0 / fps, window,
                                           include_betas=False)
        motion = motion.to(device=rigid.device, dtype=dtype)[None]
        root_uv = hairstyle.root_uv.to(rigid.device)
        angles = angle.to(device=rigid.device, dtype=dtype).expand(t)
        if contact is None and self.dynamic.config.static.contact_samples > 0:
            contact = self.dynamic.contact_features(rigid.to(dtype), root_uv, body)
        if contact is not None:
            contact = turn_contact_features(contact, -angles)
        out = self.dynamic.simulate(z, betas.to(device=rigid.device, dtype=dtype),
                                    poses64.to(device=rigid.device, dtype=dtype)[None], motion,
                                    contact=None if contact is None else contact[None])
        maps = turn_vectors(out.deformation_map.reshape(t, *out.deformation_map.shape[2:]), angles)
        projection = self.dynamic.config.static.length_projection
        return apply_deformation(rigid.to(dtype), maps, root_uv, projection).to(rigid.dtype)

    def contact_features(self, frames) -> torch.Tensor | None:
        """(T, L, F) the dynamic network's contact features of the frames' rigid placement, a
        chunk of frames at a time (`SceneFrames.chunks`: a few frames' bodies held at once);
        None for a network that reads none.
        """
        if self.dynamic is None or self.dynamic.config.static.contact_samples == 0:
            return None
        dtype = next(self.dynamic.parameters()).dtype
        root_uv = frames.scene.hairstyle.root_uv.to(frames.rigid.positions.device)
        return torch.cat([self.dynamic.contact_features(chunk.rigid.positions.to(dtype), root_uv, chunk.body_mesh)
                          for chunk in frames.chunks()])

    def simulate(self, frames, contact: torch.Tensor | None = None) -> torch.Tensor:
        """Dynamic simulation over consecutive frames of the scene's motion: (T, M, N, 3);
        `contact`: `contact_features(frames)` if computed already.
        """
        scene = frames.scene
        poses = scene.motion.poses[frames.frame_indices.cpu()]
        if contact is None:
            contact = self.contact_features(frames)
        return self.simulate_poses(scene.hairstyle, poses, frames.betas[:1], frames.rigid.positions,
                                   fps=float(scene.motion.fps), contact=contact)


def load_simulator(name: str, checkpoint: str | None, device: torch.device) -> HairFormerSimulator:
    """The network of method `name` from `checkpoint` (None: the shipped file), cached per device.

    Raises:
        ValueError: no checkpoint shipped, an unreadable file, or one holding another network.
    """
    from hairwarp.models.checkpoint import load_checkpoint

    if name not in SHIPPED:
        raise ValueError(f"name: expected one of {NETWORK_METHODS}, got {name!r}")
    path = checkpoint
    if path is None:
        path = next((p for p in map(shipped_checkpoint, SHIPPED[name]) if p is not None), None)
        if path is None:
            raise ValueError(f"checkpoint: no {name} checkpoint is shipped with this build; train one "
                             f"(`hairwarp train {name}`) and pass it as the checkpoint")
    elif not os.path.isfile(path):
        raise ValueError(f"checkpoint: no such file {path!r}")
    key = (name, os.path.abspath(path), str(device))
    if key in _LOADED:
        return _LOADED[key]
    try:
        model = load_checkpoint(path, device=device).model
    except Exception as exc:  # a foreign or truncated file: say which and why, in one line
        first = (str(exc).strip() or type(exc).__name__).splitlines()[0]
        raise ValueError(f"checkpoint: cannot load {path!r} ({first})") from None
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
    return sim


def resample_polylines_torch(points: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """(..., K, 3) polylines -> (..., num_vertices, 3) points evenly spaced in arc length (torch,
    any device; the first and last points kept).
    """
    seg = (points[..., 1:, :] - points[..., :-1, :]).norm(dim=-1)
    cum = torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], dim=-1)  # (..., K)
    total = cum[..., -1:]
    t = torch.linspace(0.0, 1.0, num_vertices, device=points.device, dtype=points.dtype) * total
    k = points.shape[-2]
    idx = (torch.searchsorted(cum.contiguous(), t.contiguous(), right=True) - 1).clamp(0, k - 2)
    c0, c1 = cum.gather(-1, idx), cum.gather(-1, idx + 1)
    w = ((t - c0) / (c1 - c0).clamp_min(1e-30)).clamp(0.0, 1.0)[..., None]
    gather = lambda i: points.gather(-2, i[..., None].expand(*i.shape, 3))  # noqa: E731
    out = gather(idx) * (1 - w) + gather(idx + 1) * w
    out[..., 0, :] = points[..., 0, :]
    out[..., -1, :] = points[..., -1, :]
    return out


def at_network_resolution(frames, num_vertices: int):
    """`frames` with the hairstyle and the rigid placement resampled to `num_vertices` per strand
    (the same frames when they have it already). The resampled hairstyle is made once per scene.
    """
    import dataclasses

    from hairwarp.scene.scene import Scene

    if frames.rigid.positions.shape[2] == num_vertices:
        return frames
    scene = frames.scene
    key = ("network_resolution", num_vertices)
    if key not in scene._cache:
        scene._cache[key] = Scene(body=scene.body, scalp=scene.scalp,
                                  hairstyle=scene.hairstyle.subset(None, num_vertices), motion=scene.motion,
                                  name=scene.name)
    rigid = dataclasses.replace(frames.rigid, positions=resample_polylines_torch(frames.rigid.positions, num_vertices))
    return dataclasses.replace(frames, rigid=rigid, scene=scene._cache[key])


def back_to_scene_resolution(positions: torch.Tensor, frames) -> torch.Tensor:
    """(B, M, n, 3) network output -> the scene's N vertices per strand: resampled by arc length,
    the fixed vertices set to the rigid placement's, and projected onto its rest lengths.
    """
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.ops import follow_the_leader

    rigid = frames.rigid.positions
    if positions.shape[2] == rigid.shape[2]:
        return positions
    out = resample_polylines_torch(positions, rigid.shape[2])
    out[:, :, :NUM_FIXED_VERTICES] = rigid[:, :, :NUM_FIXED_VERTICES]
    return follow_the_leader(rigid.contiguous(), out.contiguous())


class NetworkMethod(Method):
    """A trained network draping or simulating scene frames (see the module docstring)."""

    kind = "network"

    def __init__(self, name: str, options: MethodOptions | None = None):
        super().__init__(options)
        if name not in SHIPPED:
            raise ValueError(f"name: expected one of {NETWORK_METHODS}, got {name!r}")
        self.name = name

    def simulator(self, frames) -> HairFormerSimulator:
        """The loaded network, checked against the frames (SMPL pose and shape)."""
        scene = frames.scene
        if scene is None or not getattr(scene.body, "has_smpl_pose", True):
            raise ValueError(f"method: the {self.name} network needs an SMPL-convention body (pose and shape "
                             "parameters); use adam, lbfgs or reference on this body")
        return load_simulator(self.name, self.options.checkpoint, frames.rigid.positions.device)

    def drape(self, frames, *, metrics: Callable | None = None) -> MethodResult:
        sim = self.simulator(frames)
        ours = at_network_resolution(frames, sim.num_vertices)
        out = self._drape(sim, ours)
        out.positions = back_to_scene_resolution(out.positions, frames)
        if ours is not frames:
            out.info["network_vertices"] = sim.num_vertices
        return self._kept_out(out, frames)

    def _kept_out(self, out: MethodResult, frames) -> MethodResult:
        """`out` through the body pass (`MethodOptions.keep_out`), its time added to the drape's."""
        if not self.options.keep_out:
            return out
        from hairwarp.methods.keep_out import keep_out_of_body_in_frames

        device = frames.rigid.positions.device
        with torch.no_grad():
            positions, seconds = timed(lambda: keep_out_of_body_in_frames(out.positions.clone(), frames), device)
        out.positions = positions
        out.time_ms = (out.time_ms or 0.0) + seconds * 1e3 / positions.shape[0]
        out.info["keep_out_ms"] = seconds * 1e3 / positions.shape[0]
        return out

    def _drape(self, sim, frames) -> MethodResult:
        device = frames.rigid.positions.device
        if self.name != "dynamic":
            # On the CPU warmed up once per shape in a process: a motion's chunks after the first
            # are timed without running twice. On CUDA every call warms up: its graphs are
            # captured per shape and body, and each chunk has a body of its own.
            key = None if device.type == "cuda" else ("network drape", self.name, id(sim),
                                                       tuple(frames.rigid.positions.shape))
            if getattr(sim.static.config, "contact_samples", 0) > 0 and frames.body_mesh is not None:
                frames.body_mesh.prepare()  # the chunk's body built before the clock starts, as a warm-up does
            positions, seconds = timed(lambda: sim.drape(frames), device, warmup_key=key)
            return MethodResult(positions=positions, time_ms=seconds * 1e3 / positions.shape[0])
        # Each pose held still for HOLD_FRAMES frames from a zero state; the last frame kept.
        out, total = [], 0.0
        style, fps = frames.scene.hairstyle, float(frames.scene.motion.fps)
        contact = sim.dynamic.contact_features(frames.rigid.positions, style.root_uv.to(device), frames.body_mesh)
        for b in range(frames.rigid.positions.shape[0]):
            poses = frames.poses[b].detach().cpu().expand(HOLD_FRAMES, -1)
            rigid = frames.rigid.positions[b].expand(HOLD_FRAMES, -1, -1, -1)
            held = None if contact is None else contact[b].expand(HOLD_FRAMES, -1, -1)
            positions, seconds = timed(
                lambda: sim.simulate_poses(style, poses, frames.betas[b], rigid, fps, contact=held), device)
            out.append(positions[-1])
            total += seconds
        positions = torch.stack(out)
        return MethodResult(positions=positions, time_ms=total * 1e3 / (positions.shape[0] * HOLD_FRAMES),
                            info={"hold_frames": HOLD_FRAMES})

    def simulate(self, frames) -> MethodResult:
        if self.name != "dynamic":
            # One drape per frame, a chunk of frames (and their bodies) at a time.
            return drape_in_chunks(self.drape, frames)
        sim = self.simulator(frames)
        ours = at_network_resolution(frames, sim.num_vertices)
        device = frames.rigid.positions.device
        # The contact features once, timed on their own (a long motion's bodies are built a chunk
        # at a time; a warm-up would build them all twice), then the network.
        synchronize(device)
        start = time.perf_counter()
        contact = sim.contact_features(ours)
        synchronize(device)
        contact_seconds = time.perf_counter() - start
        positions, seconds = timed(lambda: sim.simulate(ours, contact=contact), device)
        info = {} if ours is frames else {"network_vertices": sim.num_vertices}
        return self._kept_out(MethodResult(positions=back_to_scene_resolution(positions, frames),
                                           time_ms=(seconds + contact_seconds) * 1e3 / positions.shape[0], info=info),
                              frames)
