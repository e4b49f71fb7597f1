"""Training batches: hair latents, decoded strands, bodies, poses, rigid placement, energy inputs.

The sampler turns a `DataConfig` into the batches of Section 4.2:

Hair (Section 3.1). Hairstyle i of the corpus is a procedural hairstyle with random parameters
(`sample_hairstyle_params`, seeded by `corpus_seed` and i), encoded into the 512-d latent z_i
of `hairwarp.scene.hair_latent` ("corpus"), or z_i ~ N(0, s^2 I) ("sample"). Either way the
initial hair is P_init = decode(z_i) on the scalp grid, as the paper generates P_init from z:
what the network reads (z) and what the physics measures (P_init, its rest lengths) agree
exactly (`DataConfig.grown_hair_fraction` > 0: that share of the corpus uses its generated
strands grown around the rest body instead, z their encoding, as evaluation meets them).
Decode gives a strand for every one of the 32 x 32 grid roots, so every hairstyle has
the same M strands with the same roots and root UVs, and a batch of different hairstyles is one
(B, M, N, 3) tensor. `DataConfig.strand_stride` keeps a sub-grid (and `num_vertices` resamples
the strands by arc length) for CPU-sized runs; the code path is the same.

Bodies and poses. A representative set of `num_subjects` body shapes is drawn once; phases 0-1
use its mean, phase 2 subject 0, phase 3 and dynamic training every subject plus Gaussian
noise. Motions are the procedural ones (`motion_variants` jittered copies each, variant v
performed by subject v mod num_subjects) and optional AMASS files (one subject per distinct
betas), all played at `fps`.

Placement (Eq. 1) for a batch of different hairstyles: the root offsets dt[s, 0], dt_align and
the posed scalp normals depend only on the roots, which all hairstyles share, so one
`rigid_placement` of the roots serves the batch and each hairstyle is moved by its own frame's
M_head: p_rigid = M_head p_init + dt_align + dt[s, 0], exactly `rigid_placement`'s result.

Randomness. The global batch of a step is a pure function of (seed, step): the generator is
keyed by them, so resuming at step k draws the very batches an uninterrupted run would. The
corpus, the subjects and the dynamic-score threshold depend on `corpus_seed` only.

Data parallelism (`rank`, `world_size`; see `hairwarp.training.distributed`). `batch_size` is
the global batch. Every rank makes the global batch's random draws (a few numbers per sample:
which hairstyle, motion, frame, rotation, noise; all ranks agree on them), then builds only its
own share: the contiguous slice `shard_bounds(batch_size, rank, world_size)` of the samples,
whose hairstyles it decodes, bodies it poses and places (the expensive part). So the ranks'
shares are disjoint, and together they are exactly the batch a single process draws with the
same seed, whatever the world size: a run resumed at another world size continues the same
sequence of global batches. Phase 0's batch (one sample, always the same) is replicated on
every rank. `HairBatch.share` / `SequenceBatch.share` is the weight of a rank's batch mean in
the global mean (samples / global samples; 1 / world_size for the replicated batch).

Caches: corpus latents (all, shared by the samplers of a process), decoded hairstyles (LRU,
`hairstyle_cache_size`), posed bodies of noise-free motion frames (LRU, `pose_cache_size`),
motion-descriptor windows per subsampled motion, the phase-0 batch.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import torch

from hairwarp.energy import EnergyInputs
from hairwarp.scene.body import Body, PosedBody, default_body
from hairwarp.scene.hair_latent import HairLatentBasis
from hairwarp.scene.hairstyles import generate_hairstyle, sample_hairstyle_params
from hairwarp.scene.motion import (
    DESCRIPTOR_DIM_NO_BETAS,
    JOINT,
    NUM_BETAS,
    Motion,
    dynamic_score,
    load_amass,
    motion_descriptor_windows,
    procedural_motion,
)
from hairwarp.scene.placement import rigid_placement, root_search
from hairwarp.scene.rotations import transform_points
from hairwarp.scene.scalp import Scalp, build_scalp
from hairwarp.training.config import SCALP_GRID, DataConfig

MOTION_DIM = DESCRIPTOR_DIM_NO_BETAS  # the dynamic network appends beta itself (Section 3.3.1)

# Generator streams: each kind of draw has its own, so adding draws to one never shifts another.
_STREAM_STATIC = 1
_STREAM_SEQUENCE = 2
_STREAM_CORPUS = 3
_STREAM_SUBJECTS = 4
_STREAM_THRESHOLD = 5
_STREAM_GROWN = 6
# Head rotation shares of the neck and head joints (as the procedural head motions split them).
_NECK_SHARE = 0.35
_HEAD_SHARE = 0.65
# Draws of a sequence before giving up on the dynamic-score filter and keeping the best one.
_SEQUENCE_TRIES = 64

_SCALPS: dict[int, tuple[Body, Scalp]] = {}
# Corpus latents of every sampler of this process (ranks and resumed runs share the corpus):
# (basis id, scalp id, corpus_seed, latent_source, latent_scale) -> (basis, scalp,
# {index: z (512,) float64}); the objects are kept so a reused id is recognised.
_LATENTS: dict[tuple, tuple] = {}


def _generator(*keys: int) -> np.random.Generator:
    return np.random.default_rng([int(k) for k in keys])


def shard_bounds(batch_size: int, rank: int, world_size: int) -> tuple[int, int]:
    """The samples [lo, hi) of a global batch that `rank` of `world_size` builds.

    Contiguous slices whose sizes differ by at most one (5 samples on 2 ranks: 2 and 3).

    Raises:
        ValueError: if a rank would get no sample (batch_size < world_size) or on bad ints.
    """
    for name, value, low in (("batch_size", batch_size, 1), ("world_size", world_size, 1), ("rank", rank, 0)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    if rank >= world_size:
        raise ValueError(f"rank: expected 0 <= rank < world_size={world_size}, got {rank}")
    if batch_size < world_size:
        raise ValueError(
            f"batch_size: the global batch of {batch_size} leaves some of the {world_size} ranks without a "
            "sample; use batch_size >= world size (batch_size is the global batch)"
        )
    return rank * batch_size // world_size, (rank + 1) * batch_size // world_size


def _noise(g: np.random.Generator, std: float, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(g.normal(0.0, std, size=tuple(like.shape)), dtype=like.dtype)


def _scalp_of(body: Body) -> Scalp:
    # build_scalp takes about a second: bodies are long-lived, build once per body object.
    entry = _SCALPS.get(id(body))
    if entry is None or entry[0] is not body:
        entry = (body, build_scalp(body))
        _SCALPS[id(body)] = entry
    return entry[1]


@dataclass(eq=False)
class HairBatch:
    """B training samples (one frame each), ready for a network and the energy.

    Attributes:
        z: (B, 512) hair latents.
        betas: (B, 16) body shapes.
        poses: (B, 66) body poses, axis-angle [rad].
        trans: (B, 3) root translations [m].
        strands: (B, M, N, 3) P_init = decode(z) [m] (rest pose).
        root_uv: (M, 2) root UVs shared by the batch.
        rigid: (B, M, N, 3) rigidly posed hair P_rigid [m] (Eq. 1).
        inputs: the `EnergyInputs` (rest lengths (B, M, N-1), rigid, posed scalp normals
            (B, M, 3), the cropped body meshes, or None when built without bodies).
        hairstyle_ids: corpus index of each sample's hairstyle.
        info: what was drawn (phase, motions, frames...), plain data for logs; for a batch of
            the sampler, the lists describe the global batch and "shard" is [lo, hi), the
            samples this batch holds.
        share: weight of this batch's mean in the global batch's mean: samples held / samples
            of the global batch (1 in a single process; 1 / world_size for a batch replicated
            on every rank).
        body_vertices: (B, V, 3) the posed bodies' vertices [m] (uncropped; the faces are the
            sampler's `body_faces`), or None.
        teacher: (B, M, N, 3) the drapes a distillation term pulls toward [m]
            (`StaticTrainingConfig.teacher_iterations`), or None.
    """

    z: torch.Tensor
    betas: torch.Tensor
    poses: torch.Tensor
    trans: torch.Tensor
    strands: torch.Tensor
    root_uv: torch.Tensor
    rigid: torch.Tensor
    inputs: EnergyInputs
    hairstyle_ids: list
    info: dict = field(default_factory=dict)
    share: float = 1.0
    body_vertices: torch.Tensor | None = None
    teacher: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        """Samples held (this rank's share of the global batch)."""
        return int(self.z.shape[0])


@dataclass(eq=False)
class SequenceBatch:
    """B sequences of W warm-up and R rollout frames (Section 4.2.2).

    Attributes:
        z: (B, 512) hair latents (one hairstyle per sequence).
        betas: (B, 16) body shapes.
        poses: (B, W + R, 66) poses of the frames [rad].
        motion: (B, W + R, T_w, D) motion-descriptor windows ending at each frame (D = 132).
        warmup: HairBatch of the B * W warm-up frames (sequence-major: item b * W + w), without
            body meshes (no loss is evaluated on them).
        rollout: HairBatch of the B * R rollout frames (item b * R + r), with body meshes.
        intervals: frame interval k of each sequence held.
        info: what was drawn, plain data (lists of the global batch; "shard" [lo, hi)).
        share: weight of this batch's mean in the global batch's mean (see `HairBatch`).
    """

    z: torch.Tensor
    betas: torch.Tensor
    poses: torch.Tensor
    motion: torch.Tensor
    warmup: HairBatch
    rollout: HairBatch
    intervals: list
    info: dict = field(default_factory=dict)
    share: float = 1.0

    @property
    def batch_size(self) -> int:
        """Sequences held (this rank's share of the global batch)."""
        return int(self.z.shape[0])

    @property
    def warmup_frames(self) -> int:
        return self.warmup.batch_size // self.batch_size

    @property
    def rollout_frames(self) -> int:
        return self.rollout.batch_size // self.batch_size


@dataclass(frozen=True)
class MotionEntry:
    """One motion of the pool, performed by one subject."""

    motion: Motion
    subject: int
    name: str


class TrainingSampler:
    """Draws the training batches of Section 4.2 from a `DataConfig` (see the module docstring).

    Args:
        config: what to draw (`DataConfig()` when None).
        seed: training seed (with the step it keys every global batch).
        rank: this process's rank in a data-parallel run (0-based): which share of each
            global batch it builds.
        world_size: number of ranks.
        device: torch device of every batch tensor.
        dtype: float32 (training) or float64 (checks).
        body: the body model (`default_body()` when None).
        basis: the hair latent basis (`HairLatentBasis.load_default()` when None).

    Raises:
        ValueError: on a bad rank/world size, dtype, or a basis whose grid is not 32 x 32.
    """

    def __init__(
        self,
        config: DataConfig | None = None,
        *,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        body: Body | None = None,
        basis: HairLatentBasis | None = None,
    ):
        self.config = config if config is not None else DataConfig()
        if not isinstance(self.config, DataConfig):
            raise ValueError(f"config: expected a DataConfig, got {type(self.config).__name__}")
        for name, value, low in (("seed", seed, 0), ("world_size", world_size, 1), ("rank", rank, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
        if rank >= world_size:
            raise ValueError(f"rank: expected 0 <= rank < world_size={world_size}, got {rank}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
        self.seed, self.rank, self.world_size = seed, rank, world_size
        self.device = torch.device(device)
        self.dtype = dtype
        self.body = body if body is not None else default_body()
        self.scalp = _scalp_of(self.body)
        self.basis = basis if basis is not None else HairLatentBasis.load_default()
        if self.basis.num_roots != SCALP_GRID * SCALP_GRID:
            raise ValueError(
                f"basis: expected a {SCALP_GRID}x{SCALP_GRID} root grid, got {self.basis.num_roots} roots"
            )
        cfg = self.config

        # Sub-grid of strands: every stride-th row and column, centred in each stride block.
        uv = torch.as_tensor(self.basis.root_uv, dtype=torch.float64)
        col = torch.floor(uv[:, 0] * SCALP_GRID).long()
        row = torch.floor(uv[:, 1] * SCALP_GRID).long()
        s = cfg.strand_stride
        keep = (col % s == s // 2) & (row % s == s // 2)
        self.strand_index = torch.nonzero(keep)[:, 0]
        if self.strand_index.numel() != cfg.num_strands:
            raise ValueError(f"basis: its root UVs do not form a {SCALP_GRID}x{SCALP_GRID} grid")
        self.root_uv = uv[self.strand_index].to(device=self.device, dtype=torch.float32)
        zero = torch.zeros(self.basis.latent_dim, dtype=torch.float64)
        roots = self.basis.decode(zero, self.scalp)[0][self.strand_index, 0]
        self.roots = roots.to(device=self.device, dtype=self.dtype)  # (M, 3), shared by all hairstyles
        self._search = root_search(self.body, self.roots)
        from hairwarp.ops import BodyMesh

        # The topology checks of a body mesh (watertight, consistently oriented outward) depend
        # on the faces only, which posing keeps: check the rest mesh once here, not every batch.
        self._faces = self.body.faces.to(device=self.device, dtype=torch.int32)
        BodyMesh(self.body.rest_vertices.to(device=self.device, dtype=self.dtype), self._faces)

        # The representative body shapes ("dancers") and their mean (Section 4.2.1).
        g = _generator(cfg.corpus_seed, _STREAM_SUBJECTS)
        subjects = g.normal(0.0, cfg.shape_std, size=(cfg.num_subjects, NUM_BETAS))
        self.mean_betas = torch.as_tensor(subjects.mean(axis=0), dtype=torch.float32)
        self.subject_betas = [torch.as_tensor(b, dtype=torch.float32) for b in subjects]
        self.entries = self._motion_pool()
        # The rest pose of the procedural motions (standing, arms lowered) at t = 0.
        self.rest_pose = procedural_motion("nod", duration=1.0 / cfg.fps, fps=cfg.fps).poses[0].clone()

        key = (id(self.basis), id(self.scalp), cfg.corpus_seed, cfg.latent_source, cfg.latent_scale)
        entry = _LATENTS.get(key)
        if entry is None or entry[0] is not self.basis or entry[1] is not self.scalp:
            entry = _LATENTS[key] = (self.basis, self.scalp, {})
        self._latents: dict[int, torch.Tensor] = entry[2]
        self._hairstyles: OrderedDict = OrderedDict()
        self._posed: OrderedDict = OrderedDict()
        self._descriptors: dict = {}
        self._thresholds: dict = {}
        self._phase0: HairBatch | None = None
        self._long_pools: dict = {}
        # Grown corpus hairstyles: index -> (z (512,) float64, P_init (M, N_basis, 3) float64).
        self._grown: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    # ------------------------------------------------------------------------------ sizes
    @property
    def num_strands(self) -> int:
        """M, strands per hairstyle."""
        return int(self.strand_index.numel())

    @property
    def num_vertices(self) -> int:
        """N, vertices per strand."""
        return self.config.num_vertices

    @property
    def latent_dim(self) -> int:
        """d_z (512)."""
        return self.basis.latent_dim

    @property
    def body_faces(self) -> torch.Tensor:
        """(F, 3) int32 faces of the body model (every batch's `body_vertices` share them)."""
        return self._faces

    def generator(self, stream: int, step: int) -> np.random.Generator:
        """The generator of one global batch: keyed by (seed, stream, step), the same on every
        rank. (The key's second slot, 0, once held the rank: kept so that single-process runs
        draw the batches they always drew.)
        """
        return _generator(self.seed, 0, stream, step)

    def shard(self, batch_size: int) -> tuple[int, int]:
        """This rank's samples [lo, hi) of a global batch of `batch_size` (`shard_bounds`)."""
        return shard_bounds(batch_size, self.rank, self.world_size)

    # ------------------------------------------------------------------------------ motions
    def _motion_pool(self) -> list[MotionEntry]:
        cfg = self.config
        entries = []
        for variant in range(cfg.motion_variants):
            for name in cfg.motions:
                seed = None if variant == 0 else 1000 * cfg.corpus_seed + variant
                motion = procedural_motion(name, seed=seed, fps=cfg.fps)
                entries.append(MotionEntry(motion, variant % cfg.num_subjects, f"{name}#{variant}"))
        seen: dict[tuple, int] = {}
        for path in cfg.amass_paths:
            motion = load_amass(path, target_fps=cfg.fps)
            key = tuple(np.round(motion.betas.double().numpy(), 6))
            if key not in seen:
                seen[key] = len(self.subject_betas)
                self.subject_betas.append(motion.betas.clone().float())
            entries.append(MotionEntry(motion, seen[key], str(path)))
        return entries

    # ------------------------------------------------------------------------------ hair
    def latent(self, index: int) -> torch.Tensor:
        """Z of corpus hairstyle `index` (512,), float64 on the CPU, cached."""
        if not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"index: expected a non-negative int, got {index!r}")
        index = int(index)
        if index not in self._latents:
            cfg = self.config
            g = _generator(cfg.corpus_seed, _STREAM_CORPUS, index)
            if cfg.latent_source == "sample":
                z = torch.as_tensor(g.standard_normal(self.latent_dim) * cfg.latent_scale)
            else:
                params = sample_hairstyle_params(g)
                style = generate_hairstyle(self.scalp, params, num_vertices=self.basis.num_vertices)
                if style.num_strands == 0:
                    raise ValueError(f"index: corpus hairstyle {index} has no strand left after filtering")
                z = self.basis.encode(style.strands.double(), style.root_uv)
            self._latents[index] = z.to(torch.float64)
        return self._latents[index]

    def corpus_length(self, index: int) -> float:
        """The length parameter [m] of corpus hairstyle `index` (no decoding: the first draw of
        its generator, as in `latent`).
        """
        return sample_hairstyle_params(_generator(self.config.corpus_seed, _STREAM_CORPUS, int(index))).length

    def long_hairstyles(self, num_hairstyles: int) -> list[int]:
        """Indices < `num_hairstyles` of the corpus hairstyles at least `long_hair_length` long."""
        key = ("long", num_hairstyles)
        if key not in self._long_pools:
            threshold = self.config.long_hair_length
            self._long_pools[key] = [i for i in range(num_hairstyles) if self.corpus_length(i) >= threshold]
        return self._long_pools[key]

    def is_grown(self, index: int) -> bool:
        """Whether corpus hairstyle `index` is one of the `grown_hair_fraction` share (a draw of
        its own generator: the same on every rank and run).
        """
        fraction = self.config.grown_hair_fraction
        if fraction <= 0:
            return False
        return bool(_generator(self.config.corpus_seed, _STREAM_GROWN, int(index)).uniform() < fraction)

    def grown_hairstyle(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(z (512,), P_init (M, N_basis, 3)) of corpus hairstyle `index` grown around the rest
        body: its generated strands (the sub-grid's, each on its grid root), z = their encoding.
        float64 on the CPU, cached (growing one costs ~0.4-1 s on a CPU).
        """
        index = int(index)
        if index not in self._grown:
            params = sample_hairstyle_params(_generator(self.config.corpus_seed, _STREAM_CORPUS, index))
            style = generate_hairstyle(self.scalp, params, num_vertices=self.basis.num_vertices,
                                       body=(self.body.rest_vertices, self.body.faces))
            if style.num_strands == 0:
                raise ValueError(f"index: corpus hairstyle {index} has no strand left after filtering")
            strands = style.strands.double()
            z = self.basis.encode(strands, style.root_uv)
            # Each grid root takes the strand nearest in UV (as `encode` maps them), moved onto
            # the root: a strand filtered as too short is replaced by its neighbour.
            picked = strands[self.basis.nearest_strands(style.root_uv)[self.strand_index]]
            picked = picked - picked[:, :1] + self.roots.detach().cpu().double()[:, None, :]
            self._grown[index] = (z.to(torch.float64), picked)
        return self._grown[index]

    def hairstyle(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(z (512,), P_init (M, N, 3)) of corpus hairstyle `index`, on the sampler's device and
        dtype, cached (LRU). P_init = decode(z), or the strands grown around the body for the
        `grown_hair_fraction` share (`is_grown`).
        """
        cached = self._hairstyles.get(index)
        if cached is not None:
            self._hairstyles.move_to_end(index)
            return cached
        if self.is_grown(index):
            z, strands = self.grown_hairstyle(index)
        else:
            z = self.latent(index)
            strands = self.basis.decode(z, self.scalp)[0][self.strand_index]  # (M, 100, 3) float64
        if strands.shape[1] != self.num_vertices:
            from hairwarp.scene.hairstyles import resample_strands

            strands = resample_strands(strands, self.num_vertices, dtype=torch.float64)
        item = (z.to(device=self.device, dtype=self.dtype), strands.to(device=self.device, dtype=self.dtype))
        if self.config.hairstyle_cache_size > 0:
            self._hairstyles[index] = item
            while len(self._hairstyles) > self.config.hairstyle_cache_size:
                self._hairstyles.popitem(last=False)
        return item

    def hairstyles(self, indices) -> tuple[torch.Tensor, torch.Tensor]:
        """Stacked (z (B, 512), P_init (B, M, N, 3)) of corpus hairstyles `indices`."""
        items = [self.hairstyle(int(i)) for i in indices]
        return torch.stack([z for z, _ in items]), torch.stack([s for _, s in items])

    # ------------------------------------------------------------------------------ bodies
    def _pose(self, betas: torch.Tensor, poses: torch.Tensor, trans: torch.Tensor, keys) -> PosedBody:
        """Pose B bodies; items whose key is not None come from (and go to) the LRU cache."""
        b = poses.shape[0]
        vertices: list = [None] * b
        heads: list = [None] * b
        missing = []
        for i, key in enumerate(keys):
            hit = None if key is None else self._posed.get(key)
            if hit is None:
                missing.append(i)
            else:
                self._posed.move_to_end(key)
                vertices[i], heads[i] = hit
        if missing:
            idx = torch.as_tensor(missing, device=self.device)
            posed = self.body.pose(betas=betas[idx], poses=poses[idx], trans=trans[idx])
            for j, i in enumerate(missing):
                vertices[i], heads[i] = posed.vertices[j], posed.head_transform[j]
                if keys[i] is not None and self.config.pose_cache_size > 0:
                    # Clones: a view would keep the whole batch's vertices alive in the cache.
                    self._posed[keys[i]] = (vertices[i].clone(), heads[i].clone())
            while len(self._posed) > self.config.pose_cache_size:
                self._posed.popitem(last=False)
        return PosedBody(vertices=torch.stack(vertices), joints=None, head_transform=torch.stack(heads))

    def place(
        self,
        z: torch.Tensor,
        strands: torch.Tensor,
        betas: torch.Tensor,
        poses: torch.Tensor,
        trans: torch.Tensor | None = None,
        *,
        hairstyle_ids=None,
        pose_keys=None,
        build_body: bool = True,
        info: dict | None = None,
    ) -> HairBatch:
        """Pose the bodies, place each hairstyle rigidly (Eq. 1), build the energy inputs.

        Args:
            z: (B, 512) latents.
            strands: (B, M, N, 3) P_init of each sample, roots at the sampler's grid roots.
            betas: (B, 16) shapes; poses: (B, 66) [rad]; trans: (B, 3) [m] or None (zero).
            hairstyle_ids: optional corpus indices (for the record).
            pose_keys: optional hashable key per sample for the posed-body cache (None: no
                caching for that sample).
            build_body: build the (cropped) body meshes for the contact energy.
            info: plain data stored in the batch.

        Returns:
            HairBatch.
        """
        device, dtype = self.device, self.dtype
        b = z.shape[0]
        betas = betas.to(device=device, dtype=dtype)
        poses = poses.to(device=device, dtype=dtype)
        if trans is None:
            trans = torch.zeros(b, 3)
        trans = trans.to(device=device, dtype=dtype)
        posed = self._pose(betas, poses, trans, pose_keys if pose_keys is not None else [None] * b)
        # Eq. 1: the root offsets, dt_align and the posed normals depend only on the (shared)
        # roots; a one-vertex "strand" per root gives them for every frame of the batch.
        anchor = rigid_placement(self.roots[:, None, :], posed, self.body, scalp=self.scalp,
                                 root_uv=self.root_uv, search=self._search)
        m, n = strands.shape[1], strands.shape[2]
        moved = transform_points(posed.head_transform, strands.reshape(b, m * n, 3)).reshape(b, m, n, 3)
        rigid = moved + anchor.align[:, None, None, :] + anchor.root_offsets[:, :, None, :]
        rest_lengths = torch.linalg.vector_norm(strands[:, :, 1:] - strands[:, :, :-1], dim=-1)
        body_mesh = None
        if build_body:
            from hairwarp.ops import BodyMesh

            # Checked at setup; a BVH built on the GPU (new bodies every step: build time counts).
            body_mesh = BodyMesh(posed.vertices, self._faces, require_watertight=False, bvh="lbvh")
            if self.config.crop_body:
                # One reach per strand for the batch: the longest of its hairstyles' strands.
                body_mesh = body_mesh.crop_for_hair(rigid[:, :, 0], rest_lengths.sum(-1).amax(0))
        inputs = EnergyInputs(rest_lengths=rest_lengths, rigid=rigid, scalp_normals=anchor.normals,
                              body=body_mesh)
        ids = list(hairstyle_ids) if hairstyle_ids is not None else []
        return HairBatch(z.to(device=device, dtype=dtype), betas, poses, trans, strands, self.root_uv, rigid,
                         inputs, ids, dict(info or {}), body_vertices=posed.vertices)

    # ------------------------------------------------------------------------------ static
    def head_rotation(self, g: np.random.Generator, radius_fraction: float) -> np.ndarray:
        """A head rotation vector (3,) [rad] on the phase-1 ellipsoid scaled by `radius_fraction`
        (direction uniform on the sphere, mapped onto the ellipsoid's surface).
        """
        u = g.standard_normal(3)
        u /= max(float(np.linalg.norm(u)), 1e-12)
        return radius_fraction * np.asarray(self.config.head_rotation_radii) * u

    def static_batch(
        self, step: int, phase: int, progress: float, batch_size: int, num_hairstyles: int = 1,
        build_body: bool = True,
    ) -> HairBatch:
        """The batch of a static-curriculum step (Section 4.2.1).

        Args:
            step: global step (keys the generator).
            phase: 0 (one rest body, one hairstyle: a batch of 1, replicated on every rank),
                1 (head rotations on an ellipsoid whose radii grow with `progress`), 2
                (`num_hairstyles` hairstyles, motions of subject 0) or 3 (`num_hairstyles`, all
                motions and subjects, noisy shapes).
            progress: position in the phase, in [0, 1] (phase 1's radius fraction).
            batch_size: samples of the global batch (phases 1-3); this rank builds its share.
            num_hairstyles: hairstyle pool of phases 2-3 (corpus indices 0 .. n-1).
            build_body: build the batch's (cropped) body meshes; False leaves `inputs.body`
                None (a captured training step refits its own body to `body_vertices`).

        Returns:
            HairBatch of this rank's samples (all of them in a single process).
        """
        if phase not in (0, 1, 2, 3):
            raise ValueError(f"phase: expected 0, 1, 2 or 3, got {phase!r}")
        if not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size: expected a positive int, got {batch_size!r}")
        if not isinstance(num_hairstyles, int) or num_hairstyles < 1:
            raise ValueError(f"num_hairstyles: expected a positive int, got {num_hairstyles!r}")
        cfg = self.config
        g = self.generator(_STREAM_STATIC, step)
        info: dict = {"phase": phase}
        if phase == 0:
            # Phase 0's batch never changes (one body, one pose, one hairstyle): place it once.
            if self._phase0 is None:
                z, strands = self.hairstyles([0])
                self._phase0 = self.place(z, strands, self.mean_betas[None], self.rest_pose[None], None,
                                          hairstyle_ids=[0], info={"phase": 0, "hairstyles": [0],
                                                                   "global_batch_size": 1, "shard": [0, 1]})
                self._phase0.share = 1.0 / self.world_size  # replicated: every rank holds it
            return self._phase0
        lo, hi = self.shard(batch_size)
        # The random draws of the whole global batch (cheap, identical on every rank); only
        # samples lo..hi-1 are decoded, posed and placed below.
        if phase == 1:
            ids = [0] * batch_size
            fraction = min(max(float(progress), 0.0), 1.0)
            poses = self.rest_pose[None].repeat(batch_size, 1)
            rotations = []
            for i in range(batch_size):
                r = np.zeros(3) if g.uniform() < cfg.phase1_rest_fraction else self.head_rotation(g, fraction)
                rotations.append(r.tolist())
                # Same axis for both joints, so the head turns by r in total.
                for joint, share in (("neck", _NECK_SHARE), ("head", _HEAD_SHARE)):
                    j = 3 * JOINT[joint]
                    poses[i, j:j + 3] += torch.as_tensor(share * r, dtype=poses.dtype)
            betas = self.mean_betas[None].expand(batch_size, -1)
            trans = torch.zeros(batch_size, 3)
            keys = [None] * batch_size
            info.update(radius_fraction=fraction, head_rotations=rotations)
        else:
            ids = [int(i) for i in g.integers(0, num_hairstyles, size=batch_size)]
            pool = self._phase_entries(phase)
            picks = [int(i) for i in g.integers(0, len(pool), size=batch_size)]
            frames = [int(g.integers(0, self.entries[pool[p]].motion.num_frames)) for p in picks]
            poses = torch.stack([self.entries[pool[p]].motion.poses[f] for p, f in zip(picks, frames)])
            trans = torch.stack([self.entries[pool[p]].motion.trans[f] for p, f in zip(picks, frames)])
            betas = torch.stack([self.subject_betas[self.entries[pool[p]].subject] for p in picks])
            if phase == 3 and cfg.beta_noise_std > 0:
                betas = betas + _noise(g, cfg.beta_noise_std, betas)
                keys = [None] * batch_size
            else:
                keys = [(pool[p], f) for p, f in zip(picks, frames)]
            if cfg.long_hair_fraction > 0:
                # Drawn after everything else, so the poses of the batch are the paper's.
                long_pool = self.long_hairstyles(num_hairstyles)
                swap = g.uniform(size=batch_size) < cfg.long_hair_fraction
                repl = g.integers(0, max(len(long_pool), 1), size=batch_size)
                if long_pool:
                    ids = [long_pool[int(r)] if s else i for i, s, r in zip(ids, swap, repl)]
            info.update(motions=[self.entries[pool[p]].name for p in picks], frames=frames)
        info.update(hairstyles=ids, global_batch_size=batch_size, shard=[lo, hi])
        z, strands = self.hairstyles(ids[lo:hi])
        batch = self.place(z, strands, betas[lo:hi], poses[lo:hi], trans[lo:hi], hairstyle_ids=ids[lo:hi],
                           pose_keys=keys[lo:hi], build_body=build_body, info=info)
        batch.share = (hi - lo) / batch_size
        return batch

    def _phase_entries(self, phase: int) -> list[int]:
        if phase == 2:
            # "Full-body movements from a single dancer": the subject of the pool's first motion.
            subject = self.entries[0].subject
            return [i for i, e in enumerate(self.entries) if e.subject == subject]
        return list(range(len(self.entries)))

    # ------------------------------------------------------------------------------ dynamic
    def _draw_clip(self, g: np.random.Generator, frames: int, subsample: tuple[int, int]):
        """One random clip (entry, k, offset, start) with `frames` subsampled frames, or None."""
        e = int(g.integers(0, len(self.entries)))
        k = int(g.integers(subsample[0], subsample[1] + 1))
        offset = int(g.integers(0, k))
        length = len(range(offset, self.entries[e].motion.num_frames, k))
        if length < frames:
            return None
        start = int(g.integers(0, length - frames + 1))
        return e, k, offset, start

    def _clip_frames(self, clip, frames: int) -> np.ndarray:
        _, k, offset, start = clip
        return offset + k * (start + np.arange(frames))

    def clip_score(self, clip, frames: int) -> float:
        """`dynamic_score` of a clip: mean joint angular speed [rad/s] at the training dt."""
        e = self.entries[clip[0]]
        idx = torch.as_tensor(self._clip_frames(clip, frames))
        sub = Motion(poses=e.motion.poses[idx], trans=e.motion.trans[idx], betas=e.motion.betas,
                     fps=self.config.fps)
        return dynamic_score(sub)

    def dynamic_threshold(self, frames: int, subsample: tuple[int, int], candidates: int = 500,
                          quantile: float = 0.5) -> float:
        """The dynamic-score threshold of Section 4.2.2: the `quantile` (median) of the scores of
        `candidates` random clips. Drawn from `corpus_seed` only: the same on every rank.
        """
        key = (frames, tuple(subsample), candidates, quantile)
        if key not in self._thresholds:
            g = _generator(self.config.corpus_seed, _STREAM_THRESHOLD)
            scores = []
            for _ in range(candidates * _SEQUENCE_TRIES):
                clip = self._draw_clip(g, frames, subsample)
                if clip is not None:
                    scores.append(self.clip_score(clip, frames))
                if len(scores) == candidates:
                    break
            if not scores:
                raise ValueError(self._too_short(frames, subsample))
            self._thresholds[key] = float(np.quantile(np.asarray(scores), quantile))
        return self._thresholds[key]

    def _too_short(self, frames, subsample) -> str:
        longest = max(e.motion.num_frames for e in self.entries)
        return (f"frames: no motion has {frames} frames at an interval of {subsample[0]}..{subsample[1]} "
                f"(longest motion: {longest} frames)")

    def _windows(self, entry: int, k: int, offset: int, window: int) -> torch.Tensor:
        """Descriptor windows (L, T_w, D) of every frame of a subsampled motion, cached."""
        key = (entry, k, offset, window)
        if key not in self._descriptors:
            motion = self.entries[entry].motion
            poses = motion.poses[offset::k].to(torch.float64)
            # The interval k changes the frames, not dt: the motion plays k times faster
            # (Section 4.2.2 keeps dt = 1/60 s).
            self._descriptors[key] = motion_descriptor_windows(
                poses, motion.betas.to(torch.float64), 1.0 / self.config.fps, window, include_betas=False
            )
        return self._descriptors[key]

    def sequence_batch(
        self,
        step: int,
        batch_size: int,
        warmup_frames: int,
        rollout_frames: int,
        *,
        num_hairstyles: int = 1,
        subsample: tuple[int, int] = (2, 5),
        window: int = 10,
        dynamic_filter: bool = True,
        candidates: int = 500,
        quantile: float = 0.5,
        warmup_bodies: bool = False,
        long_hair_fraction: float = 0.0,
    ) -> SequenceBatch:
        """The batch of a dynamic-training step (Section 4.2.2).

        Each sequence: a random hairstyle of the pool, a random motion of the pool, one frame
        interval k in `subsample` (inclusive), a random start; redrawn (up to 64 times, then the
        most dynamic draw is kept) until its dynamic score reaches the threshold when
        `dynamic_filter`. Shapes: the motion's subject plus noise (`beta_noise_std`).

        Args:
            step: global step (keys the generator).
            batch_size: sequences of the global batch; this rank builds its share.
            warmup_frames: W frames without loss (>= 2).
            rollout_frames: R frames with loss (>= 1).
            num_hairstyles: hairstyle pool (corpus indices 0 .. n-1).
            subsample: (k_min, k_max) frame intervals.
            window: T_w.
            dynamic_filter: apply the dynamic-score filter.
            candidates: clips whose scores set the threshold.
            quantile: threshold quantile (0.5: the median).
            warmup_bodies: also build the warm-up frames' body meshes (a network that reads
                contact features needs them; the loss never does).
            long_hair_fraction: share of the sequences whose hairstyle is redrawn from the
                pool's long hairstyles (`long_hairstyles`, corpus parameter length >=
                `DataConfig.long_hair_length`); 0 (the paper): uniform over the pool. Drawn
                after everything else, so the clips and shapes are those of the uniform draw.

        Returns:
            SequenceBatch of this rank's sequences (all of them in a single process).
        """
        for name, value, low in (("batch_size", batch_size, 1), ("warmup_frames", warmup_frames, 2),
                                 ("rollout_frames", rollout_frames, 1), ("window", window, 1),
                                 ("num_hairstyles", num_hairstyles, 1)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
        fraction_ok = isinstance(long_hair_fraction, (int, float)) and not isinstance(long_hair_fraction, bool)
        if not (fraction_ok and 0.0 <= long_hair_fraction <= 1.0):
            raise ValueError(f"long_hair_fraction: expected a number in [0, 1], got {long_hair_fraction!r}")
        if long_hair_fraction > 0 and self.config.latent_source != "corpus":
            raise ValueError("long_hair_fraction: 0 unless latent_source is 'corpus' (sampled latents have no length)")
        subsample = (int(subsample[0]), int(subsample[1]))
        if not 1 <= subsample[0] <= subsample[1]:
            raise ValueError(f"subsample: expected 1 <= k_min <= k_max, got {subsample}")
        frames = warmup_frames + rollout_frames
        threshold = -math.inf
        if dynamic_filter:
            threshold = self.dynamic_threshold(frames, subsample, candidates, quantile)
        g = self.generator(_STREAM_SEQUENCE, step)
        cfg = self.config
        clips, scores = [], []
        for _ in range(batch_size):
            best, best_score = None, -math.inf
            for _ in range(_SEQUENCE_TRIES):
                clip = self._draw_clip(g, frames, subsample)
                if clip is None:
                    continue
                score = self.clip_score(clip, frames) if dynamic_filter else 0.0
                if score > best_score:
                    best, best_score = clip, score
                if score >= threshold:
                    break
            if best is None:
                raise ValueError(self._too_short(frames, subsample))
            clips.append(best)
            scores.append(best_score)
        ids = [int(i) for i in g.integers(0, num_hairstyles, size=batch_size)]
        betas = torch.stack([self.subject_betas[self.entries[c[0]].subject] for c in clips])
        if cfg.beta_noise_std > 0:
            betas = betas + _noise(g, cfg.beta_noise_std, betas)
        if long_hair_fraction > 0:
            # Drawn last (as in `static_batch`), so the clips and shapes are the uniform draw's.
            long_pool = self.long_hairstyles(num_hairstyles)
            swap = g.uniform(size=batch_size) < long_hair_fraction
            repl = g.integers(0, max(len(long_pool), 1), size=batch_size)
            if long_pool:
                ids = [long_pool[int(r)] if s else i for i, s, r in zip(ids, swap, repl)]
        info = {
            "motions": [self.entries[c[0]].name for c in clips],
            "intervals": [c[1] for c in clips],
            "starts": [c[3] for c in clips],
            "dynamic_scores": scores,
            "threshold": threshold if dynamic_filter else None,
            "hairstyles": ids,
            "global_batch_size": batch_size,
        }
        # Every rank drew the whole global batch above (cheap); it builds sequences lo..hi-1.
        first, stop = self.shard(batch_size)
        info["shard"] = [first, stop]
        clips, ids, betas = clips[first:stop], ids[first:stop], betas[first:stop]
        share = (stop - first) / batch_size
        batch_size = stop - first

        poses, trans, motion = [], [], []
        for e, k, offset, start in clips:
            idx = torch.as_tensor(self._clip_frames((e, k, offset, start), frames))
            poses.append(self.entries[e].motion.poses[idx])
            trans.append(self.entries[e].motion.trans[idx])
            motion.append(self._windows(e, k, offset, window)[start:start + frames])
        poses = torch.stack(poses).to(device=self.device, dtype=self.dtype)  # (B, T, 66)
        trans = torch.stack(trans).to(device=self.device, dtype=self.dtype)
        motion = torch.stack(motion).to(device=self.device, dtype=self.dtype)  # (B, T, T_w, D)
        betas = betas.to(device=self.device, dtype=self.dtype)
        z, strands = self.hairstyles(ids)

        def part(lo, hi, build_body):
            count = hi - lo

            def per_frame(x):
                tail = x.shape[1:]
                return x[:, None].expand(batch_size, count, *tail).reshape(batch_size * count, *tail)

            return self.place(
                per_frame(z), per_frame(strands), per_frame(betas),
                poses[:, lo:hi].reshape(-1, poses.shape[-1]), trans[:, lo:hi].reshape(-1, 3),
                hairstyle_ids=[i for i in ids for _ in range(count)], build_body=build_body,
            )

        return SequenceBatch(
            z=z, betas=betas, poses=poses, motion=motion,
            warmup=part(0, warmup_frames, warmup_bodies), rollout=part(warmup_frames, frames, True),
            intervals=[c[1] for c in clips], info=info, share=share,
        )


__all__ = ["HairBatch", "MOTION_DIM", "MotionEntry", "SequenceBatch", "TrainingSampler", "shard_bounds"]
