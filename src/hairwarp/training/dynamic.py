"""Dynamic training (HairFormer Section 4.2.2): the dynamic network on top of a frozen static one.

Per step, B sequences of W warm-up and R rollout frames (`TrainingSampler.sequence_batch`:
one frame every k = 2..5 frames per sequence, dynamic-score filtered, T_w = 10 motion
descriptors per frame, dt = 1/60 s):

  1. warm-up, without gradient: the GRU runs from a zero state over the W frames
     (`DynamicNetwork.simulate`); their drapes give the previous states of the first rollout
     frames and their last hidden state C_dyn starts the rollout;
  2. rollout: `simulate` over the R frames from that state, the GRU state carried frame to
     frame; drapes P(t) = apply_deformation(P_rigid(t), D_dyn(t), root_uv) (Eq. 2);
  3. loss (Eq. 6), averaged over the B x R frames: the static energy (Eq. 5) + the inertia
     term (Eq. 16) against P(t-1), P(t-2) **detached** (stop-gradient: the paper forbids
     back-propagation through previous states) + the functional regularization (Eq. 4).

Gradients flow through the GRU across the R rollout frames and stop at the warm-up:
truncated back-propagation through time over short rollouts (the paper does not state its
sequence length; R = 4 keeps a step affordable and the GRU still sees T_w = 10 frames of
motion history through its descriptors).
"""

from __future__ import annotations

import dataclasses

import torch

from hairwarp.energy import total_energy
from hairwarp.models import DynamicConfig, DynamicNetwork, apply_deformation, length_projection_of
from hairwarp.training import distributed
from hairwarp.training._common import (
    DTYPES,
    Trainer,
    load_training_checkpoint,
    stored_config,
    stored_seed,
    term_means,
)
from hairwarp.training.capture import CapturedLossStep, FixedHairBatch, capture_applies
from hairwarp.training.config import DynamicTrainingConfig, energy_config
from hairwarp.training.data import MOTION_DIM, SequenceBatch, TrainingSampler

_DYNAMIC_PRESETS = {
    "paper": {},
    "shipped": {"num_static_dynamic_layers": 3, "motion_hidden_dim": 256},
    "tiny": {"num_static_dynamic_layers": 1, "motion_hidden_dim": 32},
}


def inertia_history(
    warmup_positions: torch.Tensor, positions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The previous states of Eq. 16 for every rollout frame, without gradient.

    Args:
        warmup_positions: (B, W, M, N, 3) drapes of the warm-up frames (W >= 2).
        positions: (B, R, M, N, 3) drapes of the rollout frames.

    Returns:
        (prev, prev2), each (B, R, M, N, 3): P(t-1) and P(t-2) of rollout frame t, detached
        (stop-gradient, Section 3.4.5), taken from the warm-up for the first two frames.
    """
    if warmup_positions.dim() != 5 or positions.dim() != 5 or warmup_positions.shape[1] < 2:
        raise ValueError(
            "warmup_positions, positions: expected (B, W >= 2, M, N, 3) and (B, R, M, N, 3), got "
            f"{tuple(warmup_positions.shape)} and {tuple(positions.shape)}"
        )
    r = positions.shape[1]
    history = torch.cat([warmup_positions[:, -2:].detach(), positions.detach()], dim=1)  # (B, R + 2, ...)
    return history[:, 1:r + 1], history[:, :r]


def dynamic_loss(model: DynamicNetwork, batch: SequenceBatch, energy, clip: float | None = None,
                 inertia_time_step: str = "frame"):
    """Eq. 6 averaged over the rollout frames of a sequence batch (see the module docstring).

    Args:
        model: the dynamic network (its static network frozen inside).
        batch: the sequences.
        energy: the `EnergyConfig` (time_step = dt of Eq. 16).
        clip: optional clamp of each deformation component [m].
        inertia_time_step: "frame" (Eq. 16 with h = `energy.time_step` for every sequence) or
            "interval" (h = k * `energy.time_step` for a sequence sampled every k frames:
            its inertia term divided by k^2).

    Returns:
        (loss () tensor, terms {name: mean float, "func_reg" included},
        positions (B, R, M, N, 3)).
    """
    loss, terms, positions, _ = _dynamic_loss(model, batch, energy, clip, inertia_time_step)
    return loss, term_means(terms), positions


def _dynamic_loss(model, batch, energy, clip, inertia_time_step, **energy_options):
    """`dynamic_loss` with the terms as tensors (func_reg a 0-d one) and the hair-hair info,
    nothing read back to the host (a CUDA graph captures it); `energy_options` go to
    `total_energy`; `batch.intervals` may be a tensor.
    """
    b, w, r = batch.batch_size, batch.warmup_frames, batch.rollout_frames
    m, n = batch.rollout.rigid.shape[1], batch.rollout.rigid.shape[2]
    root_uv = batch.rollout.root_uv
    projection = length_projection_of(model)
    warm_contact = model.frame_contact_features(batch.warmup.rigid, root_uv, batch.warmup.inputs.body, b)
    contact = model.frame_contact_features(batch.rollout.rigid, root_uv, batch.rollout.inputs.body, b)
    with torch.no_grad():
        warm = model.simulate(batch.z, batch.betas, batch.poses[:, :w], batch.motion[:, :w], None, clip,
                              contact=warm_contact)
        warm_maps = warm.deformation_map.reshape(b * w, *warm.deformation_map.shape[2:])
        warm_positions = apply_deformation(batch.warmup.rigid, warm_maps, root_uv, projection).reshape(b, w, m, n, 3)
    out = model.simulate(batch.z, batch.betas, batch.poses[:, w:], batch.motion[:, w:], warm.hidden, clip,
                         contact=contact)
    maps = out.deformation_map.reshape(b * r, *out.deformation_map.shape[2:])
    positions = apply_deformation(batch.rollout.rigid, maps, root_uv, projection)  # (B * R, M, N, 3)
    prev, prev2 = inertia_history(warm_positions, positions.reshape(b, r, m, n, 3))
    inputs = dataclasses.replace(batch.rollout.inputs, prev=prev.reshape(b * r, m, n, 3),
                                 prev2=prev2.reshape(b * r, m, n, 3))
    if inertia_time_step == "interval":
        # Eq. 16 ~ 1 / h^2: a sequence sampled every k frames has h = k dt.
        k = torch.as_tensor(batch.intervals, dtype=positions.dtype, device=positions.device)
        scale = (1.0 / k**2).repeat_interleave(r)
        static = total_energy(positions, inputs, energy, **energy_options)
        inertia = total_energy(positions, inputs, energy, dynamic=True, terms=("inertia",), **energy_options)
        total = static.total + inertia.total * scale
        terms = {**static.terms, "inertia": inertia.terms["inertia"] * scale}
        info = static.hair_hair_info
    else:
        result = total_energy(positions, inputs, energy, dynamic=True, **energy_options)
        total, terms, info = result.total, dict(result.terms), result.hair_hair_info
    func_reg = model.functional_regularization(out.static_features)
    terms["func_reg"] = func_reg.detach()
    return total.mean() + func_reg, terms, positions.reshape(b, r, m, n, 3), info


class _CapturedDynamicStep:
    """A dynamic training step's forward and backward (warm-up, rollout, Eq. 6) for one shape of
    sequence batch, replayed from a CUDA graph (`hairwarp.training.capture`): the warm-up and
    rollout frames in fixed buffers, each with one uncropped body refit per batch (the warm-up's
    only when the network reads contact features), the intervals a device tensor.

    Args:
        trainer: the `DynamicTrainer`.
        batch: a sequence batch whose frames carry `body_vertices`.
        capacity: hair-hair pair-buffer capacity; None: sized from `batch`.
    """

    def __init__(self, trainer, batch: SequenceBatch, capacity: int | None = None):
        cfg = trainer.config
        faces = trainer.sampler.body_faces
        self.shape = self._shape(batch)
        self.warmup = FixedHairBatch(batch.warmup, faces, with_body=batch.warmup.inputs.body is not None)
        self.rollout = FixedHairBatch(batch.rollout, faces)
        rigid = batch.rollout.rigid
        self.intervals = torch.as_tensor(batch.intervals, dtype=rigid.dtype).to(rigid.device)
        self.batch = dataclasses.replace(batch, z=batch.z.clone(), betas=batch.betas.clone(), poses=batch.poses.clone(),
                                         motion=batch.motion.clone(), warmup=self.warmup.batch,
                                         rollout=self.rollout.batch, intervals=self.intervals)
        energy = trainer.energy()

        def evaluate(graph_safe, capacity):
            loss, terms, _, info = _dynamic_loss(trainer.model, self.batch, energy, cfg.deformation_clip,
                                                 cfg.inertia_time_step, graph_safe=graph_safe,
                                                 hair_hair_capacity=capacity)
            return loss, terms, info

        b, m, n = rigid.shape[:3]
        self.step = CapturedLossStep(trainer.model, evaluate, b * m * (n - 1), capacity)

    @staticmethod
    def _shape(batch: SequenceBatch):
        return (tuple(batch.poses.shape), tuple(batch.motion.shape), tuple(batch.warmup.rigid.shape),
                tuple(batch.rollout.rigid.shape), batch.warmup.inputs.body is not None)

    def matches(self, batch: SequenceBatch) -> bool:
        """Whether `batch` has the shapes this step holds (its bodies carried: `capture_applies`)."""
        return self._shape(batch) == self.shape

    def __call__(self, batch: SequenceBatch):
        """Copy `batch` in, replay: (loss () tensor, terms {name: tensor}); gradients in `.grad`."""
        fixed = self.batch
        for dst, src in ((fixed.z, batch.z), (fixed.betas, batch.betas), (fixed.poses, batch.poses),
                         (fixed.motion, batch.motion)):
            dst.copy_(src)
        self.intervals.copy_(torch.as_tensor(batch.intervals, dtype=self.intervals.dtype))
        self.warmup.copy_from(batch.warmup)
        self.rollout.copy_from(batch.rollout)
        return self.step.run()


def dynamic_model_config(config: DynamicTrainingConfig, static_config) -> DynamicConfig:
    """The DynamicConfig of a run: preset, `model` overrides, the static network's config, and
    the data's motion-descriptor size (132) and window T_w.
    """
    fields = {**_DYNAMIC_PRESETS[config.model_preset], **config.model}
    try:
        return DynamicConfig(static=static_config, motion_dim=MOTION_DIM, window=config.window, **fields)
    except TypeError as exc:
        raise ValueError(f"model: {exc}") from None


class DynamicTrainer(Trainer):
    """Trains a dynamic network (Section 4.2.2).

    Args:
        config: the run's settings; None with `resume` or `init` takes the checkpoint's.
        out: output folder (config.toml, log.jsonl, checkpoint.pt); None writes nothing.
        device: torch device.
        seed: seeds the new layers' initialisation and the sampler (a resume keeps the
            checkpoint's seed).
        rank: this process's rank; world_size: number of ranks (> 1: DDP over the running
            process group, see `StaticTrainer`).
        resume: a dynamic checkpoint to continue from (weights, optimizer state, step),
            written at any world size.
        init: a dynamic checkpoint whose weights start a new run (fresh optimizer, step 0):
            fine-tuning.
        sampler: a ready `TrainingSampler`; None builds it from the config.

    Without `resume`/`init` the network is `DynamicNetwork.from_static` around the static
    checkpoint `config.static_checkpoint` (frozen; the dynamic head starts as its head).

    Raises:
        ValueError: on a bad config, a missing or mismatched checkpoint.
    """

    kind = "dynamic"

    def __init__(
        self,
        config: DynamicTrainingConfig | None = None,
        *,
        out=None,
        device: torch.device | str = "cpu",
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        resume=None,
        init=None,
        sampler: TrainingSampler | None = None,
    ):
        if resume is not None and init is not None:
            raise ValueError("resume, init: give one or the other")
        device = torch.device(device)
        self.device = device
        distributed.check_process_group(rank, world_size)
        source = resume if resume is not None else init
        ckpt = None
        if source is not None:
            self._before_resume()
            dtype = DTYPES[config.dtype if config is not None else "float32"]
            ckpt = load_training_checkpoint(source, device, dtype, ("dynamic",))
            if resume is not None:
                seed = stored_seed(ckpt, seed)
            if config is None:
                config = stored_config(ckpt, DynamicTrainingConfig)
                if config is None:
                    raise ValueError("checkpoint: stores no training config; pass config")
        if config is None:
            config = DynamicTrainingConfig()
        if not isinstance(config, DynamicTrainingConfig):
            raise ValueError(f"config: expected a DynamicTrainingConfig, got {type(config).__name__}")
        self.config = config
        self.dtype = DTYPES[config.dtype]
        if sampler is None:
            sampler = TrainingSampler(config.data, seed=seed, rank=rank, world_size=world_size, device=device,
                                      dtype=self.dtype)
        elif (sampler.config != config.data or sampler.dtype != self.dtype or sampler.device != device
              or (sampler.seed, sampler.rank, sampler.world_size) != (seed, rank, world_size)):
            raise ValueError("sampler: built for another data config, dtype, device, seed or rank")
        self.sampler = sampler

        if ckpt is not None:
            model = ckpt.model  # moved to the config's dtype below (float64 runs store float32 weights)
        else:
            if not config.static_checkpoint:
                raise ValueError("static_checkpoint: dynamic training needs a trained static network "
                                 "(--static-checkpoint or static_checkpoint = ... in the config)")
            self._before_resume()  # the static checkpoint may be this run's rank 0's fresh output
            static = load_training_checkpoint(config.static_checkpoint, device, self.dtype, ("static",)).model
            torch.manual_seed(seed)
            model = DynamicNetwork.from_static(static, dynamic_model_config(config, static.config))
        scfg = model.config.static
        if scfg.num_vertices != sampler.num_vertices or scfg.latent_dim != sampler.latent_dim:
            raise ValueError(
                f"data: the network predicts N = {scfg.num_vertices} vertices from {scfg.latent_dim}-d "
                f"latents, the data has N = {sampler.num_vertices} and {sampler.latent_dim}-d latents"
            )
        if model.config.window != config.window or model.config.motion_dim != MOTION_DIM:
            raise ValueError(
                f"window: the network reads T_w = {model.config.window} descriptor frames of size "
                f"{model.config.motion_dim}; the config asks T_w = {config.window} (size {MOTION_DIM})"
            )
        self.model = model.to(device=device, dtype=self.dtype)
        self.model.train()
        self.optimizer = torch.optim.Adam(self.model.trainable_parameters(), lr=config.learning_rate)
        if resume is not None and ckpt.optimizer_state is not None:
            ckpt.restore_optimizer(self.optimizer)
            for group in self.optimizer.param_groups:
                group["lr"] = config.learning_rate
        self._setup_run(out, seed, rank, world_size, ckpt.step if resume is not None else 0)
        self._captured = None  # the step's CUDA graph (`captured_loss`), made at the first step

    @property
    def total_steps(self) -> int:
        return self.config.steps

    def next_batch(self, step: int) -> SequenceBatch:
        cfg = self.config
        return self.sampler.sequence_batch(
            step, cfg.batch_size, cfg.warmup_frames, cfg.rollout_frames, num_hairstyles=cfg.hairstyles,
            subsample=(cfg.subsample_min, cfg.subsample_max), window=cfg.window,
            dynamic_filter=cfg.dynamic_filter, candidates=cfg.dynamic_candidates,
            quantile=cfg.dynamic_quantile, warmup_bodies=self.model.static.config.contact_samples > 0,
            long_hair_fraction=cfg.long_hair_fraction,
        )

    def energy(self):
        """The run's `EnergyConfig`: b_p fixed, Eq. 16's dt the motions' frame time by default."""
        cfg = self.config
        fixed = {"barrier_join_fraction": cfg.barrier_join_fraction}
        if "time_step" not in cfg.energy:
            # Eq. 16's dt is the frame time the motions are played at (1/60 s in the paper).
            fixed["time_step"] = 1.0 / cfg.data.fps
        return energy_config(cfg.energy, **fixed)

    def _extras(self, batch: SequenceBatch) -> dict:
        # The global batch's size and intervals (every rank drew them all).
        cfg = self.config
        return {"bp": cfg.barrier_join_fraction, "batch_size": batch.info.get("global_batch_size", batch.batch_size),
                "intervals": list(batch.info.get("intervals", batch.intervals))}

    def compute_loss(self, batch: SequenceBatch, step: int, model: DynamicNetwork | None = None):
        cfg = self.config
        loss, terms, _ = dynamic_loss(self.model if model is None else model, batch, self.energy(),
                                      cfg.deformation_clip, cfg.inertia_time_step)
        return loss, terms, self._extras(batch)

    def captured_loss(self, batch: SequenceBatch, step: int):
        """The step's loss through `_CapturedDynamicStep` (gradients left in `.grad`), or None
        where it does not apply (see `hairwarp.training.capture.capture_applies`); a new capture
        for new shapes, a batch that overflowed the hair-hair buffer redone with twice its pairs.
        """
        if not capture_applies(self, batch.rollout):
            return None
        if self._captured is None or not self._captured.matches(batch):
            self._captured = None  # its graph's memory first
            self._captured = _CapturedDynamicStep(self, batch)
        loss, terms = self._captured(batch)
        needed = self._captured.step.overflowed()
        if needed:
            self._captured = None
            self._captured = _CapturedDynamicStep(self, batch, capacity=2 * needed)
            loss, terms = self._captured(batch)
        return loss, term_means(terms), self._extras(batch)


def train_dynamic(
    config: DynamicTrainingConfig | None = None,
    out=None,
    *,
    device: torch.device | str = "cpu",
    seed: int = 0,
    resume=None,
    steps: int | None = None,
    progress: bool = True,
) -> DynamicTrainer:
    """Train a dynamic network from `config.static_checkpoint` and write its checkpoint.

    Args:
        config: settings (the checkpoint's on resume when None).
        out: output folder (None: nothing written).
        device: torch device ("cuda" under torchrun: each rank's cuda:LOCAL_RANK).
        seed: initialisation and sampling seed.
        resume: a dynamic checkpoint (file or folder) to continue from.
        steps: run at most this many steps (None: `config.steps`).
        progress: show the progress bar.

    Returns:
        The trainer.

    Under torchrun (WORLD_SIZE > 1) this joins the data-parallel run, as `train_static` does.
    """
    ctx = distributed.init_distributed(device)  # under torchrun: join the data-parallel run
    trainer = DynamicTrainer(config, out=out, device=ctx.device, seed=seed, rank=ctx.rank,
                             world_size=ctx.world_size, resume=resume)
    try:
        trainer.train(steps, progress=progress)
    finally:
        trainer.close()
    return trainer


__all__ = ["DynamicTrainer", "dynamic_loss", "dynamic_model_config", "inertia_history", "train_dynamic"]
