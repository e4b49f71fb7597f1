"""Training the inertial step (`hairwarp.models.inertial`) on physics trajectories: distillation by rollouts.

Data: clips (a grown preset hairstyle on the default body, a motion window), each simulated once
by the implicit-Euler physics (method "physics", the teacher) and draped frame by frame by the
equilibrium method (the static network by default); both cached per clip in `out/clips/`, so a
resumed run does not simulate again.

Loss, per step, over every training clip: the step rolls the clip out from its first frame's
equilibrium at rest, on its own predictions, and back-propagates through the whole clip (no
stop-gradient: the teacher's trajectory is the target, not Eq. 16 on the step's own past, which
ranks a swing-free trajectory above the physics: docs/network_diagnosis.md, D5). The loss is

    swing_weight * |swing(x) - swing(physics)|^2 + position_weight * |x - physics|^2,

mean over frames and vertices, where swing(x) = (x - P_rigid) minus its mean over the clip: what
the hair does beyond following the head (`hairwarp.metrics.tip_swing`, for every vertex). The
swing term makes the step learn the dynamics even where the equilibrium (the static network)
differs from the physics' by a constant offset.

Learning curve: every `eval_every` steps the motion metrics (`hairwarp.metrics.motion_fidelity`)
of the held-out clips are written to `out/log.jsonl` beside the loss. `out/checkpoint.pt` holds
the step, its optimizer and the step count: `resume=` continues the same run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from dataclasses import dataclass, field

import torch

from hairwarp.config import EnergyConfig
from hairwarp.models.checkpoint import load_checkpoint, save_checkpoint
from hairwarp.models.inertial import InertialConfig, InertialStep
from hairwarp.scene.scalp import root_subset
from hairwarp.solvers.physics import PhysicsConfig

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.jsonl"


@dataclass(frozen=True)
class ClipSpec:
    """One clip: a preset hairstyle grown around the rest body, a motion window, a size.

    Attributes:
        hairstyle: preset name (`hairwarp.scene.hairstyles.list_hairstyle_presets()`), grown
            around the default body at rest (hairstyle seed 0, as the comparison scenes').
        motion: "head_moves" (`hairwarp.scene.motion.random_head_moves`) or a procedural
            motion's name (`list_motions()`).
        seed: the motion's draw (the moves of "head_moves"; the jitter of a procedural motion,
            None for its nominal form).
        start, end: the window kept [s] (end None: the motion's end; "head_moves" lasts `end`).
    """

    hairstyle: str
    motion: str
    seed: int | None = 0
    start: float = 0.0
    end: float | None = 1.5

    @property
    def key(self) -> str:
        return f"{self.hairstyle}_{self.motion}{'' if self.seed is None else self.seed}_{self.start:g}_{self.end}"


@dataclass
class InertialTrainingConfig:
    """A training run of the inertial step.

    Attributes:
        clips: the training clips (`ClipSpec` or dicts of its fields).
        held_out: the clips of the learning curve, never trained on.
        strand_stride: keep one root in this many of the 32 x 32 scalp, spread over it (4: 256 strands).
        num_vertices: vertices per strand.
        equilibrium: the method giving E(t) per frame ("static": the static network), or
            "optimum": each frame's static optimum (the physics' drape of the frame; what a
            perfect static network would give).
        steps: Adam steps.
        learning_rate: Adam's.
        swing_weight, position_weight: the loss's two terms (module docstring).
        eval_every: steps between learning-curve points (and checkpoints).
        grad_clip: the gradient's norm is clipped to this (0: not clipped). The chain step's
            rollouts at 256 strands had gradient norms of 0.4-200 from step to step (one clip of
            long straight hair, 2-core CPU), where the per-vertex step's were 0.03-0.05: a few
            targets land within a few per cent of a segment of the last projected vertex, and
            follow-the-leader's gradient grows as the inverse of that distance.
        projection_max_gain: 0, the exact gradient; else follow-the-leader's adjoint with each
            vertex's gain l_i / |p_i - x_(i-1)| capped at this (`follow_the_leader(max_gain=...)`;
            the forward stays exact). The chain step at 256 strands on the 2-core CPU (two clips):
            capped at 3 the gradient's norm stayed at 1e-4 to 5e-4 and the loss fell from 3.02e-3
            to 2.67e-3 by step 50 and stayed there to step 100. The identity's gradient
            (straight-through, tried) reached the same loss by step 70 and then rose to 2.82e-3 by
            step 300 (docs/network_diagnosis.md, "Fifteenth session").
        model: `InertialConfig` fields.
    """

    clips: list = field(default_factory=lambda: [ClipSpec("medium_wavy", "head_moves", s) for s in range(4)])
    held_out: list = field(default_factory=lambda: [ClipSpec("medium_wavy", "whiplash", None, 0.35, 1.0)])
    strand_stride: int = 4
    num_vertices: int = 100
    equilibrium: str = "static"
    steps: int = 300
    learning_rate: float = 3e-3
    swing_weight: float = 1.0
    position_weight: float = 0.3
    eval_every: int = 50
    grad_clip: float = 0.0
    projection_max_gain: float = 0.0
    model: dict = field(default_factory=dict)

    def __post_init__(self):
        self.clips = [c if isinstance(c, ClipSpec) else ClipSpec(**c) for c in self.clips]
        self.held_out = [c if isinstance(c, ClipSpec) else ClipSpec(**c) for c in self.held_out]
        if not self.clips:
            raise ValueError("clips: expected at least one training clip")
        for name in ("strand_stride", "num_vertices", "steps", "eval_every"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(f"{name}: expected a positive int, got {value!r}")
        for name in ("learning_rate", "swing_weight", "position_weight", "grad_clip", "projection_max_gain"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value >= 0:
                raise ValueError(f"{name}: expected a non-negative number, got {value!r}")
        InertialConfig(**self.model)  # fails early on a bad field

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@functools.lru_cache(maxsize=8)
def _grown(hairstyle: str):
    """The default scene of a preset and the preset grown around its rest body (full size)."""
    from hairwarp.scene.scene import default_scene, preset_hairstyle

    base = default_scene(hairstyle, seed=0)
    return base, preset_hairstyle(hairstyle, base.body, base.scalp, seed=0, grow_around_body=True)


def clip_scene(spec: ClipSpec, strand_stride: int, num_vertices: int):
    """The `Scene` of a clip (see `ClipSpec`): one strand in `strand_stride`, spread over the
    scalp (`root_subset`), resampled to `num_vertices`. ClipSpec("medium_wavy", "whiplash",
    None, 0.35, 1.0) is the comparison scene whiplash, ClipSpec("long_straight", "torso_bend", None, 0.3, 1.3) torso_bend.
    """
    from hairwarp.scene.motion import procedural_motion, random_head_moves
    from hairwarp.scene.scene import Scene

    base, style = _grown(spec.hairstyle)
    if spec.motion == "head_moves":
        motion = random_head_moves(spec.seed or 0, duration=spec.end or 1.5)
    else:
        motion = procedural_motion(spec.motion, seed=spec.seed)
        a = int(round(spec.start * motion.fps))
        b = motion.num_frames if spec.end is None else min(int(round(spec.end * motion.fps)) + 1, motion.num_frames)
        motion = motion.replace(poses=motion.poses[a:b].clone(), trans=motion.trans[a:b].clone())
    keep = root_subset(style.num_strands, base.scalp.resolution, strand_stride)
    return Scene(body=base.body, scalp=base.scalp, hairstyle=style.subset(keep, num_vertices), motion=motion,
                 name=spec.key)


def clip_trajectories(scene, equilibrium: str = "static", device: torch.device | str = "cpu") -> dict:
    """{"rigid", "physics", "equilibrium"}: (T, M, N, 3) float32 CPU tensors [m] of a scene's frames
    (`InertialTrainingConfig.equilibrium` names E(t)).
    """
    from hairwarp.methods import make

    frames = scene.frames(device=device)
    if equilibrium == "optimum":
        balance = make("physics").drape(frames)
    else:
        balance = make(equilibrium).simulate(frames)
    return {"rigid": frames.rigid.positions.detach().float().cpu(),
            "physics": make("physics").simulate(frames).positions.detach().float().cpu(),
            "equilibrium": balance.positions.detach().float().cpu()}


def swing_of(x: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
    """Every vertex's offset from the rigid placement minus its mean over the frames: (T, M, N, 3)."""
    offset = x - rigid
    return offset - offset.mean(dim=0, keepdim=True)


class InertialTrainer:
    """Trains an `InertialStep` (module docstring).

    Args:
        config: the run; None with `resume` takes the checkpoint's.
        out: output folder (clips/, checkpoint.pt, log.jsonl); None keeps the clips in memory.
        device: where the rollouts run (the clips are simulated there too).
        seed: seeds the step's initialisation.
        resume: a checkpoint.pt (or its folder) of this kind of run to continue.
        progress: progress bars.
        clip_cache: the folder of the simulated clips (None: out/clips); runs that share it
            simulate each clip once.
    """

    def __init__(self, config: InertialTrainingConfig | None = None, *, out=None, device="cpu", seed: int = 0,
                 resume=None, progress: bool = True, clip_cache=None):
        self.device = torch.device(device)
        self.out = None if out is None else os.fspath(out)
        self.clip_cache = os.fspath(clip_cache) if clip_cache is not None else (
            None if self.out is None else os.path.join(self.out, "clips"))
        self.progress = progress
        self.step_count = 0
        ckpt = None
        if resume is not None:
            path = os.path.join(resume, CHECKPOINT_NAME) if os.path.isdir(resume) else os.fspath(resume)
            if not os.path.isfile(path):
                raise ValueError(f"resume: no checkpoint at {path!r}")
            ckpt = load_checkpoint(path, self.device)
            if ckpt.config is None or not isinstance(ckpt.model, InertialStep):
                raise ValueError(f"resume: {path!r} holds no inertial step")
            stored = (ckpt.extra or {}).get("training")
            if config is None:
                if stored is None:
                    raise ValueError("resume: the checkpoint stores no training config; pass config")
                config = InertialTrainingConfig(**stored)
        config = InertialTrainingConfig() if config is None else config
        if not isinstance(config, InertialTrainingConfig):
            raise ValueError(f"config: expected an InertialTrainingConfig, got {type(config).__name__}")
        self.config = config
        if ckpt is not None:
            self.model = ckpt.model.train()
            self.step_count = ckpt.step
        else:
            torch.manual_seed(seed)
            self.model = InertialStep(InertialConfig(**config.model)).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.learning_rate)
        if ckpt is not None and ckpt.optimizer_state is not None:
            ckpt.restore_optimizer(self.optimizer)
        for folder in (self.out, self.clip_cache):
            if folder is not None:
                os.makedirs(folder, exist_ok=True)
        self.train_clips = [self._clip(c) for c in config.clips]
        self.held_out_clips = [self._clip(c) for c in config.held_out]
        # All training clips rolled out as one: strands are independent in the step, so clips of
        # the same length are stacked along the strand axis.
        self._batches = _stack_by_length(self.train_clips)

    def _clip(self, spec: ClipSpec) -> dict:
        cfg = self.config
        # The physics' settling (`PhysicsConfig.settle_time`) and the strands its means divide by
        # (`EnergyConfig.reference_strand_count`) change the clips: a cache is read only by runs
        # of the same physics.
        physics = f"settle{PhysicsConfig().settle_time:g}_R{EnergyConfig().reference_strand_count}"
        name = f"{spec.key}_s{cfg.strand_stride}_n{cfg.num_vertices}_{cfg.equilibrium}_{physics}.pt"
        path = None if self.clip_cache is None else os.path.join(self.clip_cache, name)
        if path is not None and os.path.isfile(path):
            data = torch.load(path, weights_only=True)
        else:
            start = time.perf_counter()
            data = clip_trajectories(clip_scene(spec, cfg.strand_stride, cfg.num_vertices), cfg.equilibrium,
                                     self.device)
            if self.progress:
                print(f"clip {spec.key}: {data['rigid'].shape[0]} frames x {data['rigid'].shape[1]} strands simulated "
                      f"in {time.perf_counter() - start:.1f} s", flush=True)
            if path is not None:
                torch.save(data, path)
        return {"spec": spec, **{k: v.to(self.device) for k, v in data.items()}}

    def loss(self, batch: dict) -> torch.Tensor:
        """The loss (module docstring) of one stacked batch of clips."""
        cfg = self.config
        x = self.model.rollout(batch["equilibrium"], batch["rigid"])
        swing = (swing_of(x, batch["rigid"]) - swing_of(batch["physics"], batch["rigid"])).square().sum(-1).mean()
        position = (x - batch["physics"]).square().sum(-1).mean()
        return cfg.swing_weight * swing + cfg.position_weight * position

    @torch.no_grad()
    def evaluate(self) -> dict:
        """`motion_fidelity` of each held-out clip, and of the equilibrium alone for comparison."""
        from hairwarp.metrics import motion_fidelity

        out = {}
        for clip in self.held_out_clips:
            x = self.model.rollout(clip["equilibrium"], clip["rigid"])
            keep = ("mean_distance_mm", "swing_correlation", "swing_amplitude_ratio", "physics_swing_mm")
            ours = motion_fidelity(x, clip["physics"], clip["rigid"])
            eq = motion_fidelity(clip["equilibrium"], clip["physics"], clip["rigid"])
            out[clip["spec"].key] = {**{k: ours[k] for k in keep},
                                     **{f"equilibrium_{k}": eq[k] for k in keep[:3]}}
        return out

    def train(self, steps: int | None = None) -> InertialStep:
        """Run up to `steps` more steps (None: to `config.steps`); checkpoint and log every `eval_every`."""
        cfg = self.config
        end = cfg.steps if steps is None else min(cfg.steps, self.step_count + steps)
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=end, initial=self.step_count, desc="train inertial", dynamic_ncols=True)
        self.model.train()
        self.model.projection_max_gain = cfg.projection_max_gain or None
        while self.step_count < end:
            self.optimizer.zero_grad()
            loss = sum(self.loss(b) for b in self._batches) / len(self._batches)
            loss.backward()
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
            self.optimizer.step()
            self.step_count += 1
            record = {"step": self.step_count, "loss": float(loss.detach())}
            if self.step_count % cfg.eval_every == 0 or self.step_count == end:
                record["held_out"] = self.evaluate()
                self.save()
            self._log(record)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{float(loss.detach()):.3e}")
        if bar is not None:
            bar.close()
        self.model.projection_max_gain = None
        return self.model

    def save(self, path=None) -> None:
        """Write the checkpoint (the step, its optimizer, the step count, the training config)."""
        if path is None:
            if self.out is None:
                return
            path = os.path.join(self.out, CHECKPOINT_NAME)
        save_checkpoint(path, self.model, optimizer=self.optimizer, step=self.step_count,
                        extra={"training": self.config.to_dict()})

    def _log(self, record: dict) -> None:
        if self.out is not None:
            with open(os.path.join(self.out, LOG_NAME), "a") as f:
                f.write(json.dumps(record) + "\n")


def _stack_by_length(clips: list[dict]) -> list[dict]:
    groups: dict[tuple, list[dict]] = {}
    for clip in clips:
        groups.setdefault((clip["rigid"].shape[0], clip["rigid"].shape[2]), []).append(clip)
    return [{k: torch.cat([c[k] for c in group], dim=1) for k in ("rigid", "physics", "equilibrium")}
            for group in groups.values()]


def read_log(out) -> list[dict]:
    """The records of a run's log.jsonl (the learning curve)."""
    with open(os.path.join(os.fspath(out), LOG_NAME)) as f:
        return [json.loads(line) for line in f if line.strip()]


__all__ = ["ClipSpec", "InertialTrainer", "InertialTrainingConfig", "clip_scene", "clip_trajectories", "read_log",
           "swing_of"]
