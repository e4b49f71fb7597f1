"""Training settings of the HairFormer networks (Sections 4.1, 4.2): dataclasses, TOML, `--set`.

Three dataclasses hold every knob of a run, each phase size a field (the paper's 1 000 / 20 000
hair latents and its AMASS dancers are targets for a GPU cluster, not requirements on a laptop):

    DataConfig              what the sampler draws: hair subset, latents, motions, body shapes.
    StaticTrainingConfig    the four-phase curriculum of the static network (Section 4.2.1) and
                            of the Quaffure (adapted) baseline (same loss, Section 4.3.1).
    DynamicTrainingConfig   the dynamic network (Section 4.2.2) and the fine-tuning (Fig. 4).

Paper defaults (Section 4.1, 4.2): Adam, learning rate 1e-4, batch 32; dt = 1/60 s, T_w = 10,
one frame every 2-5 frames per sequence, dynamic-score filter at the median of 500 sequences;
b_p annealed from 0.9 to 0.01; deformations clipped at 0.01 m early in static training.

A config round-trips through plain dicts (`to_dict` / `from_dict`), TOML files (`load_config`,
`write_toml`) and command-line overrides `key=value` with dotted keys for nested tables
(`apply_overrides(cfg, ["data.num_vertices=20", "phase_steps=[2, 2, 0, 0]"])`); values are
TOML literals, a bare word is a string, and `none` sets an optional field to None.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tomllib
from dataclasses import dataclass, field
from typing import Any

from hairwarp.config import EnergyConfig
from hairwarp.models import DynamicConfig, QuaffureConfig, StaticConfig
from hairwarp.scene.motion import DEFAULT_FPS, list_motions

MODEL_PRESETS = ("paper", "shipped", "tiny")
STATIC_MODEL_KINDS = ("static", "quaffure")
BP_SCHEDULES = ("linear", "geometric")
LOSS_NORMALIZATIONS = ("none", "rigid", "inverse")
TEACHER_KINDS = ("physics", "map")
# Where the physics teacher's solve starts (`StaticTrainingConfig.teacher_start`).
TEACHER_STARTS = ("network", "rigid", "lower", "lower_where_clean", "rigid_where_clean")
INERTIA_TIME_STEPS = ("interval", "frame")
# Energy added to the rigid placement's before dividing by it ("rigid" normalization): keeps
# samples that start at rest (energy near its minimum) from being magnified.
LOSS_NORMALIZATION_FLOOR = 1.0
LATENT_SOURCES = ("corpus", "sample")
DTYPES = ("float32", "float64")
SCALP_GRID = 32  # roots per side of the scalp grid (Section 3.1: 32 x 32 = 1024 strands)


# ------------------------------------------------------------------------------------ checks
def _fail(owner: str, name: str, expected: str, value) -> None:
    raise ValueError(f"{owner}.{name}: expected {expected}, got {value!r}")


def _int(owner: str, name: str, value, minimum: int = 0) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        _fail(owner, name, f"an int >= {minimum}", value)


def _number(owner: str, name: str, value, minimum: float = 0.0, *, strict: bool = False,
            maximum=None) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > minimum if strict else value >= minimum)
    ok = ok and (maximum is None or value <= maximum)
    if not ok:
        bound = f"> {minimum}" if strict else f">= {minimum}"
        bound += "" if maximum is None else f" and <= {maximum}"
        _fail(owner, name, f"a finite number {bound}", value)


def _choice(owner: str, name: str, value, choices) -> None:
    if value not in choices:
        _fail(owner, name, f"one of {list(choices)}", value)


# ------------------------------------------------------------------------------------ base
class _TrainingConfig:
    """Dict round trip with validation and type coercion from TOML / command-line values."""

    def to_dict(self) -> dict:
        """The settings as plain data: dicts, lists, str, numbers, bools and None."""
        return _plain(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict):
        """Build the config from `to_dict`'s output (or a parsed TOML file).

        Missing keys keep their defaults; ints are accepted for float fields, lists for tuple
        fields, and the string "none" for optional fields.

        Raises:
            ValueError: on a key that is not a field (named), or a value that fails validation.
        """
        if not isinstance(data, dict):
            raise ValueError(f"{cls.__name__}: expected a table (dict), got {type(data).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown setting(s) {unknown}; known: {sorted(fields)}")
        defaults = cls()
        kwargs = {}
        for name, value in data.items():
            default = getattr(defaults, name)
            kwargs[name] = _coerce(cls.__name__, name, value, default, fields[name])
        return cls(**kwargs)

    def replace(self, **changes):
        """A validated copy with some fields changed."""
        return dataclasses.replace(self, **changes)


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _optional(f: dataclasses.Field) -> bool:
    return "None" in str(f.type)


def _coerce(owner: str, name: str, value, default, f: dataclasses.Field):
    if isinstance(value, str) and value.lower() in ("none", "null") and _optional(f):
        return None
    if isinstance(default, _TrainingConfig):
        if isinstance(value, type(default)):
            return value
        return type(default).from_dict(value)
    if isinstance(default, tuple) and isinstance(value, list):
        return tuple(value)
    if isinstance(default, list) and isinstance(value, tuple):
        return list(value)
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if default is None and isinstance(value, int) and not isinstance(value, bool) and "float" in str(f.type):
        return float(value)
    return value


# ------------------------------------------------------------------------------------ data
@dataclass
class DataConfig(_TrainingConfig):
    """What the training sampler draws (`hairwarp.training.data.TrainingSampler`).

    Attributes:
        strand_stride: keep every k-th root of the 32 x 32 scalp grid along u and v (1: all
            1024 strands; 4: an 8 x 8 sub-grid of 64) to train faster; the network still sees
            the full latent and predicts the full deformation map.
        num_vertices: N, vertices per strand; the decoded strands (100 vertices) are resampled
            by arc length when this differs (the network's N follows it).
        latent_source: "corpus": z = encode(procedural hairstyle i) with random parameters
            (`sample_hairstyle_params`), so z lies on the family the basis was fitted on;
            "sample": z ~ N(0, latent_scale^2 I). Either way P_init = decode(z) (Section 3.1:
            the initial hair is generated from z), so z and the physics agree exactly.
        latent_scale: standard deviation of the "sample" latents.
        corpus_seed: seed of the hairstyle corpus, the subjects and the dynamic-score
            threshold: the same on every rank and run.
        motions: procedural motions in the pool (`hairwarp.scene.motion.list_motions()`).
        motion_variants: jittered copies of each procedural motion (variant 0 the nominal
            motion); variant v is performed by subject v mod num_subjects.
        amass_paths: AMASS `.npz` files added to the pool (each file one sequence; files with
            equal betas are one subject).
        num_subjects: size of the representative set of body shapes (the "dancers"); phases
            0-2 use their mean shape, phase 3 and dynamic training each subject's shape plus
            noise.
        shape_std: standard deviation of the representative betas (SMPL units).
        beta_noise_std: Gaussian noise added to betas in phase 3 and dynamic training.
        long_hair_fraction: share of each phase-2/3 batch drawn from the long hairstyles of the
            pool (corpus parameter length >= `long_hair_length`); 0 (the paper): uniform over
            the pool. The log-uniform corpus has ~16 % of hairstyles >= 0.4 m, so without it the
            long, deep-start hair of phase 0-1 grows rare later and is forgotten
            (docs/training_diagnosis.md, H7).
        long_hair_length: the length [m] from which a corpus hairstyle counts as long.
        grown_hair_fraction: share of the corpus hairstyles (picked per index, the same on
            every rank and run) whose P_init are their generated strands grown around the rest
            body (`generate_hairstyle(..., body=...)`, as the comparison scenes' hairstyles
            are), with z = encode(those strands), instead of decode(z). The networks then meet
            the hair they drape at evaluation: strands resting on the shoulders and back, which
            the latent reconstructs only to ~2-5 cm, its decode lying inside the body
            (docs/training_diagnosis.md, H20-H21). 0 (the paper): P_init = decode(z) always.
        head_rotation_radii: semi-axes [rad] of the phase-1 ellipsoid of head rotation vectors
            about x (nod), y (turn) and z (tilt), reached at the end of phase 1.
        phase1_rest_fraction: share of phase-1 samples kept at the rest pose (no rotation),
            so the rest drape is not forgotten while the radii grow.
        fps: frame rate the motions are played at [1/s] (60: dt = 1/60 s, Section 4.2.2).
        crop_body: crop each posed body to the triangles the hair can reach (no change to any
            contact result, fewer triangles to query).
        pose_cache_size: posed bodies (noise-free motion frames) kept in memory.
        hairstyle_cache_size: decoded hairstyles kept in memory.
    """

    strand_stride: int = 1
    num_vertices: int = 100
    latent_source: str = "corpus"
    latent_scale: float = 1.0
    corpus_seed: int = 0
    motions: list = field(default_factory=list_motions)
    motion_variants: int = 4
    amass_paths: list = field(default_factory=list)
    num_subjects: int = 8
    shape_std: float = 1.0
    beta_noise_std: float = 0.1
    long_hair_fraction: float = 0.0
    long_hair_length: float = 0.4
    grown_hair_fraction: float = 0.0
    head_rotation_radii: tuple = (0.6, 1.0, 0.5)
    phase1_rest_fraction: float = 0.1
    fps: float = DEFAULT_FPS
    crop_body: bool = True
    pose_cache_size: int = 512
    hairstyle_cache_size: int = 64

    def __post_init__(self):
        owner = type(self).__name__
        _int(owner, "strand_stride", self.strand_stride, 1)
        if SCALP_GRID % self.strand_stride:
            _fail(owner, "strand_stride", f"a divisor of {SCALP_GRID}", self.strand_stride)
        _int(owner, "num_vertices", self.num_vertices, 3)
        _choice(owner, "latent_source", self.latent_source, LATENT_SOURCES)
        _number(owner, "latent_scale", self.latent_scale, strict=True)
        _int(owner, "corpus_seed", self.corpus_seed)
        self.motions = list(self.motions)
        known = list_motions()
        for name in self.motions:
            _choice(owner, "motions", name, known)
        self.amass_paths = [os.fspath(p) for p in self.amass_paths]
        if not self.motions and not self.amass_paths:
            _fail(owner, "motions", "at least one motion (or amass_paths)", self.motions)
        _int(owner, "motion_variants", self.motion_variants, 1)
        _int(owner, "num_subjects", self.num_subjects, 1)
        _number(owner, "shape_std", self.shape_std)
        _number(owner, "long_hair_fraction", self.long_hair_fraction, maximum=1.0)
        _number(owner, "long_hair_length", self.long_hair_length, strict=True)
        if self.long_hair_fraction > 0 and self.latent_source != "corpus":
            _fail(owner, "long_hair_fraction", "0 unless latent_source is 'corpus' (sampled latents have no length)",
                  self.long_hair_fraction)
        _number(owner, "grown_hair_fraction", self.grown_hair_fraction, maximum=1.0)
        if self.grown_hair_fraction > 0 and self.latent_source != "corpus":
            _fail(owner, "grown_hair_fraction", "0 unless latent_source is 'corpus' (sampled latents have no strands)",
                  self.grown_hair_fraction)
        _number(owner, "beta_noise_std", self.beta_noise_std)
        self.head_rotation_radii = tuple(self.head_rotation_radii)
        if len(self.head_rotation_radii) != 3:
            _fail(owner, "head_rotation_radii", "3 numbers", self.head_rotation_radii)
        for r in self.head_rotation_radii:
            _number(owner, "head_rotation_radii", r, maximum=math.pi)
        _number(owner, "phase1_rest_fraction", self.phase1_rest_fraction, maximum=1.0)
        _number(owner, "fps", self.fps, strict=True)
        if not isinstance(self.crop_body, bool):
            _fail(owner, "crop_body", "true or false", self.crop_body)
        _int(owner, "pose_cache_size", self.pose_cache_size)
        _int(owner, "hairstyle_cache_size", self.hairstyle_cache_size)

    @property
    def num_strands(self) -> int:
        """M, strands per hairstyle after the sub-grid selection."""
        return (SCALP_GRID // self.strand_stride) ** 2

    @classmethod
    def tiny(cls) -> DataConfig:
        """64 strands x 20 vertices, 2 motions, no variants, uncropped bodies (with so few hair
        vertices the crop costs more than it saves): for CPU tests and examples.
        """
        return cls(strand_stride=4, num_vertices=20, motions=["nod", "whiplash"], motion_variants=1,
                   num_subjects=2, crop_body=False, pose_cache_size=64, hairstyle_cache_size=16)


def _check_energy(owner: str, energy: dict) -> None:
    if not isinstance(energy, dict):
        _fail(owner, "energy", "a table of EnergyConfig fields", energy)
    try:
        EnergyConfig(**energy)
    except TypeError as exc:
        raise ValueError(f"{owner}.energy: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"{owner}.energy.{exc}") from None


def _check_model_keys(owner: str, model: dict, config_cls, reserved=()) -> None:
    if not isinstance(model, dict):
        _fail(owner, "model", f"a table of {config_cls.__name__} fields", model)
    known = {f.name for f in dataclasses.fields(config_cls)} - set(reserved)
    unknown = sorted(set(model) - known)
    if unknown:
        raise ValueError(f"{owner}.model: unknown {config_cls.__name__} field(s) {unknown}; known: {sorted(known)}")


def energy_config(overrides: dict, **fixed) -> EnergyConfig:
    """EnergyConfig from a run's `energy` table plus fields the trainer sets (e.g. b_p)."""
    return EnergyConfig(**{**overrides, **fixed})


def _check_curve(owner: str, cfg) -> None:
    _int(owner, "curve_every", cfg.curve_every)
    cfg.curve_scenes = list(cfg.curve_scenes)
    for name in cfg.curve_scenes:
        if not isinstance(name, str):
            _fail(owner, "curve_scenes", "scene names", cfg.curve_scenes)
    if cfg.curve_strand_stride is not None:
        _int(owner, "curve_strand_stride", cfg.curve_strand_stride, 1)
    _int(owner, "curve_reference_iterations", cfg.curve_reference_iterations)


# ------------------------------------------------------------------------------------ static
@dataclass
class StaticTrainingConfig(_TrainingConfig):
    """The static network's curriculum (Section 4.2.1); also the Quaffure (adapted) baseline.

    Attributes:
        model_kind: "static" (HairFormer, Section 3.2) or "quaffure" (Section 4.3.1).
        model_preset: "paper" (`StaticConfig()`), "shipped" or "tiny" network sizes.
        model: overrides of the network config's fields (e.g. {num_heads = 4}); latent_dim
            and num_vertices always follow the data (512 and `data.num_vertices`).
        phase_steps: optimizer steps of phases 0-3: 0 one rest body + one hairstyle; 1 head
            rotations on growing ellipsoids; 2 `phase2_hairstyles` hairstyles + the motions of
            one subject; 3 `phase3_hairstyles`, all motions and subjects, noisy shapes.
        phase2_hairstyles: hairstyle pool of phase 2 (1 000 in the paper).
        phase3_hairstyles: hairstyle pool of phase 3 (20 000 in the paper).
        batch_size: samples per step (32 in the paper); phase 0 uses 1 (its samples are all
            the same: one body, one pose, one hairstyle).
        learning_rate: Adam step size (1e-4 in the paper).
        bp_start: b_p at the first step (0.9 in the paper).
        bp_end: b_p at the last step (0.01 in the paper).
        bp_schedule: "geometric" (default) or "linear" interpolation over all steps. The
            paper names no schedule; under the default quadratic barrier the push-out force
            scales with the barrier's curvature at d_b, ~5 000 times weaker at b_p = 0.9 than
            at 0.01, so a linear schedule leaves most steps nearly without contact force
            (docs/gpu.md: a 3 000-step linear run barely moved the hair).
        deformation_clip: clamp of each deformation component [m] early in training (0.01).
        clip_steps: steps during which the clip applies; None: phase 0.
        grad_clip_norm: clip the gradient norm to this (0: off; the paper does not clip).
        loss_normalization: "none" (Eq. 5 averaged over the batch, the paper) or "rigid":
            each sample's energy divided by its rigid placement's at the step's b_p (plus
            `LOSS_NORMALIZATION_FLOOR`), so a sample whose tips start 10 cm inside the body
            (contact gradients ~1e5 times gravity's, tools/diagnose_one_scene.py) does not
            drown the others in Adam's second moment; or "inverse": each sample's energy
            weighted by 1 / (1 + |E|) of its current value (detached), the gradient of
            log(1 + E): a sample deep inside the body pulls with the relative, not the absolute,
            size of its contact gradient, and the weights return to ~1 as the drapes settle.
        checkpoint_every: write `checkpoint.pt` every this many steps (0: only at the end).
        cuda_graph: on CUDA in one process, replay each step's forward and backward from a CUDA
            graph (`hairwarp.training.static`; 2.0-2.5x faster steps at batch 32 on an H100,
            docs/contact.md 16); False: eager. The CPU and data-parallel runs are eager.
        dtype: "float32" (training) or "float64" (checks).
        curve_every: record the learning curve (`hairwarp.training.monitor`: per-term gradient
            norms w.r.t. the map, displacement by vertex index, held-out scores) at step 0, every
            this many steps and at the end, into `learning_curve.json` / `.png` (0: off).
        curve_scenes: held-out comparison scenes scored by the curve (static scenes of
            `hairwarp.evaluation.scenes`; the trainer needs their factory, `scene_factory`).
        curve_strand_stride: their size: None full size (every scalp root), k one root in k.
        curve_reference_iterations: L-BFGS iterations over the free vertices (the L-BFGS baseline) that give each scene's
            reference energy E* for the energy gap (0: no energy gap).
        teacher_iterations: distillation from the physics (0: off, the paper's loss alone). Each
            step the network's own drape of the batch (detached) is refined by this many
            iterations of the physics' static drape (`hairwarp.solvers.physics`, device L-BFGS
            on the rest lengths, b_p at `bp_end`), and the drape is pulled toward it. The
            refinement's move is a curvature-aware step toward the optimum: the energy's own
            gradient is dominated by contact and root alignment (17-32x the inertia and gravity
            in |dE/dD|), and an energy-trained network errs up and out where the body is near
            (docs/network_diagnosis.md, S4-S5, D7).
        teacher_weight: weight of the distillation term [1/m^2]: teacher_weight times the mean
            squared distance [m^2] of the free vertices to the teacher's, per sample (1e4: a
            1 cm gap costs 1, an energy-sized term under the "inverse" normalization).
        teacher_pool: 0: the teacher refines every step's fresh batch in `teacher_iterations`
            iterations (one chunk, no restart). P > 0: the run cycles through P fixed batches
            (the sampler's batches of steps 0..P-1, in the step's phase), and each one's teacher
            is solved once, the first time it is drawn, to convergence: up to
            `teacher_iterations` iterations with the static drape's restarts
            (`PhysicsSolver.solve`), and kept on the run's device. Sixteen iterations from the
            network's drape moved it 0.3 mm RMS and left the strands it throws up where they
            were (docs/network_diagnosis.md, sixth session); a converged teacher is each
            sample's optimum.
        teacher_kind: "physics": the teacher is the physics' static drape (any positions; the
            network's tapered 8 x 8 map cannot reach most of them). "map": the drape of the best
            deformation map of each sample, L-BFGS (strong Wolfe, `teacher_iterations`
            iterations) over the map through the network's own taper and projection, from the
            network's map, on the energy at `bp_end`: a target the network can reach exactly
            (the 8 x 8 oracle map reached 0.999 x E*, docs/network_diagnosis.md S1).
        teacher_start: where the physics teacher's solve starts (a static drape rests in the
            state nearest its start). "network": the network's own drape; "rigid": the rigid
            placement, as the optimum E* does; "lower": both, and per sample the teacher of
            lower energy (twice the solves). Long straight hair grown on the body at rest (256
            strands, 2-core CPU, 800 iterations): from the shipped network's drape the teacher
            kept its lift (tips +45 mm above E*'s, 1.147 x E*); from the rigid placement it
            reached 1.008 x E*, tips +7 mm. On a bob at rest the network's start was the lower
            one (0.984 x E*). Trained with "lower" on one H100, the long hair at rest fell from
            2.55 to 1.24 x E*, but curly hair pushed deep into the body by a nod rose from 1.65
            to 3.91 x E* with 1.57 % inside (docs/network_diagnosis.md, ninth session, S8).
            "lower_where_clean": "lower" on the samples whose rigid placement has no free vertex
            inside the body, "network" on the others. Trained the same way (pool 48): 3 000
            steps gave the long hair at rest 1.48 x E* and the curly nod 1.27; 6 000 steps 1.32
            and 2.16 (0.42 % inside) (docs/network_diagnosis.md, tenth session).
            "rigid_where_clean": the rigid start wherever the rigid placement has nothing inside,
            the network's elsewhere, with no energy test. Over 384 training samples the two
            starts' teachers were within 1 % in energy and "lower" took either half the time, so
            similar samples got targets from two resting states; this rule is stable from sample
            to sample (not yet trained).
        teacher_settle_time: with `teacher_pool`, each pool teacher is then held in its pose for
            up to this long [s] of implicit-Euler steps and polished (`hairwarp.solvers.physics.
            drape_at_rest`, the physics' drape at rest, as E* now is); 0: the static solve's
            drape, which at full size stalled 3-129 mm above where the hair hangs
            (docs/physics.md, "Sixteenth session").
        teacher_settle_time_step: the settling steps' time step [s]: rest, not the way there, is
            the target, and implicit Euler is stable at any step. A training batch (2 samples of
            512 strands, 2-core CPU) settled for 1 s reached 1.0032 / 0.0116 J in 60 steps of
            1/60 s (296 s) and 1.0032 / 0.0124 J in 10 steps of 0.1 s (75 s)
            (docs/network_diagnosis.md, seventeenth session).
        energy: overrides of `hairwarp.config.EnergyConfig` fields (b_p is set per step).
        data: what the sampler draws.
    """

    model_kind: str = "static"
    model_preset: str = "paper"
    model: dict = field(default_factory=dict)
    phase_steps: tuple = (1000, 2000, 10000, 50000)
    phase2_hairstyles: int = 1000
    phase3_hairstyles: int = 20000
    batch_size: int = 32
    learning_rate: float = 1.0e-4
    bp_start: float = 0.9
    bp_end: float = 0.01
    bp_schedule: str = "geometric"
    deformation_clip: float = 0.01
    clip_steps: int | None = None
    grad_clip_norm: float = 0.0
    loss_normalization: str = "none"
    checkpoint_every: int = 1000
    cuda_graph: bool = True
    dtype: str = "float32"
    curve_every: int = 500
    curve_scenes: list = field(default_factory=lambda: ["table1", "medium_poses"])
    curve_strand_stride: int | None = None
    curve_reference_iterations: int = 100
    teacher_iterations: int = 0
    teacher_weight: float = 1.0e4
    teacher_pool: int = 0
    teacher_kind: str = "physics"
    teacher_start: str = "network"
    teacher_settle_time: float = 0.0
    teacher_settle_time_step: float = 0.1
    energy: dict = field(default_factory=dict)
    data: DataConfig = field(default_factory=DataConfig)

    def __post_init__(self):
        owner = type(self).__name__
        _choice(owner, "model_kind", self.model_kind, STATIC_MODEL_KINDS)
        _int(owner, "teacher_iterations", self.teacher_iterations)
        _number(owner, "teacher_weight", self.teacher_weight)
        _int(owner, "teacher_pool", self.teacher_pool)
        _choice(owner, "teacher_kind", self.teacher_kind, TEACHER_KINDS)
        _choice(owner, "teacher_start", self.teacher_start, TEACHER_STARTS)
        if self.teacher_kind != "physics" and self.teacher_start != "network":
            _fail(owner, "teacher_start", '"network" unless teacher_kind is "physics" (a map teacher starts '
                  "from the network's map)", self.teacher_start)
        _number(owner, "teacher_settle_time", self.teacher_settle_time)
        _number(owner, "teacher_settle_time_step", self.teacher_settle_time_step, strict=True)
        if self.teacher_settle_time > 0 and (self.teacher_pool == 0 or self.teacher_kind != "physics"):
            _fail(owner, "teacher_settle_time", '0 unless teacher_pool > 0 and teacher_kind is "physics" (only '
                  "a pool's converged physics teachers are settled)", self.teacher_settle_time)
        if self.teacher_pool > 0 and self.teacher_iterations == 0:
            _fail(owner, "teacher_pool", "0 unless teacher_iterations > 0 (the pool's teachers are solved "
                  "in teacher_iterations iterations)", self.teacher_pool)
        _check_curve(owner, self)
        _choice(owner, "model_preset", self.model_preset, MODEL_PRESETS)
        _check_model_keys(owner, self.model, StaticConfig if self.model_kind == "static" else QuaffureConfig)
        self.phase_steps = tuple(self.phase_steps)
        if len(self.phase_steps) != 4:
            _fail(owner, "phase_steps", "4 step counts (phases 0-3)", self.phase_steps)
        for s in self.phase_steps:
            _int(owner, "phase_steps", s)
        if sum(self.phase_steps) == 0:
            _fail(owner, "phase_steps", "at least one step in total", self.phase_steps)
        _int(owner, "phase2_hairstyles", self.phase2_hairstyles, 1)
        _int(owner, "phase3_hairstyles", self.phase3_hairstyles, 1)
        _int(owner, "batch_size", self.batch_size, 1)
        _number(owner, "learning_rate", self.learning_rate, strict=True)
        _number(owner, "bp_start", self.bp_start, strict=True, maximum=1.0)
        _number(owner, "bp_end", self.bp_end, strict=True, maximum=1.0)
        if self.bp_start >= 1.0 or self.bp_end >= 1.0:
            _fail(owner, "bp_start/bp_end", "values in (0, 1)", (self.bp_start, self.bp_end))
        _choice(owner, "bp_schedule", self.bp_schedule, BP_SCHEDULES)
        _number(owner, "deformation_clip", self.deformation_clip, strict=True)
        if self.clip_steps is not None:
            _int(owner, "clip_steps", self.clip_steps)
        _number(owner, "grad_clip_norm", self.grad_clip_norm)
        _choice(owner, "loss_normalization", self.loss_normalization, LOSS_NORMALIZATIONS)
        _int(owner, "checkpoint_every", self.checkpoint_every)
        if not isinstance(self.cuda_graph, bool):
            _fail(owner, "cuda_graph", "True or False", self.cuda_graph)
        _choice(owner, "dtype", self.dtype, DTYPES)
        _check_energy(owner, self.energy)
        if isinstance(self.data, dict):
            self.data = DataConfig.from_dict(self.data)
        if not isinstance(self.data, DataConfig):
            _fail(owner, "data", "a DataConfig", self.data)

    @property
    def total_steps(self) -> int:
        """Steps of the whole curriculum."""
        return int(sum(self.phase_steps))

    @property
    def clip_until(self) -> int:
        """First step without the deformation clip."""
        return self.phase_steps[0] if self.clip_steps is None else self.clip_steps

    @classmethod
    def tiny(cls, model_kind: str = "static") -> StaticTrainingConfig:
        """A CPU-sized curriculum: tiny network, 64 x 20 hair, a few steps per phase."""
        return cls(
            model_kind=model_kind, model_preset="tiny", phase_steps=(4, 4, 4, 4), phase2_hairstyles=2,
            phase3_hairstyles=3, batch_size=2, learning_rate=1e-3, checkpoint_every=0, data=DataConfig.tiny(),
            curve_every=0,
        )


# ------------------------------------------------------------------------------------ dynamic
@dataclass
class DynamicTrainingConfig(_TrainingConfig):
    """The dynamic network (Section 4.2.2) and its fine-tuning on one motion (Fig. 4).

    Each batch item is a sequence of `warmup_frames + rollout_frames` frames of one motion,
    subsampled every k in [subsample_min, subsample_max] frames (one k per sequence) and kept
    when its dynamic score reaches the `dynamic_quantile` of `dynamic_candidates` random
    sequences. The GRU runs from a zero state over the warm-up frames without gradient; their
    last two drapes are the previous states of the first rollout frames. The loss (Eq. 6) is
    averaged over the rollout frames; gradients flow back through the GRU over the rollout
    (truncated back-propagation through time), never through previous hair states (Eq. 16).

    Attributes:
        static_checkpoint: the trained static network (a `hairwarp train static` checkpoint).
        model_preset: sizes of the dynamic parts: "paper" (`DynamicConfig()`), "shipped" or
            "tiny".
        model: overrides of `DynamicConfig` fields (num_static_dynamic_layers,
            motion_hidden_dim, fusion, lora_rank, lora_alpha, func_reg_weight);
            motion_dim and window follow the data.
        steps: optimizer steps.
        hairstyles: hairstyle pool (the static phase 3's 20 000 in the paper).
        batch_size: sequences per step (32 in the paper).
        learning_rate: Adam step size (1e-4 in the paper).
        warmup_frames: frames run without gradient before the rollout (>= 2: they supply the
            two previous states of Eq. 16).
        rollout_frames: frames whose Eq. 6 loss is averaged and back-propagated.
        subsample_min: smallest frame interval k (2 in the paper).
        subsample_max: largest frame interval k (5 in the paper).
        window: T_w, motion-descriptor frames per step (10 in the paper).
        dynamic_filter: drop sequences whose dynamic score is under the threshold.
        dynamic_candidates: random sequences whose scores set the threshold (500).
        dynamic_quantile: quantile of those scores used as threshold (0.5, the median).
        barrier_join_fraction: b_p of the contact barrier (the static curriculum's final 0.01).
        long_hair_fraction: share of each batch's sequences whose hairstyle is drawn from the
            pool's long hairstyles (corpus parameter length >= `data.long_hair_length`); 0 (the
            paper): uniform over the pool, which holds ~16 % long hair, so long hair on the
            torso bend is ~1 % of the rollout frames (docs/training_diagnosis.md, H17; on its
            own it did not help there, H21).
        inertia_time_step: the h of Eq. 16 between two drapes of a sequence: "interval" (k / fps
            for a sequence sampled every k frames: the time that passed) or "frame" (1 / fps
            whatever k: inertia weighted k^2 = 4-25 times too much, which trained networks that
            throw the hair up and out).
        deformation_clip: optional clamp of each deformation component [m] (None: off).
        grad_clip_norm: clip the gradient norm to this (0: off).
        checkpoint_every: write `checkpoint.pt` every this many steps (0: only at the end).
        cuda_graph: on CUDA in one process, replay each step's forward and backward from a CUDA
            graph (`hairwarp.training.capture`); False: eager. The CPU and data-parallel runs are
            eager.
        dtype: "float32" or "float64".
        energy: overrides of `EnergyConfig` fields.
        data: what the sampler draws (its strand subset and N must match the static network).
    """

    static_checkpoint: str = ""
    model_preset: str = "paper"
    model: dict = field(default_factory=dict)
    steps: int = 20000
    hairstyles: int = 20000
    batch_size: int = 32
    learning_rate: float = 1.0e-4
    warmup_frames: int = 3
    rollout_frames: int = 4
    subsample_min: int = 2
    subsample_max: int = 5
    window: int = 10
    dynamic_filter: bool = True
    dynamic_candidates: int = 500
    dynamic_quantile: float = 0.5
    barrier_join_fraction: float = 0.01
    long_hair_fraction: float = 0.0
    inertia_time_step: str = "interval"
    deformation_clip: float | None = None
    grad_clip_norm: float = 0.0
    checkpoint_every: int = 1000
    cuda_graph: bool = True
    dtype: str = "float32"
    energy: dict = field(default_factory=dict)
    data: DataConfig = field(default_factory=DataConfig)

    def __post_init__(self):
        owner = type(self).__name__
        self.static_checkpoint = os.fspath(self.static_checkpoint)
        _choice(owner, "model_preset", self.model_preset, MODEL_PRESETS)
        _choice(owner, "inertia_time_step", self.inertia_time_step, INERTIA_TIME_STEPS)
        if isinstance(self.model, dict):
            for name in ("motion_dim", "window", "static"):
                if name in self.model:
                    _fail(owner, f"model.{name}", "not set (it follows the data and the static network)",
                          self.model[name])
        _check_model_keys(owner, self.model, DynamicConfig)
        _int(owner, "steps", self.steps, 1)
        _int(owner, "hairstyles", self.hairstyles, 1)
        _int(owner, "batch_size", self.batch_size, 1)
        _number(owner, "learning_rate", self.learning_rate, strict=True)
        _int(owner, "warmup_frames", self.warmup_frames, 2)
        _int(owner, "rollout_frames", self.rollout_frames, 1)
        _int(owner, "subsample_min", self.subsample_min, 1)
        _int(owner, "subsample_max", self.subsample_max, 1)
        if self.subsample_max < self.subsample_min:
            _fail(owner, "subsample_max", f">= subsample_min={self.subsample_min}", self.subsample_max)
        _int(owner, "window", self.window, 1)
        if not isinstance(self.dynamic_filter, bool):
            _fail(owner, "dynamic_filter", "true or false", self.dynamic_filter)
        _int(owner, "dynamic_candidates", self.dynamic_candidates, 1)
        _number(owner, "dynamic_quantile", self.dynamic_quantile, maximum=1.0)
        _number(owner, "barrier_join_fraction", self.barrier_join_fraction, strict=True, maximum=1.0)
        if self.barrier_join_fraction >= 1.0:
            _fail(owner, "barrier_join_fraction", "a value in (0, 1)", self.barrier_join_fraction)
        _number(owner, "long_hair_fraction", self.long_hair_fraction, maximum=1.0)
        if self.deformation_clip is not None:
            _number(owner, "deformation_clip", self.deformation_clip, strict=True)
        _number(owner, "grad_clip_norm", self.grad_clip_norm)
        _int(owner, "checkpoint_every", self.checkpoint_every)
        if not isinstance(self.cuda_graph, bool):
            _fail(owner, "cuda_graph", "True or False", self.cuda_graph)
        _choice(owner, "dtype", self.dtype, DTYPES)
        _check_energy(owner, self.energy)
        if isinstance(self.data, dict):
            self.data = DataConfig.from_dict(self.data)
        if not isinstance(self.data, DataConfig):
            _fail(owner, "data", "a DataConfig", self.data)
        if self.long_hair_fraction > 0 and self.data.latent_source != "corpus":
            _fail(owner, "long_hair_fraction", "0 unless data.latent_source is 'corpus' (sampled latents have no "
                  "length)", self.long_hair_fraction)

    @property
    def frames_per_sequence(self) -> int:
        """Warm-up plus rollout frames."""
        return self.warmup_frames + self.rollout_frames

    @classmethod
    def tiny(cls, static_checkpoint: str = "") -> DynamicTrainingConfig:
        """A CPU-sized run: tiny dynamic parts, 2 sequences of 2 + 2 frames, 64 x 20 hair."""
        return cls(
            static_checkpoint=static_checkpoint, model_preset="tiny", steps=4, hairstyles=2, batch_size=2,
            learning_rate=1e-3, warmup_frames=2, rollout_frames=2, window=3, dynamic_candidates=16,
            checkpoint_every=0, data=DataConfig.tiny(),
        )


# ------------------------------------------------------------------------------------ files
CONFIG_CLASSES = {
    "static": StaticTrainingConfig,
    "quaffure": StaticTrainingConfig,
    "dynamic": DynamicTrainingConfig,
}


def parse_value(text: str) -> Any:
    """A command-line value as a TOML literal (numbers, true/false, [lists], "strings");
    anything that does not parse is taken as a bare string.
    """
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(config, overrides):
    """A copy of `config` with `key=value` overrides applied (dotted keys reach nested tables).

    Args:
        config: a StaticTrainingConfig or DynamicTrainingConfig.
        overrides: iterable of "key=value" strings, e.g. "batch_size=8",
            "data.motions=['nod']", "energy.hair_hair_weight=10", "clip_steps=none".

    Returns:
        The validated new config.

    Raises:
        ValueError: naming the override that is malformed or sets an unknown or bad field.
    """
    data = config.to_dict()
    for item in overrides or ():
        if not isinstance(item, str) or "=" not in item:
            raise ValueError(f"--set: expected key=value, got {item!r}")
        key, text = (s.strip() for s in item.split("=", 1))
        if not key:
            raise ValueError(f"--set: empty key in {item!r}")
        parts = key.split(".")
        node = data
        for depth, part in enumerate(parts[:-1]):
            if part not in node:
                raise ValueError(f"--set {key}: unknown setting {'.'.join(parts[:depth + 1])!r}")
            if not isinstance(node[part], dict):
                raise ValueError(f"--set {key}: {'.'.join(parts[:depth + 1])!r} is not a table")
            node = node[part]
        # The model and energy tables take new keys (they are validated when the config is
        # rebuilt); every other table only knows its fields.
        free = len(parts) >= 2 and parts[-2] in ("model", "energy")
        if parts[-1] not in node and not free:
            raise ValueError(f"--set {key}: unknown setting {key!r}")
        node[parts[-1]] = parse_value(text)
    try:
        return type(config).from_dict(data)
    except ValueError as exc:
        raise ValueError(f"--set: {exc}") from None


def load_config(path, kind: str = "static", overrides=()):
    """Read a TOML config file (or none) for a kind of run and apply `--set` overrides.

    Args:
        path: a `.toml` file whose top-level keys are the config's fields and whose tables
            [data], [energy], [model] are the nested ones; None for the defaults.
        kind: "static", "quaffure" or "dynamic".
        overrides: "key=value" strings applied after the file.

    Returns:
        StaticTrainingConfig (model_kind = kind for static/quaffure) or DynamicTrainingConfig.

    Raises:
        ValueError: an unknown kind, an unreadable file, or a bad setting (named).
        FileNotFoundError: if `path` does not exist.
    """
    if kind not in CONFIG_CLASSES:
        raise ValueError(f"kind: expected one of {list(CONFIG_CLASSES)}, got {kind!r}")
    cls = CONFIG_CLASSES[kind]
    data: dict = {}
    if path is not None:
        with open(os.fspath(path), "rb") as f:
            try:
                data = tomllib.load(f)
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{os.fspath(path)}: not valid TOML ({exc})") from None
    if cls is StaticTrainingConfig:
        if "model_kind" in data and data["model_kind"] != kind:
            raise ValueError(
                f"{os.fspath(path)}: model_kind = {data['model_kind']!r} but the command trains {kind!r}"
            )
        data["model_kind"] = kind
    try:
        config = cls.from_dict(data)
    except ValueError as exc:
        where = os.fspath(path) if path is not None else "config"
        raise ValueError(f"{where}: {exc}") from None
    return apply_overrides(config, overrides)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value) if isinstance(value, int) or math.isfinite(value) else json.dumps(str(value))
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if value is None:
        return '"none"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ValueError(f"cannot write {type(value).__name__} to TOML")


def to_toml(config) -> str:
    """The config as TOML text that `load_config` reads back to an equal config."""
    data = config.to_dict()
    lines, tables = [], []
    for key, value in data.items():
        if isinstance(value, dict):
            tables.append((key, value))
        else:
            lines.append(f"{key} = {_toml_value(value)}")
    for key, table in tables:
        lines.append("")
        lines.append(f"[{key}]")
        for k, v in table.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def write_toml(config, path) -> None:
    """Write `to_toml(config)` to `path`."""
    with open(os.fspath(path), "w", encoding="utf-8") as f:
        f.write(to_toml(config))


__all__ = [
    "BP_SCHEDULES",
    "CONFIG_CLASSES",
    "DataConfig",
    "DynamicTrainingConfig",
    "LATENT_SOURCES",
    "MODEL_PRESETS",
    "StaticTrainingConfig",
    "apply_overrides",
    "energy_config",
    "load_config",
    "parse_value",
    "to_toml",
    "write_toml",
]
