"""Static training: the four-phase curriculum of HairFormer Section 4.2.1 (and Quaffure's).

Loss (Eq. 5): the batch mean of the static energy of the drape
    P = apply_deformation(P_rigid, net(z, beta, Theta), root_uv)        (Eq. 2, Section 4.2.3)
scored by `hairwarp.energy.total_energy` (every strand term, hair-body contact through the
Warp kernels, hair-hair contact when its weight is non-zero).

Curriculum: phase 0 one rest body and one hairstyle; phase 1 the same with head rotations
sampled on ellipsoids whose radii grow over the phase; phase 2 `phase2_hairstyles` hairstyles
and the motions of one subject; phase 3 `phase3_hairstyles`, every motion and subject, noisy
shapes (`TrainingSampler.static_batch`). The contact barrier's join fraction b_p is annealed
from 0.9 to 0.01 over the whole run (`barrier_schedule`), and deformations are clipped at
0.01 m during the first `clip_steps` steps (phase 0 by default). The Quaffure (adapted)
baseline trains on exactly this loss and curriculum (Section 4.3.1).
"""

from __future__ import annotations

import dataclasses
import math
import os

import torch
from torch import nn

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.energy import total_energy
from hairwarp.models import (
    QuaffureConfig,
    QuaffureNetwork,
    StaticConfig,
    StaticNetwork,
    apply_deformation,
    length_projection_of,
)
from hairwarp.models.contact_features import network_deformation
from hairwarp.training import distributed
from hairwarp.training.capture import CapturedLossStep, FixedHairBatch, capture_applies, refit_body
from hairwarp.training._common import (
    DTYPES,
    Trainer,
    load_training_checkpoint,
    resolve_checkpoint,
    stored_config,
    stored_seed,
    term_means,
)
from hairwarp.training.config import LOSS_NORMALIZATION_FLOOR, StaticTrainingConfig, energy_config
from hairwarp.training.data import HairBatch, TrainingSampler


# The pool's converged teachers, beside a run's checkpoint (`StaticTrainingConfig.teacher_pool`).
TEACHERS_NAME = "teachers.pt"
# What a pool teacher depends on besides its batch and its start (`StaticTrainer(teachers_from=)`).
TEACHER_FIELDS = ("teacher_iterations", "teacher_pool", "teacher_kind", "teacher_start", "teacher_settle_time",
                  "teacher_settle_time_step", "batch_size", "energy")


def barrier_schedule(
    step: int, total_steps: int, start: float = 0.9, end: float = 0.01, kind: str = "linear"
) -> float:
    """b_p of the contact barrier at `step` (Section 4.2.1: 0.9 at the start, 0.01 at the end).

    Args:
        step: 0-based step index.
        total_steps: steps of the run (the last step, total_steps - 1, gets `end`).
        start: b_p at step 0.
        end: b_p at the last step.
        kind: "linear" interpolation, or "geometric" (linear in log b_p: more steps near the
            small values that resolve the last penetrations).

    Returns:
        b_p, between `start` and `end` (steps past the end get `end`).
    """
    if not isinstance(total_steps, int) or total_steps < 1:
        raise ValueError(f"total_steps: expected a positive int, got {total_steps!r}")
    if not isinstance(step, int) or step < 0:
        raise ValueError(f"step: expected a non-negative int, got {step!r}")
    for name, value in (("start", start), ("end", end)):
        if not 0.0 < float(value) < 1.0:
            raise ValueError(f"{name}: expected a value in (0, 1), got {value!r}")
    t = 1.0 if total_steps == 1 else min(step / (total_steps - 1), 1.0)
    if kind == "linear":
        return float(start + (end - start) * t)
    if kind == "geometric":
        return float(math.exp(math.log(start) + (math.log(end) - math.log(start)) * t))
    raise ValueError(f"kind: expected 'linear' or 'geometric', got {kind!r}")


def curriculum_phase(step: int, phase_steps) -> tuple[int, float]:
    """The curriculum phase of `step` and the position in it.

    Args:
        step: 0-based step index.
        phase_steps: steps of phases 0-3 (zero skips a phase).

    Returns:
        (phase, progress): progress in [0, 1] is (step - phase start + 1) / phase length, so the
        phase's last step has 1 (phase 1 then reaches its full radii). Steps past the end stay
        in the last non-empty phase with progress 1.
    """
    if not isinstance(step, int) or step < 0:
        raise ValueError(f"step: expected a non-negative int, got {step!r}")
    start = 0
    last = None
    for phase, length in enumerate(phase_steps):
        if length <= 0:
            continue
        last = phase
        if step < start + length:
            return phase, (step - start + 1) / length
        start += length
    if last is None:
        raise ValueError(f"phase_steps: expected at least one step, got {tuple(phase_steps)}")
    return last, 1.0


_STATIC_PRESETS = {"paper": StaticConfig, "shipped": StaticConfig.shipped, "tiny": StaticConfig.tiny}
_QUAFFURE_PRESETS = {"paper": QuaffureConfig, "shipped": QuaffureConfig, "tiny": QuaffureConfig.tiny}


def model_config(config: StaticTrainingConfig, latent_dim: int = 512):
    """The network config of a run: the preset, the `model` overrides, and the data's sizes
    (latent_dim = d_z of the hair basis, num_vertices = `data.num_vertices`).
    """
    presets = _STATIC_PRESETS if config.model_kind == "static" else _QUAFFURE_PRESETS
    base = presets[config.model_preset]()
    fixed = {"latent_dim": latent_dim, "num_vertices": config.data.num_vertices}
    clash = sorted(k for k in fixed if k in config.model and config.model[k] != fixed[k])
    if clash:
        raise ValueError(f"model: {clash} follow the data ({fixed}); remove them from [model]")
    try:
        return dataclasses.replace(base, **{**config.model, **fixed})
    except TypeError as exc:
        raise ValueError(f"model: {exc}") from None


def build_model(config: StaticTrainingConfig, latent_dim: int = 512) -> nn.Module:
    """A fresh StaticNetwork or QuaffureNetwork for `config` (seed torch first)."""
    cfg = model_config(config, latent_dim)
    return StaticNetwork(cfg) if config.model_kind == "static" else QuaffureNetwork(cfg)


def static_loss(model: nn.Module, batch: HairBatch, energy, clip: float | None = None, normalization: str = "none",
                teacher_weight: float = 0.0):
    """Eq. 5 averaged over the batch for the drapes a static network predicts, plus the
    distillation term toward `batch.teacher` when it holds drapes and `teacher_weight` > 0.

    Args:
        model: a StaticNetwork or QuaffureNetwork (forward(z, beta, theta, clip) -> map).
        batch: the samples (latents, shapes, poses, rigid placement, energy inputs).
        energy: the `EnergyConfig` (b_p of this step inside).
        clip: optional clamp of each deformation component [m].
        normalization: "none", "rigid" or "inverse" (`StaticTrainingConfig.loss_normalization`).
        teacher_weight: [1/m^2] (`StaticTrainingConfig.teacher_weight`).

    Returns:
        (loss () tensor, terms {name: batch-mean float; "teacher" the distillation term},
        positions (B, M, N, 3)).
    """
    loss, result, positions = _static_loss(model, batch, energy, clip, normalization, teacher_weight)
    return loss, term_means(result.terms), positions


def teacher_term(positions: torch.Tensor, teacher: torch.Tensor, weight: float) -> torch.Tensor:
    """The distillation term per sample (B,): `weight` [1/m^2] times the mean squared distance
    [m^2] of the free vertices (2..N-1) of `positions` to `teacher`, both (B, M, N, 3).
    """
    gap = (positions - teacher)[:, :, NUM_FIXED_VERTICES:]
    return weight * gap.square().sum(dim=-1).mean(dim=(1, 2))


def _static_loss(model, batch, energy, clip, normalization, teacher_weight=0.0, **energy_options):
    """`static_loss` with the `EnergyResult` in place of the terms' means (nothing read back to
    the host: a CUDA graph captures it); `energy_options` go to `total_energy`. The distillation
    term, when it applies, is added to the normalised energy and to `result.terms` ("teacher").
    """
    deformation = network_deformation(model, batch.z, batch.betas, batch.poses, batch.rigid, batch.root_uv,
                                      batch.inputs.body, clip)
    positions = apply_deformation(batch.rigid, deformation, batch.root_uv, length_projection_of(model))
    result = total_energy(positions, batch.inputs, energy, **energy_options)
    if normalization == "inverse":
        weight = 1.0 / (1.0 + result.total.detach().abs())
        loss = (result.total * weight).mean()
    elif normalization == "rigid":
        with torch.no_grad():
            scale = total_energy(batch.rigid, batch.inputs, energy, **energy_options).total.abs()
            scale = scale + LOSS_NORMALIZATION_FLOOR
        loss = (result.total / scale).mean()
    else:
        loss = result.total.mean()
    if batch.teacher is not None and teacher_weight > 0:
        distillation = teacher_term(positions, batch.teacher, teacher_weight)
        result.terms["teacher"] = distillation.detach()
        loss = loss + distillation.mean()
    return loss, result, positions


class _DrapeTeacher:
    """The distillation targets of a training batch (`StaticTrainingConfig.teacher_iterations`):
    the network's own drapes (no gradient) refined by K iterations of the physics' static drape
    (`hairwarp.solvers.physics.PhysicsSolver`, the energy at b_p = `bp_end`, the physics' own
    barrier, not the step's annealed one).

    One solver serves every batch of one shape: its buffers (rigid placement, rest lengths, scalp
    normals, one uncropped body refit to the batch's poses) are written before each solve, so
    on CUDA its two graphs (start, K iterations) are captured once. A batch without
    `body_vertices` (built with its cropped bodies) gets a solver of its own.
    """

    def __init__(self, trainer):
        self.trainer = trainer
        self.solver = None
        self.shape = None
        # With two starts, per solved batch: which start won per sample, both teachers' energies,
        # the rigid placement's share of free vertices inside the body and the mean strand length
        # (what decides the choice, for the diagnosis of docs/network_diagnosis.md).
        self.choices: list[dict] = []

    def _physics_config(self):
        from hairwarp.solvers.physics import PhysicsConfig

        config = self.trainer.config
        k = config.teacher_iterations
        if config.teacher_pool > 0:  # converged once per pool batch: the static drape's chunks and restarts
            return PhysicsConfig(static_max_iterations=k)
        return PhysicsConfig(static_max_iterations=k, static_chunk=k)

    def _make_solver(self, batch: HairBatch, body):
        from hairwarp.solvers.physics import PhysicsSolver

        config = self.trainer.config
        energy = energy_config(config.energy, barrier_join_fraction=config.bp_end)
        rest = batch.inputs.rest_lengths.detach().clone()
        return PhysicsSolver(rest, batch.rigid.detach(), batch.inputs.scalp_normals, body, energy,
                             self._physics_config(), dynamic=False)

    def __call__(self, batch: HairBatch, clip) -> torch.Tensor:
        """(B, M, N, 3) the teacher's drapes of `batch` [m]."""
        model = self.trainer.model
        if batch.body_vertices is None:
            solver = self._make_solver(batch, batch.inputs.body)
        else:
            shape = (tuple(batch.rigid.shape), tuple(batch.body_vertices.shape))
            if self.solver is None or self.shape != shape:
                self.solver = None
                body = refit_body(batch, self.trainer.sampler.body_faces)
                self.solver, self.shape = self._make_solver(batch, body), shape
            solver = self.solver
            solver.inputs.rest_lengths.copy_(batch.inputs.rest_lengths)
            solver.set_frame(batch.rigid, batch.inputs.scalp_normals, batch.body_vertices)
        config = self.trainer.config
        starts = []
        if config.teacher_start != "rigid":
            with torch.no_grad():
                deformation = network_deformation(model, batch.z, batch.betas, batch.poses, batch.rigid,
                                                  batch.root_uv, solver.body, clip)
                starts.append(apply_deformation(batch.rigid, deformation, batch.root_uv, length_projection_of(model)))
        # Per sample, whether the rigid start may be taken ("lower_where_clean", and
        # "rigid_where_clean" without the energy test: only where the rigid placement has no free
        # vertex inside the body).
        rigid_allowed = rigid_inside = None
        if config.teacher_start in ("lower", "lower_where_clean", "rigid_where_clean"):
            from hairwarp.ops import hair_body_signed_distance

            with torch.no_grad():
                free = hair_body_signed_distance(batch.rigid.detach(), solver.body)[:, :, NUM_FIXED_VERTICES:]
            rigid_inside = (free < 0).flatten(1).double().mean(dim=1) * 100.0
            if config.teacher_start in ("lower_where_clean", "rigid_where_clean"):
                rigid_allowed = rigid_inside == 0
        if config.teacher_start in ("rigid", "lower") or (rigid_allowed is not None and bool(rigid_allowed.any())):
            starts.append(batch.rigid)
        best = best_energy = None
        for start in starts:
            solver.solve(start.detach(), config.teacher_iterations)
            if len(starts) == 1:
                return self._settled(solver, solver.positions())
            x = solver.positions().detach().clone()
            with torch.no_grad():
                energy = total_energy(x, solver.inputs, energy_config(config.energy,
                                                                      barrier_join_fraction=config.bp_end)).total
            if best is None:
                best, best_energy = x, energy
            else:  # per sample, the teacher of lower energy (or, "rigid_where_clean", of a clean start)
                lower = energy < best_energy
                if config.teacher_start == "rigid_where_clean":
                    lower = rigid_allowed
                elif rigid_allowed is not None:
                    lower = lower & rigid_allowed
                self.choices.append({
                    "rigid_chosen": lower.tolist(), "energy_network_start": best_energy.tolist(),
                    "energy_rigid_start": energy.tolist(), "rigid_inside_percent": rigid_inside.tolist(),
                    "mean_strand_length_m":
                        batch.inputs.rest_lengths.sum(dim=-1).mean(dim=-1).expand(lower.shape[0]).tolist()})
                best = torch.where(lower[:, None, None, None], x, best)
                best_energy = torch.where(lower, energy, best_energy)
        return self._settled(solver, best)

    def _settled(self, solver, drape: torch.Tensor) -> torch.Tensor:
        """`drape` brought to rest with its pose held (`StaticTrainingConfig.teacher_settle_time`;
        `hairwarp.solvers.physics.drape_at_rest` from it), or as it is.
        """
        from dataclasses import replace

        from hairwarp.solvers.physics import drape_at_rest, settling_solver

        settle = self.trainer.config.teacher_settle_time
        if settle <= 0:
            return drape
        config = replace(solver.config, settle_time=settle)
        energy = solver.energy_config.replace(time_step=self.trainer.config.teacher_settle_time_step)
        dynamic = settling_solver(solver.inputs.rest_lengths, solver.rigid, solver.normals, solver.body, energy, config)
        return drape_at_rest(solver, dynamic, drape.detach(), config).positions


class _MapTeacher:
    """The distillation targets of `StaticTrainingConfig.teacher_kind` "map": the drapes of each
    sample's best deformation map, L-BFGS (strong Wolfe) over the map through the network's own
    `apply_deformation` (taper and projection) from the network's map, on the energy at b_p =
    `bp_end`. The network can reach these drapes exactly; the physics' optimum it cannot (its
    positions are free, the network's map is 8 x 8 cells shared by their strands).
    """

    def __init__(self, trainer):
        self.trainer = trainer
        self.body = None
        self.shape = None

    def _body(self, batch: HairBatch):
        if batch.body_vertices is None:
            return batch.inputs.body
        shape = tuple(batch.body_vertices.shape)
        if self.body is None or self.shape != shape:
            self.body, self.shape = refit_body(batch, self.trainer.sampler.body_faces), shape
        else:
            self.body.update(batch.body_vertices)
        return self.body

    def __call__(self, batch: HairBatch, clip) -> torch.Tensor:
        """(B, M, N, 3) the drapes of the best maps of `batch` [m]."""
        config, model = self.trainer.config, self.trainer.model
        body = self._body(batch)
        inputs = dataclasses.replace(batch.inputs, body=body)
        energy = energy_config(config.energy, barrier_join_fraction=config.bp_end)
        projection = length_projection_of(model)
        with torch.no_grad():
            start = network_deformation(model, batch.z, batch.betas, batch.poses, batch.rigid, batch.root_uv, body,
                                        clip)
        deformation = start.detach().clone().requires_grad_(True)
        optimizer = torch.optim.LBFGS([deformation], lr=1.0, max_iter=config.teacher_iterations, history_size=20,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-14)

        def closure():
            optimizer.zero_grad()
            positions = apply_deformation(batch.rigid, deformation, batch.root_uv, projection)
            total = total_energy(positions, inputs, energy).total.sum()
            total.backward()
            return total

        with torch.enable_grad():
            optimizer.step(closure)
        with torch.no_grad():
            return apply_deformation(batch.rigid, deformation.detach(), batch.root_uv, projection)


class _CapturedStaticStep:
    """A static training step's forward and backward for one batch shape and clip, replayed from
    a CUDA graph (`hairwarp.training.capture`); b_p is a device scalar written before each
    replay (`total_energy(barrier_join_fraction=)`).

    Args:
        trainer: the `StaticTrainer` (its model, config and sampler's body faces).
        batch: a batch with `body_vertices`, whose shapes every later batch shares.
        clip: the deformation clip the graph holds (None: none).
        bp: b_p for the sizing call.
        capacity: hair-hair pair-buffer capacity; None: sized from `batch`.
    """

    def __init__(self, trainer, batch: HairBatch, clip, bp: float, capacity: int | None = None):
        config = trainer.config
        self.clip, self.shape = clip, tuple(batch.rigid.shape)
        self.fixed = FixedHairBatch(batch, trainer.sampler.body_faces)
        self.bp = torch.full((1,), bp, dtype=batch.rigid.dtype, device=batch.rigid.device)
        energy = energy_config(config.energy, barrier_join_fraction=bp)  # b_p read from self.bp

        def evaluate(graph_safe, capacity):
            loss, result, _ = _static_loss(trainer.model, self.fixed.batch, energy, clip, config.loss_normalization,
                                           config.teacher_weight, graph_safe=graph_safe, hair_hair_capacity=capacity,
                                           barrier_join_fraction=self.bp)
            return loss, result.terms, result.hair_hair_info

        b, m, n = self.shape[:3]
        self.step = CapturedLossStep(trainer.model, evaluate, b * m * (n - 1), capacity)

    def matches(self, batch: HairBatch, clip) -> bool:
        """Whether `batch` (its shapes) and `clip` are the ones this step holds (its bodies
        carried: `capture_applies`).
        """
        return tuple(batch.rigid.shape) == self.shape and clip == self.clip

    def __call__(self, batch: HairBatch, bp: float):
        """Copy `batch` in, replay: (loss () tensor, terms {name: (B,) tensor}); the gradients
        are left in the parameters' `.grad`.
        """
        self.fixed.copy_from(batch)
        self.bp.fill_(bp)
        return self.step.run()


class StaticTrainer(Trainer):
    """Trains a static network (or the Quaffure baseline) through the curriculum.

    Args:
        config: the run's settings; None with `resume` takes the checkpoint's.
        out: output folder (config.toml, log.jsonl, checkpoint.pt); None writes nothing.
        device: torch device.
        seed: seeds the network's initialisation and the sampler; a resumed run keeps the
            checkpoint's seed, so it draws the batches the uninterrupted run would have.
        rank: this process's rank (it builds its share of each global batch; rank 0 writes
            the files).
        world_size: number of ranks; > 1 needs the process group running
            (`hairwarp.training.distributed.init_distributed`, as `train_static` does under
            torchrun) and wraps the loss in DistributedDataParallel.
        resume: a checkpoint (file or run folder) to continue from: weights, optimizer
            state and step; it may come from a run with another world size.
        init: a checkpoint whose network's weights start a new run (a fresh optimizer, step 0):
            a static or Quaffure run's, or a dynamic one's (its frozen static network, as the
            shipped `hairformer_dynamic.pt` holds it). Its network must be the config's.
        sampler: a ready `TrainingSampler` (tests share one); None builds it from the config.
        scene_factory: builds the learning curve's held-out scenes
            (`hairwarp.evaluation.scenes.comparison_scene`, which the layers keep out of this
            package's imports); None scores the training batch only (`config.curve_every`).
        teachers_from: another pool run's folder (or its `TEACHERS_NAME` file): its saved pool
            teachers are this run's, not solved again (a settled pool of 32 took ~5 min of an
            H100): a variant of that run (another teacher weight, learning rate or length) on
            the same data, seed, batch size, pool and teacher settings (`TEACHER_FIELDS`),
            started from the same network.

    Raises:
        ValueError: on a bad config, a checkpoint of another model kind or sizes.
    """

    def __init__(
        self,
        config: StaticTrainingConfig | None = None,
        *,
        out=None,
        device: torch.device | str = "cpu",
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        resume=None,
        sampler: TrainingSampler | None = None,
        scene_factory=None,
        init=None,
        teachers_from=None,
    ):
        if resume is not None and init is not None:
            raise ValueError("resume, init: give one or the other")
        device = torch.device(device)
        self.device = device
        distributed.check_process_group(rank, world_size)
        ckpt = None
        if resume is not None:
            self._before_resume()
            dtype = DTYPES[(config.dtype if config is not None else "float32")]
            ckpt = load_training_checkpoint(resume, device, dtype, ("static", "quaffure"))
            seed = stored_seed(ckpt, seed)
            if config is None:
                config = stored_config(ckpt, StaticTrainingConfig)
                if config is None:
                    raise ValueError("resume: the checkpoint stores no training config; pass config")
        if config is None:
            config = StaticTrainingConfig()
        if not isinstance(config, StaticTrainingConfig):
            raise ValueError(f"config: expected a StaticTrainingConfig, got {type(config).__name__}")
        self.config = config
        self.kind = config.model_kind
        self.dtype = DTYPES[config.dtype]
        if sampler is None:
            sampler = TrainingSampler(config.data, seed=seed, rank=rank, world_size=world_size, device=device,
                                      dtype=self.dtype)
        elif (sampler.config != config.data or sampler.dtype != self.dtype or sampler.device != device
              or (sampler.seed, sampler.rank, sampler.world_size) != (seed, rank, world_size)):
            raise ValueError("sampler: built for another data config, dtype, device, seed or rank")
        self.sampler = sampler
        expected = model_config(config, sampler.latent_dim)
        if init is not None:
            self.model = _initial_network(init, expected, config.model_kind).to(device=device, dtype=self.dtype)
        elif ckpt is not None:
            if type(ckpt.model).kind != config.model_kind or ckpt.config != expected:
                raise ValueError(
                    f"resume: the checkpoint's network differs from the config's {config.model_kind} "
                    "network (kind or sizes)"
                )
            # A config stored in the checkpoint may ask for float64 where the checkpoint was
            # loaded before the config was known (weights are stored as float32 either way).
            self.model = ckpt.model.to(dtype=self.dtype)
        else:
            torch.manual_seed(seed)
            self.model = build_model(config, sampler.latent_dim).to(device=device, dtype=self.dtype)
        self.model.train()
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.learning_rate)
        if ckpt is not None and ckpt.optimizer_state is not None:
            ckpt.restore_optimizer(self.optimizer)
            for group in self.optimizer.param_groups:
                group["lr"] = config.learning_rate
        self._setup_run(out, seed, rank, world_size, 0 if ckpt is None else ckpt.step)
        self._captured = None  # the step's CUDA graph (`captured_loss`), made at the first step
        self._teacher = None  # the distillation's solver (`training_batch`), made at the first step
        self._pool_teachers: dict[tuple, torch.Tensor] = {}  # (phase, pool index) -> converged drapes
        # (phase, pool index) -> the pool batch's rigid placement summed, where its teacher was solved
        self._pool_rigid_sums: dict[tuple, float] = {}
        self._pool_checked: set[tuple] = set()  # the keys whose teacher matched its batch here
        if teachers_from is not None and resume is not None:
            raise ValueError("teachers_from, resume: give one or the other (a resumed run keeps its own teachers)")
        if teachers_from is not None and config.teacher_pool == 0:
            raise ValueError("teachers_from: only a run with teacher_pool > 0 takes a pool's teachers")
        if resume is not None and config.teacher_pool > 0:
            self._load_pool_teachers(os.path.dirname(resolve_checkpoint(resume)))
        elif teachers_from is not None:
            self._load_pool_teachers(teachers_from, required=True)
        if config.curve_every > 0:
            from hairwarp.training.monitor import LearningCurve

            self.curve = LearningCurve(self, scene_factory)

    @property
    def total_steps(self) -> int:
        return self.config.total_steps

    def schedule(self, step: int) -> dict:
        """Phase, progress in it, b_p and the deformation clip of `step`."""
        cfg = self.config
        phase, progress = curriculum_phase(step, cfg.phase_steps)
        bp = barrier_schedule(step, cfg.total_steps, cfg.bp_start, cfg.bp_end, cfg.bp_schedule)
        clip = cfg.deformation_clip if step < cfg.clip_until else None
        return {"phase": phase, "progress": progress, "bp": bp, "clip": clip}

    def next_batch(self, step: int, build_body: bool = True) -> HairBatch:
        """The batch of `step`: the sampler's, or with `teacher_pool` P the sampler's batch of step
        `step % P` in `step`'s phase.
        """
        cfg = self.config
        s = self.schedule(step)
        pool = {2: cfg.phase2_hairstyles, 3: cfg.phase3_hairstyles}.get(s["phase"], 1)
        drawn = step % cfg.teacher_pool if cfg.teacher_pool > 0 else step
        return self.sampler.static_batch(drawn, s["phase"], s["progress"], cfg.batch_size, pool, build_body)

    def training_batch(self, step: int) -> HairBatch:
        """`next_batch`, without the body meshes when the step is captured (it refits its own),
        with the teacher's drapes when the run distils (`StaticTrainingConfig.teacher_iterations`;
        with `teacher_pool`, each pool batch's converged drapes are solved once and kept).
        """
        cfg = self.config
        batch = self.next_batch(step, build_body=not capture_applies(self))
        if cfg.teacher_iterations > 0:
            if self._teacher is None:
                self._teacher = (_MapTeacher if cfg.teacher_kind == "map" else _DrapeTeacher)(self)
            s = self.schedule(step)
            key = (s["phase"], step % cfg.teacher_pool) if cfg.teacher_pool > 0 else None
            teacher = self._pool_teachers.get(key) if key is not None else None
            if teacher is None:
                teacher = self._teacher(batch, s["clip"])
                if key is not None:  # kept: a copy, the solver's buffers serve the next batch
                    teacher = self._pool_teachers[key] = teacher.clone()
                    self._pool_rigid_sums[key] = float(batch.rigid.double().sum())
                    self._pool_checked.add(key)
            elif key not in self._pool_checked and key in self._pool_rigid_sums:
                # a saved teacher, checked once against the batch it was solved for
                if teacher.shape != batch.rigid.shape or not math.isclose(
                        float(batch.rigid.double().sum()), self._pool_rigid_sums[key], rel_tol=1e-5, abs_tol=1e-3):
                    raise ValueError(f"teachers_from: pool batch {key[1]} of phase {key[0]} is not the batch its "
                                     "saved teacher was solved for (another seed, data config, batch size or pool)")
                self._pool_checked.add(key)
            batch.teacher = teacher
        return batch

    def save(self, path=None) -> str | None:
        """`Trainer.save`, and with `teacher_pool` the pool's teachers solved so far beside the
        checkpoint (`TEACHERS_NAME`), so that a resumed run trains on the same targets.
        """
        written = super().save(path)
        if written is not None and self._pool_teachers:
            target = os.path.join(os.path.dirname(written), TEACHERS_NAME)
            record = {"teachers": {f"{p}:{i}": t.detach().cpu() for (p, i), t in self._pool_teachers.items()},
                      "rigid_sums": {f"{p}:{i}": v for (p, i), v in self._pool_rigid_sums.items()},
                      "teacher_config": self._teacher_config()}
            torch.save(record, target + ".tmp")
            os.replace(target + ".tmp", target)
        return written

    def _teacher_config(self) -> dict:
        """The config fields a pool teacher depends on (besides the network it starts from)."""
        return {name: getattr(self.config, name) for name in TEACHER_FIELDS}

    def _load_pool_teachers(self, folder, required: bool = False) -> None:
        """The pool's teachers saved in `folder` (`TEACHERS_NAME`, or that file itself): a resumed
        run's own, or another run's (`teachers_from`: same data, seed, batch size, pool and teacher
        settings, so that each pool batch is the one its teacher was solved for; checked per batch
        by its rigid placement when it is drawn). None saved: solved again as drawn (`required`:
        an error).
        """
        path = folder if os.path.isfile(folder) else os.path.join(folder, TEACHERS_NAME)
        if not os.path.isfile(path):
            if required:
                raise ValueError(f"teachers_from: no {TEACHERS_NAME} at {folder!r}")
            return
        record = torch.load(path, map_location="cpu", weights_only=True)
        if "teachers" not in record:  # written before the record held its config and batch sums
            record = {"teachers": record, "rigid_sums": {}, "teacher_config": None}
        stored = record["teacher_config"]
        if required and stored is not None and stored != self._teacher_config():
            changed = sorted(k for k in TEACHER_FIELDS if stored.get(k) != getattr(self.config, k))
            raise ValueError(f"teachers_from: the teachers were solved with other settings ({', '.join(changed)})")
        for key, teacher in record["teachers"].items():
            phase, index = (int(v) for v in key.split(":"))
            self._pool_teachers[(phase, index)] = teacher.to(device=self.device, dtype=self.dtype)
            if key in record["rigid_sums"]:
                self._pool_rigid_sums[(phase, index)] = float(record["rigid_sums"][key])

    def captured_loss(self, batch: HairBatch, step: int):
        """The step's loss through `_CapturedStaticStep` (gradients left in `.grad`): (loss, terms,
        extras) like `compute_loss`, or None where it does not apply (`cuda_graph` off, not CUDA,
        data-parallel, a batch without `body_vertices`). Captures again for a new batch shape or
        clip, and redoes a batch that overflowed the hair-hair buffer with twice its pairs.
        """
        if not capture_applies(self, batch):
            return None
        s = self.schedule(step)
        if self._captured is None or not self._captured.matches(batch, s["clip"]):
            self._captured = None  # its graph's memory first
            self._captured = _CapturedStaticStep(self, batch, s["clip"], s["bp"])
        loss, terms = self._captured(batch, s["bp"])
        needed = self._captured.step.overflowed()
        if needed:
            self._captured = None
            self._captured = _CapturedStaticStep(self, batch, s["clip"], s["bp"], capacity=2 * needed)
            loss, terms = self._captured(batch, s["bp"])
        size = batch.info.get("global_batch_size", batch.batch_size)
        return loss, term_means(terms), {"phase": s["phase"], "bp": s["bp"], "clip": s["clip"], "batch_size": size}

    def compute_loss(self, batch: HairBatch, step: int, model: nn.Module | None = None):
        s = self.schedule(step)
        energy = energy_config(self.config.energy, barrier_join_fraction=s["bp"])
        loss, terms, _ = static_loss(self.model if model is None else model, batch, energy, s["clip"],
                                     self.config.loss_normalization, self.config.teacher_weight)
        size = batch.info.get("global_batch_size", batch.batch_size)
        extras = {"phase": s["phase"], "bp": s["bp"], "clip": s["clip"], "batch_size": size}
        return loss, terms, extras


def _initial_network(init, expected, kind: str) -> nn.Module:
    """The network of checkpoint `init` (a dynamic one's frozen static network) for `StaticTrainer`'s
    `init`; its config must be `expected`.
    """
    from hairwarp.models.checkpoint import load_checkpoint

    model = load_checkpoint(resolve_checkpoint(init), "cpu").model
    if type(model).kind == "dynamic":
        model = model.static
    if type(model).kind != kind or model.config != expected:
        raise ValueError(f"init: {init} holds a {type(model).kind} network of other sizes or settings than the "
                         f"config's {kind} network")
    return model.requires_grad_(True).train()  # a dynamic network's static one is frozen


def train_static(
    config: StaticTrainingConfig | None = None,
    out=None,
    *,
    device: torch.device | str = "cpu",
    seed: int = 0,
    resume=None,
    steps: int | None = None,
    progress: bool = True,
    scene_factory=None,
) -> StaticTrainer:
    """Train a static network (or Quaffure, `config.model_kind`) and write its checkpoint.

    Under torchrun (RANK, WORLD_SIZE, LOCAL_RANK set, WORLD_SIZE > 1) this joins the
    data-parallel run (`hairwarp.training.distributed`): each rank trains on its device with
    its share of every global batch of `config.batch_size`; rank 0 writes the files. Otherwise
    it trains in this process alone.

    Args:
        config: settings (`StaticTrainingConfig()` when None, or the checkpoint's on resume).
        out: output folder for config.toml, log.jsonl and checkpoint.pt (None: none).
        device: torch device ("cuda" under torchrun: each rank's cuda:LOCAL_RANK).
        seed: initialisation and sampling seed.
        resume: checkpoint (file or folder) to continue from (any world size wrote it).
        steps: run at most this many steps (None: to the end of the curriculum).
        progress: show the progress bar (rank 0).
        scene_factory: the learning curve's held-out scenes (see `StaticTrainer`).

    Returns:
        The trainer (its `model`, `history`, `step`).
    """
    ctx = distributed.init_distributed(device)  # under torchrun: join the data-parallel run
    trainer = StaticTrainer(config, out=out, device=ctx.device, seed=seed, rank=ctx.rank,
                            world_size=ctx.world_size, resume=resume, scene_factory=scene_factory)
    try:
        trainer.train(steps, progress=progress)
    finally:
        trainer.close()
    return trainer


__all__ = [
    "StaticTrainer",
    "barrier_schedule",
    "build_model",
    "curriculum_phase",
    "model_config",
    "static_loss",
    "train_static",
]
