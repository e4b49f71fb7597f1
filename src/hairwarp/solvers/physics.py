"""The physics simulation: implicit Euler on the device L-BFGS.

Each frame t solves one implicit-Euler step, the incremental potential
    x_t = argmin_x  L_inertia(x; x_{t-1}, x_{t-2}) + L_static(x; frame t),
the dynamic objective of Eq. 6 (inertia, Eq. 16, plus the static energy, Eq. 5) without the
network's functional regularization; a single frame is draped as the static optimum (Eq. 5).
It is the ground truth that every method is measured against, a teacher for training, and a
method of its own (`physics`; `reference` is the same solver with tolerances 100x tighter).

What makes it fast:
- warm start: the moving vertices start from the inertial prediction 2 x_{t-1} - x_{t-2}, the
  fixed vertices 0 and 1 from the frame's rigid placement (Eq. 1);
- steps on the rest lengths (`PhysicsConfig.inextensible`): the stretch term's k_s = 1e8 is
  eight orders of magnitude above the inertia's mass / dt^2; solved as a penalty, a step that
  turns a segment creeps along a curved valley;
- fixed buffers: the rigid placement, scalp normals, previous states and one body
  (`BodyMesh.update` moves it in place) are written before each step, so on CUDA a step's start
  (energy, first direction) and one iteration are two CUDA graphs captured once and
  replayed for every frame (`hairwarp.solvers.device_lbfgs.DeviceLBFGS`); on the CPU the same
  calls run eagerly with the hair-hair pair cache;
- a step's hair-hair pairs in a device list (`PhysicsConfig.hair_hair_list`, with the graphs):
  built at the step's start within a skin of the cutoff, built again (a third graph) after a
  chunk that left the iterate out of its reach, where the broad phase ran at every call;
- variables scaled by the stiffness (`PhysicsConfig.stiffness_scaling`): root alignment (Eq. 15)
  turns the first millimetre-long segments three orders of magnitude stiffer than a vertex's
  inertia, which doubled the iterations a step takes; the solver's variable of each vertex is
  its target divided by (k_min / k)^a, so L-BFGS starts from H0 = gamma diag((k_min / k)^2a);
- a stopping rule stated as a tolerance [m], read once per `chunk` iterations: a step ends when
  its last chunk moved no vertex farther than `tolerance` (a static drape: `static_tolerance`;
  after two chunks at least: a step whose first trials the line search rejects would otherwise
  stop at the inertial prediction, a free flight, and a released strand then gained energy,
  swinging above its root).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import torch

from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs, total_energy
from hairwarp.runtime import synchronize


# `PhysicsConfig.stopping`'s rules, and the largest ratio of two chunks' moves the "rate" rule
# reads (its tail then at most 10 m_k).
STOPPING_RULES = ("move", "rate")
STOPPING_RATE_CAP = 0.9


@dataclass
class PhysicsConfig:
    """Settings of the physics solver.

    Attributes:
        tolerance: an implicit-Euler step ends when its last chunk of iterations moved no vertex
            farther than this [m]. 1e-4 m: on one H100 at full size each step lands within
            0.13-0.16 mm of the tight setting's and 10 frames within 0.83-0.84 mm (goals 1 and
            2 mm), in 25 % fewer iterations on whiplash than at 1e-5 (127-144 a step against
            160-169; docs/physics.md, section 2).
        static_tolerance: the same for a static drape, read over `static_chunk` iterations [m]
            (from a rigid placement the hair travels far at a few tenths of a millimetre per
            iteration).
        max_iterations: cap of L-BFGS iterations (energy evaluations) per time step.
        static_max_iterations: cap for a static drape (the optimum of one frame, from far).
        static_chunk: `chunk` of a static drape (from a rigid placement the hair travels far
            at a few tenths of a millimetre per iteration: a short chunk would stop it early).
        history: L-BFGS memory (curvature pairs).
        chunk: iterations between two reads of the stopping rule (one device sync each).
        keep_memory: carry the L-BFGS memory from one step into the next. Off: as a strand
            turns, the old pairs call its new soft directions stiff (a released strand's steps
            stopped after four iterations, at the free flight, before the two-chunk minimum). At
            full size on one H200 it took 8 % fewer to 2 % more iterations a step (docs/physics.md,
            "Twenty-ninth session").
        max_step: the farthest one trial step moves a vertex [m].
        cuda_graph: on CUDA, replay the step's start and its iterations from CUDA graphs.
        inextensible: solve on the strands' rest lengths: the solver's variables are targets
            that the follow-the-leader projection (`hairwarp.ops.follow_the_leader`) turns into
            positions, so Eq. 7 is zero by construction. Its k_s = 1e8 makes a strand a chain
            whose length errors cost eight orders of magnitude more than its inertia: a step
            that turns a segment stretches it to second order, and an unconstrained solver
            creeps along the curved valley (a released strand fell in ~2 s instead of ~0.3 s).
        head_follow_length: the warm start adds the head's unpredicted move, fading along the
            strand over this arc length [m] (0: the inertial prediction alone).
        stiffness_scaling: the implicit-Euler steps solve for z = target / S with
            S = (k_min / k)^a per vertex, k the diagonal stiffness (`vertex_stiffness`), a this
            exponent (0: unscaled): L-BFGS with H0 = gamma S^2. Root alignment makes the first
            vertices ~10^3 times stiffer than the rest; the full diagonal scaling (a = 1/2)
            overshoots what follow-the-leader leaves of that stiffness, a quarter of it
            (a = 1/8) measured best (docs/physics.md, section 1). Static drapes are unscaled
            (no inertia to scale by).
        hair_hair_list: the implicit-Euler steps keep their hair-hair pairs in a device list
            (`hairwarp.ops.hair_hair_contact.HairHairPairList`), built at a step's start within
            `hair_hair_list_skin` of the cutoff and built again after a chunk that left the
            iterate out of its reach (a step then ends only after a chunk within it); None:
            where the steps replay CUDA graphs (the CPU keeps its own pair cache). The cells
            broad phase at every energy call was 0.31-0.50 ms of a ~1 ms iteration on one H100.
        hair_hair_list_skin: the device list's margin [m]: wider, fewer rebuilds and more
            pairs tested at every call.
        strand_preconditioner: the implicit-Euler steps solve for z = U^T (t - t_0), P = U U^T each
            strand's stiffness at the step's start t_0 (`hairwarp.ops.strand_preconditioner`: the
            energy's block-banded Hessian along the strand without contact, plus the segments'
            tension): L-BFGS with H0 = P^-1, each strand's Newton step. Replaces
            `stiffness_scaling` where on. Off by default: on sparse hair (64 strands) a step capped
            at 8 iterations came 10-30x closer to the tight one than with the diagonal scaling,
            but at full size on one H100 it was slower (whiplash 214 against 80 ms a frame,
            torso_bend 92 against 58: fewer iterations on torso_bend, each ~2x the cost), as
            contact, not the strands' stiffness, sets the pace there (docs/physics.md, section 2,
            "Thirteenth session" and "Fourteenth session").
        chain_preconditioner: the hanging tension's factor of `ChainPreconditioner`
            (`hairwarp.ops.strand_preconditioner`; 0: off): the implicit-Euler steps solve for
            z = L^T (t - t_0), P = L L^T the stiffness scaling's diagonal plus each strand's
            tension Laplacian as it hangs under its weight, made once from the rest lengths, so
            that one direction carries the head's move down the whole strand. Replaces
            `stiffness_scaling`'s variables (its exponent sets P's diagonal). One H200, 1 024 x
            100, 16 frames, four runs (docs/physics.md, "Twenty-ninth session"): 11-17 % fewer
            iterations a step on whiplash, 28-29 % on torso_bend; torso_bend 8-16 % faster,
            whiplash not (its directions leave the hair-hair pair list's reach more often: up to
            6.8 rebuilds a step against 4); 10 frames within 0.34-1.09 mm of the tight trajectory
            (the default's 0.04-0.24). With a tolerance of 2e-4 m: torso_bend 40.5-42.5, whiplash
            45-58 ms a frame. Off by default: no faster on whiplash.
        settle_time: every static drape of the physics (`drape_at_rest`: the `physics` and
            `reference` drapes, E*, and a motion's first frame) is followed by implicit-Euler
            steps with the pose held, for at most this long [s], until a step moves no vertex
            farther than `settle_tolerance`, then polished by a static solve. 0: the first static
            solve's drape. That drape is not at rest at full size: L-BFGS from the rigid placement
            stops (2 000 iterations) above where the hair hangs, and the first frames of every
            motion then showed the hair falling. One H100, 1 024 x 100, the mean tip height below
            the rigid placement unsettled / settled for 1 s: whiplash 10 / 36 mm, bob nod 4 / 21
            mm, long curly hair 30 / 158 mm (then sinking to 196 mm within 0.3 s unsettled);
            settling costs 4-8 s a motion there, 37 s at 256 strands on a 2-core CPU
            (docs/physics.md, "Sixteenth session").
        settle_tolerance: the settling steps end when a step moves no vertex farther than this [m]
            (each step solved to it or the config's `tolerance`, whichever is looser).
        settle_momentum: the share of each settling step's velocity the next inherits, in (0, 1]
            (`settle_with_pose_held`; 1: the physics' own motion, the hair swinging about its rest
            on the way there). 0.8, the inertial method's settle (docs/network_diagnosis.md, T19): on
            128 strands of long hair on the arm raise's first pose (2-core CPU) it came to rest in
            30 steps, 0.85 mm (mean) from the tight drape, where the undamped settle ran its 60
            steps and ended 2.44 mm from it, the tips 7.9 mm; on long curly hair both ran their 60
            steps (7.3 against 6.9 mm, the tips 16.2 against 17.6 mm) and the damped one in 58 %
            of the time. At full size on one H200 the arm raise's first frame came to rest in
            33-37 steps, two runs 0.51 mm apart, where the undamped settle's ran 60 steps and
            ended 3.87 mm apart (docs/physics.md, "Thirtieth session").
        stopping: how the implicit-Euler steps read a chunk's largest vertex move m_k against the
            tolerance (static drapes read the move itself: their restarts catch the stall). "move":
            m_k <= tolerance. "rate" (default): its geometric tail m_k / (1 - r) <= tolerance, r =
            m_k / m_{k-1} the ratio of the last two chunks' moves, capped at `STOPPING_RATE_CAP` (the
            a-posteriori bound of a linearly converging iteration), so that an iterate creeping at
            a steady pace toward a solution still far away is not read as converged. One H200,
            1 024 x 100, six motions, 16 frames (docs/physics.md, "Thirtieth session"): "move"
            stopped a bob's nod steps after 8 iterations 0.3 mm short of the tight solve (144) and
            drifted 3.8-4.4 mm from the tight trajectory in 10 frames (goal 2 mm); "rate" 0.40 mm,
            at 87 -> 143 iterations a step there and within 1-5 % of "move"'s time on the five others.
    """

    tolerance: float = 1.0e-4
    static_tolerance: float = 1.0e-5
    max_iterations: int = 200
    static_max_iterations: int = 2000
    static_chunk: int = 50
    history: int = 8
    chunk: int = 4
    keep_memory: bool = False
    max_step: float = 0.02
    cuda_graph: bool = True
    inextensible: bool = True
    head_follow_length: float = 0.05
    stiffness_scaling: float = 0.125
    hair_hair_list: bool | None = None
    hair_hair_list_skin: float = 3.0e-3
    strand_preconditioner: bool = False
    chain_preconditioner: float = 0.0
    settle_time: float = 1.0
    settle_tolerance: float = 1.0e-4
    settle_momentum: float = 0.8
    stopping: str = "rate"

    def __post_init__(self):
        if self.stopping not in STOPPING_RULES:
            raise ValueError(f"stopping: expected one of {list(STOPPING_RULES)}, got {self.stopping!r}")
        for name in ("tolerance", "static_tolerance", "max_step", "hair_hair_list_skin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a finite positive length [m], got {value}")
        if not (math.isfinite(self.settle_time) and self.settle_time >= 0):
            raise ValueError(f"settle_time: expected a finite time >= 0 [s], got {self.settle_time}")
        if not (math.isfinite(self.settle_tolerance) and self.settle_tolerance > 0):
            raise ValueError(f"settle_tolerance: expected a finite positive length [m], got {self.settle_tolerance}")
        if not (math.isfinite(self.settle_momentum) and 0.0 < self.settle_momentum <= 1.0):
            raise ValueError(f"settle_momentum: expected a share in (0, 1], got {self.settle_momentum}")
        if not (math.isfinite(self.chain_preconditioner) and self.chain_preconditioner >= 0):
            raise ValueError(f"chain_preconditioner: expected a finite tension factor >= 0, got {self.chain_preconditioner}")
        if self.chain_preconditioner and self.strand_preconditioner:
            raise ValueError("chain_preconditioner: expected 0 with strand_preconditioner on (one change of variables)")
        if not (math.isfinite(self.stiffness_scaling) and self.stiffness_scaling >= 0):
            raise ValueError(f"stiffness_scaling: expected a finite exponent >= 0, got {self.stiffness_scaling}")
        for name in ("max_iterations", "static_max_iterations", "static_chunk", "history", "chunk"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")

    def tight(self, factor: float = 100.0) -> "PhysicsConfig":
        """The `reference` setting: both tolerances / factor and iteration caps to match."""
        return replace(self, tolerance=self.tolerance / factor, static_tolerance=self.static_tolerance / factor,
                       max_iterations=self.max_iterations * 10,
                       static_max_iterations=self.static_max_iterations * 5)


def remaining_distance(move: float, previous: float, rule: str = "move") -> float:
    """The stopping rule's estimate [m] of how far a solve still has to go (`PhysicsConfig.stopping`):
    "move": the last chunk's largest vertex move `move`; "rate": its geometric tail move / (1 - r),
    r = move / `previous` (the chunk before; none: 0) capped at `STOPPING_RATE_CAP`.
    """
    if rule == "move":
        return move
    rate = move / previous if 0.0 < previous < math.inf else 0.0
    return move / (1.0 - min(rate, STOPPING_RATE_CAP))


def vertex_stiffness(config: EnergyConfig, rest_lengths: torch.Tensor, *, inextensible: bool = True) -> torch.Tensor:
    """The diagonal of the step's Hessian per moving vertex [J/m^2], (M, N-2), float64.

    Inertia (Eq. 16, lambda_inertia m / (M (N-2) dt^2)), smoothness (Eq. 10, 2 s_smooth times the
    squared weights (1, -2, 1) of the joints at the vertex), the auxiliary term (Eq. 9), root
    alignment's transverse stiffness on the first k' moving edges (Eq. 15, s_root / l0^2: a unit
    direction over millimetre edges, four orders of magnitude above the inertia), and stretch's
    2 s_stretch per segment end unless the steps are `inextensible`. The scales are the energy's
    (`hairwarp.ops.strand_energies`).
    """
    m, n = config.strand_normalization(rest_lengths.shape[0]), rest_lengths.shape[1] + 1
    rest = rest_lengths.detach().to(torch.float64)
    diagonal = torch.zeros(rest.shape[0], n, dtype=torch.float64, device=rest.device)
    diagonal += config.inertia_stiffness(rest.shape[0], n)
    diagonal += 2.0 * config.auxiliary_weight / (3 * m * n)
    smooth = 2.0 * config.smoothness_weight / (m * (n - 2))
    for offset, weight in ((-1, 1.0), (0, 4.0), (1, 1.0)):  # joints v-1, v, v+1 (joints lie at 1..N-2)
        joints = torch.arange(n, device=rest.device) + offset
        diagonal += smooth * weight * ((joints >= 1) & (joints <= n - 2)).to(torch.float64)
    k_align = min(config.root_alignment_segments, n - 2)
    if k_align and config.root_alignment_weight:
        root = config.root_alignment_weight / (m * k_align) / rest[:, 1:k_align + 1] ** 2  # edges 1..k'
        diagonal[:, 1:k_align + 1] += root
        diagonal[:, 2:k_align + 2] += root
    if not inextensible:
        stretch = 2.0 * config.stretch_weight / (m * (n - 1))
        diagonal[:, :-1] += stretch
        diagonal[:, 1:] += stretch
    return diagonal[:, NUM_FIXED_VERTICES:]


# The hair-hair pair list's margin on the CPU [m] (`HairHairPairCache.skin`). An implicit-Euler
# step moves the hair millimetres, not the centimetres of a drape from the rigid placement, so a
# wider list is requeried less; but every stored pair is tested at every call (at 3 mm, 107 000
# stored for 8 500 within the 1.25 mm cutoff, 7.7 ms of the side thread's 12 ms). 2-core CPU,
# 256 x 100, 10 steps, the skins alternated in one process, two rounds [ms an iteration]:
# torso_bend 1 mm 23.0 / 21.8, 1.5 mm 20.6 / 19.8, 2 mm 20.7 / 22.9, 3 mm 22.7 / 26.0; whiplash
# 1.5 mm 16.2 / 18.0, 3 mm 17.0 / 19.2 (docs/physics.md; the same pairs at any skin).
PHYSICS_PAIR_SKIN = 1.5e-3

# A static drape is restarted (`PhysicsSolver.solve`) while a restart lowers its energy by more than
# this share of it.
STALL_RELATIVE_DECREASE = 1e-6


@dataclass
class StepReport:
    """What one solve did: iterations (energy evaluations), why it stopped, the stopping rule's
    last measure [m] (`PhysicsConfig.tolerance`), the final energy [J] and the hair-hair pair
    list's rebuilds after a chunk left its reach (`PhysicsConfig.hair_hair_list`).
    """

    iterations: int
    stop_reason: str
    residual: float
    energy: float
    rebuilds: int = 0


class PhysicsSolver:
    """Implicit-Euler steps (or static drapes) of hair of one shape against one moving body.

    Args:
        rest_lengths: (M, N-1) rest segment lengths [m], or (B, M, N-1) per sample (a training batch
            of several hairstyles; static drapes, or dynamic steps without `stiffness_scaling`).
        rigid: (B, M, N, 3) a rigid placement (shape, dtype (float32 or float64) and device of every step).
        scalp_normals: (B, M, 3) posed scalp normals at the roots, or None (no Eq. 15).
        body: a `hairwarp.ops.BodyMesh` (one mesh or B), moved in place by `step`'s
            `body_vertices`; None: no hair-body contact.
        energy_config: weights and constants; `time_step` is the frame spacing [s].
        config: `PhysicsConfig`.
        dynamic: implicit-Euler steps (Eq. 6); False: static drapes (Eq. 5).
    """

    def __init__(self, rest_lengths: torch.Tensor, rigid: torch.Tensor, scalp_normals: torch.Tensor | None,
                 body, energy_config: EnergyConfig, config: PhysicsConfig, *, dynamic: bool = True):
        from hairwarp._validate import check_tensor
        from hairwarp.solvers.direct import DirectOptimizationConfig

        check_tensor("rigid", rigid, shape=(None, None, None, 3), allow_empty=False)
        if rigid.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"rigid: expected float32 or float64, got {rigid.dtype}")
        if rigid.shape[2] < NUM_FIXED_VERTICES + 1:
            raise ValueError(f"rigid: expected N >= 3 vertices per strand, got {rigid.shape[2]}")
        self.config, self.energy_config, self.dynamic = config, energy_config, dynamic
        self.device = rigid.device
        self.on_cuda = self.device.type == "cuda"
        self.use_graphs = self.on_cuda and config.cuda_graph
        batch, strands, vertices, _ = rigid.shape
        self.shape = tuple(rigid.shape)
        # Fixed buffers: the energy (and the graphs) read these; `step` writes them.
        self.rigid = rigid.detach().clone()
        self.normals = None if scalp_normals is None else scalp_normals.detach().clone()
        self.prev = self.rigid.clone()
        self.prev2 = self.rigid.clone()
        self.rigid_prev = self.rigid.clone()
        self.rigid_prev2 = self.rigid.clone()
        rest = rest_lengths.to(device=self.device, dtype=rigid.dtype)
        # (M, N) or (B, M, N) [m] arc length from the root
        self.arc_length = torch.cat([torch.zeros_like(rest[..., :1]), rest.cumsum(dim=-1)], dim=-1)
        self.body = body
        self.inputs = EnergyInputs(rest_lengths=rest_lengths, rigid=self.rigid, scalp_normals=self.normals, body=body,
                                   prev=self.prev if dynamic else None, prev2=self.prev2 if dynamic else None)
        self.start = self.rigid.clone()  # the step's starting point (all vertices)
        self.free_shape = (batch, strands, vertices - NUM_FIXED_VERTICES, 3)
        segments = batch * strands * (vertices - 1)
        self.capacity = 2 * segments  # hair-hair pair buffer of the graph-safe energy (regrown on overflow)
        # What the hair-body queries proved, kept over a solve's iterations (the body stands still
        # within one): reset whenever `set_frame` moves the body.
        self.body_cache = None
        if body is not None and energy_config.hair_body_weight != 0.0:
            from hairwarp.ops.hair_body_contact import HairBodyDistanceCache

            self.body_cache = HairBodyDistanceCache()
        self.pair_cache = None
        if not self.on_cuda and energy_config.hair_hair_weight != 0.0:
            from hairwarp.ops.hair_hair_contact import HairHairPairCache

            self.pair_cache = HairHairPairCache(skin=PHYSICS_PAIR_SKIN)
        # The steps' device pair list (`PhysicsConfig.hair_hair_list`), made with the solver (its
        # buffer's rows are `capacity`).
        wants_list = self.use_graphs if config.hair_hair_list is None else config.hair_hair_list
        self.list_cutoff = None
        if dynamic and wants_list and energy_config.hair_hair_weight != 0.0:
            self.list_cutoff = energy_config.hair_diameter + energy_config.hair_hair_dhat
            self.pair_cache = None
        self.pair_list = None
        self.chunk = config.chunk if dynamic else config.static_chunk
        # The solver's variables z = free targets / scale (`PhysicsConfig.stiffness_scaling`).
        self.scale = None
        self.preconditioner = None
        if config.strand_preconditioner and dynamic:
            from hairwarp.config import ALL_TERMS
            from hairwarp.ops.strand_preconditioner import StrandPreconditioner

            self.preconditioner = StrandPreconditioner(batch * strands, vertices, self.device, rigid.dtype)
            # z = U^T (t - origin), the origin the step's start: absolute targets times U (up to
            # ~300 along a segment) would leave float32 variables a resolution of ~1e-5.
            self.origin = self.rigid[:, :, NUM_FIXED_VERTICES:].clone()
            # the stiffness the bands are divided by: the inertia's per moving vertex (Eq. 16) [J/m^2]
            self.inertia_stiffness = (energy_config.inertia_weight * energy_config.vertex_mass
                                      / (strands * (vertices - NUM_FIXED_VERTICES) * energy_config.time_step ** 2))
            # Contact stays out of P (docs/physics.md, fourteenth session). At 512 strands, after 64
            # iterations a step was 0.27 mm from the tight one with hair-body differenced into P (B'
            # times the surface's curvature: indefinite, and one indefinite vertex shifted its
            # strand's whole P), 0.49 mm with its Gauss-Newton blocks B'' n n^T, 0.42 mm with those
            # and the hair-hair pairs' own-strand blocks, 0.04 mm with no contact in P. A contact's
            # curvature at the step's start models the step badly, and a pair's per-strand block
            # stiffens the two strands' common motion, which is free (the blocks: commit 0181ff7).
            self.preconditioner_terms = tuple(t for t in ALL_TERMS
                                              if t not in ("hair_hair_contact", "hair_body_contact", "stretch"))
            self.stretch_stiffness = 2.0 * energy_config.stretch_weight / (strands * (vertices - 1))
        elif config.chain_preconditioner > 0 and dynamic:
            from hairwarp.ops.strand_preconditioner import ChainPreconditioner

            if rest_lengths.dim() != 2:
                raise ValueError("rest_lengths: per-sample (B, M, N-1) rest lengths need chain_preconditioner = 0 in "
                                 "dynamic steps (the chain is one per strand)")
            stiffness = vertex_stiffness(energy_config, rest_lengths, inextensible=config.inextensible)
            self.preconditioner = ChainPreconditioner(rest_lengths, stiffness, energy_config,
                                                      exponent=config.stiffness_scaling,
                                                      tension=config.chain_preconditioner, device=self.device,
                                                      dtype=rigid.dtype)
            self.origin = self.rigid[:, :, NUM_FIXED_VERTICES:].clone()
        elif config.stiffness_scaling > 0 and dynamic and rest_lengths.dim() != 2:
            raise ValueError("rest_lengths: per-sample (B, M, N-1) rest lengths need stiffness_scaling = 0 in "
                             "dynamic steps (the scaling is one per strand and vertex)")
        if config.stiffness_scaling > 0 and dynamic and self.preconditioner is None:
            stiffness = vertex_stiffness(energy_config, rest_lengths, inextensible=config.inextensible)
            scale = (stiffness.min() / stiffness) ** config.stiffness_scaling
            self.scale = scale.to(device=self.device, dtype=rigid.dtype)[None, :, :, None].expand(self.free_shape)
            self.scale = self.scale.contiguous()
        self.solver = DirectOptimizationConfig(method="lbfgs", lbfgs_history=config.history,
                                               lbfgs_max_step=config.max_step, lbfgs_chunk=self.chunk,
                                               lbfgs_restart=5)
        self.lbfgs = None
        self.graphs: dict = {}
        self.residual = torch.zeros((), device=self.device, dtype=rigid.dtype)

    # -- the energy and the solver's calls over the fixed buffers --------------------------------
    def _assemble(self, z: torch.Tensor) -> torch.Tensor:
        """Positions (B, M, N, 3) from the solver's variables z (the free targets / `scale`)."""
        free = z.reshape(self.free_shape)
        if self.scale is not None:
            free = free * self.scale
        if self.preconditioner is not None:
            free = self.origin + self.preconditioner.targets(free)
        x = torch.cat([self.rigid[:, :, :NUM_FIXED_VERTICES], free], dim=2)
        if self.config.inextensible:
            from hairwarp.ops.strand_projection import follow_the_leader

            x = follow_the_leader(self.rigid, x)
        return x

    def _energy(self, x: torch.Tensor, graph_safe: bool):
        from hairwarp._validate import set_finite_checks

        free = x.detach().reshape(self.free_shape).requires_grad_(True)
        if not graph_safe and not bool(torch.isfinite(free).all()):
            # A trial that left the finite numbers never reaches the kernels: its loss is
            # non-finite, which the line search rejects.
            return torch.full((), math.inf, dtype=x.dtype, device=x.device), torch.zeros_like(x).reshape(-1), 0
        # The buffers were checked when they were written (`set_frame`, `set_state`), the iterate
        # just above: the per-call NaN scans of every input were 15 % of an iteration on the
        # 2-core CPU (256 x 100, whiplash: ~9 scans, 2.3 ms of 15.4).
        previous = set_finite_checks(False)
        try:
            with torch.enable_grad():
                xg = self._assemble(free)
                result = total_energy(xg, self.inputs, self.energy_config, dynamic=self.dynamic,
                                      graph_safe=graph_safe, hair_hair_capacity=self.capacity if graph_safe else None,
                                      hair_hair_cache=None if graph_safe else self.pair_cache,
                                      hair_hair_list=self.pair_list, hair_body_cache=self.body_cache)
                f = result.total.sum()
                (grad,) = torch.autograd.grad(f, free)
        finally:
            set_finite_checks(previous)
        info = result.hair_hair_info
        count = 0 if info is None else info.device_count
        return f.detach(), grad.reshape(-1), count

    def _position_gradient(self, x: torch.Tensor) -> torch.Tensor:
        """The energy's gradient (B, M, N, 3) [J/m] at positions x, stretch and contact left out
        (the strand preconditioner's differences: the other terms within a strand).
        """
        from hairwarp._validate import set_finite_checks

        previous = set_finite_checks(False)
        try:
            with torch.enable_grad():
                xg = x.detach().requires_grad_(True)
                result = total_energy(xg, self.inputs, self.energy_config, dynamic=True,
                                      terms=self.preconditioner_terms, graph_safe=self.use_graphs,
                                      hair_body_cache=self.body_cache)
                (grad,) = torch.autograd.grad(result.total.sum(), xg)
        finally:
            set_finite_checks(previous)
        return grad

    def _make_solver(self) -> None:
        from hairwarp.solvers.device_lbfgs import DeviceLBFGS

        if self.list_cutoff is not None:
            from hairwarp.ops.hair_hair_contact import HairHairPairList

            self.pair_list = None  # the old buffer goes before the new one comes
            self.pair_list = HairHairPairList(self.shape[:3], self.list_cutoff, self.config.hair_hair_list_skin,
                                              self.capacity, self.device, self.rigid.dtype)
            self.pair_list.build(self._assemble(self._variables(self.start)))
        self.lbfgs = DeviceLBFGS(self._energy, self._variables(self.start), self.solver, chunk=self.chunk,
                                 graph_safe=self.use_graphs)
        self.chunk_start = self.lbfgs.x.clone()

    def _begin(self) -> None:
        """A step's start: the pair list built there, evaluate at the start point, first direction."""
        if self.preconditioner is not None:
            if self.config.strand_preconditioner:  # each step's Newton matrix (the chain's is made once)
                from hairwarp.ops.strand_projection import follow_the_leader

                x0 = follow_the_leader(self.rigid, self.start, check=False) if self.config.inextensible else self.start
                self.preconditioner.build(x0, self._position_gradient, self.inertia_stiffness, self.stretch_stiffness)
            self.origin.copy_(self.start[:, :, NUM_FIXED_VERTICES:])
        z = self._variables(self.start)
        if self.pair_list is not None:
            self.pair_list.build(self._assemble(z))
        self.lbfgs.restart_at(z, keep_memory=self.config.keep_memory)
        self.residual.fill_(math.inf)

    def _rebuild(self) -> None:
        """After a chunk that left the pair list's reach: the list built at the iterate, the
        energy and the memory's direction there again (`DeviceLBFGS.refresh`).
        """
        self.pair_list.build(self._assemble(self.lbfgs.x))
        self.lbfgs.refresh()

    def _variables(self, x: torch.Tensor) -> torch.Tensor:
        """The solver's variables z of positions x (B, M, N, 3): the free vertices / `scale`."""
        free = x[:, :, NUM_FIXED_VERTICES:]
        if self.preconditioner is not None:
            return self.preconditioner.variables(free - self.origin)
        return free if self.scale is None else free / self.scale

    def _iterate(self, k: int) -> None:
        self.lbfgs.start_chunk()
        self.chunk_start.copy_(self.lbfgs.x)
        for _ in range(k):
            self.lbfgs.iterate()
        self._residual()

    def _residual(self) -> None:
        """The stopping rule's measure into `self.residual` [m] (graph-safe): the largest vertex
        move over the last chunk (a scaled-gradient step says nothing of the distance left).
        """
        moves = self.lbfgs.x - self.chunk_start
        if self.scale is not None:
            moves = moves * self.scale.reshape(-1)
        if self.preconditioner is not None:
            moves = self.preconditioner.targets(moves.view(self.free_shape))
        self.residual.copy_(torch.linalg.vector_norm(moves.view(-1, 3), dim=1).max())
        if self.pair_list is not None:
            self.pair_list.mark_stale(self._assemble(self.lbfgs.x))

    def _run(self, name: str, fn) -> None:
        """`fn()` eagerly, or replayed from its CUDA graph (captured at the first call)."""
        if not self.use_graphs:
            fn()
            return
        graph = self.graphs.get(name)
        if graph is None:
            from hairwarp.runtime import CapturedCall

            with torch.cuda.device(self.device):
                # The warm-up runs `fn` once for real; the capture itself runs nothing.
                self.graphs[name] = CapturedCall(fn, warmup=1)
            return
        graph()

    # -- one solve ---------------------------------------------------------------------------
    def solve(self, start: torch.Tensor, max_iterations: int, tolerance: float | None = None) -> StepReport:
        """Minimise from `start` (B, M, N, 3) (its fixed vertices replaced by the rigid placement's);
        the result is `self.positions()`. `tolerance` [m] replaces the config's for this solve.

        A static drape (no inertia) is restarted with a fresh L-BFGS memory from where it stopped
        for as long as a restart still lowers the energy (by more than `STALL_RELATIVE_DECREASE`
        of it), within `max_iterations` in all: without inertia the solver stalls (its line
        searches stop moving the hair, which the stopping rule cannot tell from convergence) far
        from the optimum. Long curly hair at rest, 64 strands: the first solve stopped after 100
        iterations at E = 0.19969 J with the tips 1.6 mm below the rigid placement; five restarts
        reached 0.19643 J and 12.3 mm, where a second of the implicit-Euler simulation with the
        pose held settled (0.1965 J, 11.8 mm) (docs/physics.md, "The static drape's stall").
        """
        report = self._solve_once(start, max_iterations, tolerance)
        total = report.iterations
        while not self.dynamic and report.stop_reason == "tolerance" and total < max_iterations:
            before = report.energy
            report = self._solve_once(self.positions().detach().clone(), max_iterations - total, tolerance)
            total += report.iterations
            if not report.energy < before - STALL_RELATIVE_DECREASE * abs(before):
                break
        return StepReport(iterations=total, stop_reason=report.stop_reason, residual=report.residual,
                          energy=report.energy, rebuilds=report.rebuilds)

    def _solve_once(self, start: torch.Tensor, max_iterations: int, tolerance: float | None) -> StepReport:
        """One L-BFGS run from `start` with a fresh memory (`solve`)."""
        self.start.copy_(start)
        self.start[:, :, :NUM_FIXED_VERTICES] = self.rigid[:, :, :NUM_FIXED_VERTICES]
        while True:
            if self.lbfgs is None:
                self._make_solver()
            self.lbfgs.pairs.zero_()
            self._run("begin", self._begin)
            done, reason, rebuilds = 0, "max_iterations", 0
            chunk = self.chunk
            if tolerance is None:
                tolerance = self.config.tolerance if self.dynamic else self.config.static_tolerance
            residual = previous = math.inf
            rule = self.config.stopping if self.dynamic else "move"
            overflow = False
            while True:
                watched = [self.residual, self.lbfgs.pairs, self.lbfgs.f]
                if self.pair_list is not None:
                    watched.append(self.pair_list.stale)
                values = torch.stack([v.double().reshape(()) for v in watched]).tolist()
                previous, residual, pairs = residual, values[0], int(values[1])
                stale = len(values) > 3 and values[3] != 0
                if (self.use_graphs or self.pair_list is not None) and pairs > self.capacity:
                    overflow = True
                    break
                if not math.isfinite(values[2]):
                    reason = "diverged: non-finite energy"
                    break
                if stale:
                    # A vertex left the pair list's reach during the chunk: the list again, here.
                    self._run("rebuild", self._rebuild)
                    rebuilds += 1
                # Two chunks at least: a line search that rejects a step's first trials moves
                # nothing for a chunk while the hair still has far to go.
                elif remaining_distance(residual, previous, rule) <= tolerance and done >= 2 * chunk:
                    reason = "tolerance"
                    break
                if done >= max_iterations:
                    break
                k = min(chunk, max_iterations - done)
                if self.use_graphs and k != chunk:
                    k = chunk  # one graph holds `chunk` iterations; the cap is met to a chunk
                self._run(f"iterate{k}", lambda k=k: self._iterate(k))
                done += k
            if not overflow:
                break
            # More hair-hair pairs than the buffer holds: a larger buffer, new graphs, the step again.
            self.capacity = 2 * pairs
            self.graphs.clear()
            self.lbfgs = None
        return StepReport(iterations=done, stop_reason=reason, residual=residual, energy=values[2], rebuilds=rebuilds)

    def positions(self) -> torch.Tensor:
        """(B, M, N, 3) the last solve's result [m] (a new tensor)."""
        return self._assemble(self.lbfgs.x).detach().clone()

    def set_frame(self, rigid: torch.Tensor, scalp_normals: torch.Tensor | None = None,
                  body_vertices: torch.Tensor | None = None) -> None:
        """Write a frame's rigid placement, scalp normals and posed body into the buffers (the
        rigid placements of the two frames before are kept for the warm start).

        Raises:
            ValueError: naming the argument, for a shape unlike the solver's or NaN/Inf.
        """
        from hairwarp._validate import check_tensor

        check_tensor("rigid", rigid, shape=("...", *self.shape[1:]), device=self.device)
        if scalp_normals is not None:
            check_tensor("scalp_normals", scalp_normals, device=self.device)
        self.rigid_prev2.copy_(self.rigid_prev)
        self.rigid_prev.copy_(self.rigid)
        self.rigid.copy_(rigid)
        if self.normals is not None and scalp_normals is not None:
            self.normals.copy_(scalp_normals.reshape(self.normals.shape))
        if self.body is not None and body_vertices is not None:
            self.body.update(body_vertices)
            if self.body_cache is not None:
                self.body_cache.reset()

    def set_state(self, x: torch.Tensor, x_prev: torch.Tensor | None = None) -> None:
        """The hair's state: x_{t-1} = x and x_{t-2} = x_prev (default x: at rest).

        Raises:
            ValueError: naming the argument, for a shape unlike the solver's or NaN/Inf.
        """
        from hairwarp._validate import check_tensor

        check_tensor("x", x, shape=("...", *self.shape[1:]), device=self.device)
        if x_prev is not None:
            check_tensor("x_prev", x_prev, shape=("...", *self.shape[1:]), device=self.device)
        self.prev.copy_(x)
        self.prev2.copy_(x if x_prev is None else x_prev)

    def prediction(self) -> torch.Tensor:
        """The step's start (B, M, N, 3): the inertial prediction 2 x_{t-1} - x_{t-2}, plus the
        head's own unpredicted move (the rigid placement against its inertial prediction)
        weighted by exp(-s / `PhysicsConfig.head_follow_length`), s the arc length from the root:
        hair near the root goes where the head went.
        """
        x = 2 * self.prev - self.prev2
        length = self.config.head_follow_length
        if length > 0:
            surprise = self.rigid - (2 * self.rigid_prev - self.rigid_prev2)
            fade = torch.exp(-self.arc_length / length)
            x = x + (fade if fade.dim() == 3 else fade[None])[..., None] * surprise
        return x

    def step(self, tolerance: float | None = None) -> StepReport:
        """One implicit-Euler step from the inertial prediction (to `tolerance` [m], default the
        config's); the state moves on.
        """
        if not self.dynamic:
            raise RuntimeError("step: this solver drapes statically (dynamic=False)")
        report = self.solve(self.prediction(), self.config.max_iterations, tolerance)
        x = self.positions()
        self.prev2.copy_(self.prev)
        self.prev.copy_(x)
        return report


@dataclass
class PhysicsResult:
    """A simulated motion (or one static drape).

    Attributes:
        positions: (T, B, M, N, 3) hair positions per frame [m].
        reports: one `StepReport` per frame (frame 0: the static drape, or "initial" when given).
        time_s: wall time of the solves [s] (device synchronised), posing and the body's build
            excluded (`setup_s`).
        setup_s: posing the frames and building the body [s].
        frame_ms: wall time of each frame's solve [ms] (frame 0 the static drape's, settling
            included).
        settle_steps: the implicit-Euler steps taken with the first pose held
            (`PhysicsConfig.settle_time`).
    """

    positions: torch.Tensor
    reports: list[StepReport]
    time_s: float
    setup_s: float
    frame_ms: list[float] = field(default_factory=list)
    settle_steps: int = 0

    @property
    def iterations(self) -> list[int]:
        return [r.iterations for r in self.reports]

    @property
    def stop_reasons(self) -> list[str]:
        return [r.stop_reason for r in self.reports]


@dataclass
class RestingDrape:
    """A static drape brought to rest (`drape_at_rest`).

    Attributes:
        positions: (B, M, N, 3) the drape [m].
        report: its solves together: iterations of the static solves and the settling steps,
            the last static solve's stop reason and residual, the drape's energy [J] (summed).
        settle_steps: implicit-Euler steps taken with the pose held.
        settled: (B,) bool, per frame: the settled drape was kept (lower energy than the first
            static solve's).
    """

    positions: torch.Tensor
    report: StepReport
    settle_steps: int
    settled: torch.Tensor


def settling_solver(rest_lengths: torch.Tensor, rigid: torch.Tensor, scalp_normals: torch.Tensor | None, body,
                    energy_config: EnergyConfig, config: PhysicsConfig) -> PhysicsSolver:
    """The implicit-Euler solver that `drape_at_rest` settles a drape with (the same arguments
    as `PhysicsSolver`; its `energy_config.time_step` the settling step). Per-sample rest lengths
    (B, M, N-1) take no per-vertex stiffness scaling (one per strand and vertex).
    """
    if rest_lengths.dim() == 3:
        config = replace(config, stiffness_scaling=0.0)
    return PhysicsSolver(rest_lengths, rigid, scalp_normals, body, energy_config, config, dynamic=True)


def settle_with_pose_held(dynamic: PhysicsSolver, start: torch.Tensor, max_steps: int,
                          settle_tolerance: float, momentum: float = 1.0) -> tuple[int, int]:
    """Implicit-Euler steps of `dynamic` from `start` at rest with its frame's pose held, until a
    step moves no vertex farther than `settle_tolerance` [m] or after `max_steps`; each step is
    solved to `settle_tolerance` or the config's `tolerance`, whichever is looser. The solver's
    state is left at the last step (`dynamic.prev`).

    Args:
        dynamic: a `PhysicsSolver` with dynamic=True, its buffers at the frame to hold.
        start: (B, M, N, 3) the state to start from, at rest [m].
        max_steps: the most steps to take.
        settle_tolerance: the stopping rule's scale [m].
        momentum: the share of each step's velocity the next step inherits, in (0, 1]: 1, the
            physics' own motion (the hair swings about its rest on the way there); less, a damped
            settle that approaches the rest without swinging past it.

    Returns:
        (steps taken, L-BFGS iterations of them).
    """
    # the pose held: no head move for the warm start to add
    dynamic.rigid_prev.copy_(dynamic.rigid)
    dynamic.rigid_prev2.copy_(dynamic.rigid)
    dynamic.set_state(start)
    steps, iterations = 0, 0
    step_tolerance = max(dynamic.config.tolerance, settle_tolerance)
    for _ in range(max_steps):
        before = dynamic.prev.clone()
        iterations += dynamic.step(tolerance=step_tolerance).iterations
        steps += 1
        if momentum < 1.0:
            dynamic.prev2.copy_(dynamic.prev - momentum * (dynamic.prev - before))
        if float((dynamic.prev - before).norm(dim=-1).max()) <= settle_tolerance:
            break
    return steps, iterations


def drape_at_rest(static: PhysicsSolver, dynamic: PhysicsSolver | None, start: torch.Tensor,
                  config: PhysicsConfig) -> RestingDrape:
    """The static optimum of each frame (Eq. 5), at rest: where the hair hangs when its pose is held.

    L-BFGS from a rigid placement stalls above where the hair hangs (at full size it stopped 0.7-12 %
    above the settled energy, the tips 3-129 mm higher; docs/physics.md, "Sixteenth session"). So
    the first static solve is followed by implicit-Euler steps with the pose held, damped
    (`config.settle_momentum`), for at most `config.settle_time` [s] (each step solved to
    `settle_tolerance`, the scale rest is judged at),
    until a step moves no vertex farther than `settle_tolerance`; a static solve from there
    polishes the settled state to `static_tolerance`. Per frame the lower-energy drape of the two
    is kept: settling dissipates energy but is not bound to lower it.

    Args:
        static: a `PhysicsSolver` with dynamic=False on the frames.
        dynamic: a `PhysicsSolver` with dynamic=True on the same frames (its buffers: the same
            rigid placement, scalp normals and body; its `time_step` the settling steps'; its
            state is left at the settled drape); None: no settling.
        start: (B, M, N, 3) where the first static solve starts [m].
        config: `PhysicsConfig` (`static_max_iterations`, `settle_time`, `settle_tolerance`,
            `settle_momentum`).
    """
    from hairwarp.energy import total_energy

    first = static.solve(start, config.static_max_iterations)
    x = static.positions()
    batch = x.shape[0]
    if dynamic is None or config.settle_time <= 0:
        return RestingDrape(x, first, 0, torch.zeros(batch, dtype=torch.bool))
    steps, settle_iterations = settle_with_pose_held(
        dynamic, x, max(1, int(round(config.settle_time / dynamic.energy_config.time_step))), config.settle_tolerance,
        config.settle_momentum)
    iterations = first.iterations + settle_iterations
    polish = static.solve(dynamic.prev, config.static_max_iterations)
    y = static.positions()
    with torch.no_grad():
        energy_first = total_energy(x, static.inputs, static.energy_config).total.reshape(-1)
        energy_settled = total_energy(y, static.inputs, static.energy_config).total.reshape(-1)
    settled = energy_settled <= energy_first
    positions = torch.where(settled[:, None, None, None], y, x)
    report = StepReport(iterations=iterations + polish.iterations, stop_reason=polish.stop_reason,
                        residual=polish.residual, energy=float(torch.minimum(energy_first, energy_settled).sum()),
                        rebuilds=first.rebuilds + polish.rebuilds)
    return RestingDrape(positions, report, steps, settled.cpu())


# Frames posed at once (the body and rigid placement of a motion's frames, without body meshes).
_POSE_CHUNK = 32


def simulate_physics(scene, frame_indices=None, *, device="cpu", energy_config: EnergyConfig | None = None,
                     config: PhysicsConfig | None = None, initial: torch.Tensor | None = None,
                     split_self_intersections: bool = True, progress: bool = False) -> PhysicsResult:
    """Implicit-Euler simulation of a scene's hair over consecutive frames.

    Frame 0 (the first index) is the static drape of that frame unless `initial` is given
    (settled with the pose held for up to `PhysicsConfig.settle_time`); the hair rests there
    before the motion starts (x_{-1} = x_{-2} = x_0). Frames are posed in
    chunks of 32 as they are needed (memory flat in the motion's length); the body is built
    once, at the first frame, and moved in place, its self-intersections cut where any of every
    `SPLIT_POSE_STRIDE`-th pose passes through itself (`Scene.moving_body`).

    Args:
        scene: a `hairwarp.scene.Scene`.
        frame_indices: consecutive frame indices (default: all).
        device: torch device.
        energy_config: weights and constants, its `time_step` the step [s] (default
            `EnergyConfig()` at the scene's frame spacing).
        config: `PhysicsConfig` (default `PhysicsConfig()`).
        initial: (1, M, N, 3) or (M, N, 3) state at the first frame [m].
        split_self_intersections: cut the body where it passes through itself (over the motion's poses).
        progress: show a progress bar over frames.

    Returns:
        PhysicsResult with positions (T, 1, M, N, 3).
    """
    from tqdm.auto import tqdm

    device = torch.device(device)
    config = config or PhysicsConfig()
    if energy_config is None:
        energy_config = EnergyConfig().replace(time_step=1.0 / float(scene.motion.fps))
    indices = list(range(scene.num_frames)) if frame_indices is None else [int(i) for i in frame_indices]
    if not indices:
        raise ValueError("frame_indices: expected at least one frame")
    if any(b != a + 1 for a, b in zip(indices, indices[1:])):
        raise ValueError(f"frame_indices: expected consecutive frames (one time step apart), got {indices[:8]}...")
    setup_start = time.perf_counter()
    posed_chunks: dict[int, object] = {}

    def frame(position: int):
        chunk = position // _POSE_CHUNK
        if chunk not in posed_chunks:
            posed_chunks.clear()  # one chunk held at a time
            part = indices[chunk * _POSE_CHUNK:(chunk + 1) * _POSE_CHUNK]
            posed_chunks[chunk] = scene.frames(part, device=device, build_body=False)
        f = posed_chunks[chunk]
        i = position % _POSE_CHUNK
        return f.rigid.positions[i:i + 1], f.rigid.normals[i:i + 1], f.posed.vertices[i:i + 1]

    rigid0, normals0, body0 = frame(0)
    # The body moves in place (`set_frame`): its cuts must cover the crossings of every pose it
    # moves through, not of the first alone (a walk's arm crosses the chest later).
    body = scene.moving_body(indices, device=device, dtype=body0.dtype, bvh="lbvh",
                             split_self_intersections=split_self_intersections)
    body.update(body0)  # posed with its chunk, as every later frame is (a batch rounds apart by ~6e-8 m)
    rest = scene.rest_lengths.to(device=device, dtype=torch.float32)
    synchronize(device)
    setup = time.perf_counter() - setup_start
    reports, states, frame_ms = [], [], []
    start = time.perf_counter()
    solver = PhysicsSolver(rest, rigid0, normals0, body, energy_config, config, dynamic=True)
    settle_steps = 0
    if initial is None:
        static = PhysicsSolver(rest, rigid0, normals0, body, energy_config, config, dynamic=False)
        drape = drape_at_rest(static, solver, rigid0, config)
        del static
        x0, settle_steps = drape.positions, drape.settle_steps
        reports.append(drape.report)
    else:
        from hairwarp._validate import check_tensor

        check_tensor("initial", initial, shape=("...", rigid0.shape[1], rigid0.shape[2], 3), allow_empty=False)
        x0 = (initial if initial.dim() == 4 else initial.unsqueeze(0)).to(device=device, dtype=torch.float32)
        reports.append(StepReport(0, "initial", 0.0, float("nan")))
    solver.set_state(x0)
    synchronize(device)
    frame_ms.append((time.perf_counter() - start) * 1e3)
    states.append(x0.detach().clone())
    for position in tqdm(range(1, len(indices)), desc="physics", disable=not progress, leave=False):
        t0 = time.perf_counter()
        setup_t0 = t0
        rigid, normals, vertices = frame(position)
        solver.set_frame(rigid, normals, vertices)
        report = solver.step()
        states.append(solver.prev.clone())
        reports.append(report)
        synchronize(device)
        frame_ms.append((time.perf_counter() - setup_t0) * 1e3)
    synchronize(device)
    elapsed = time.perf_counter() - start
    return PhysicsResult(positions=torch.stack(states), reports=reports, time_s=elapsed, setup_s=setup,
                         frame_ms=frame_ms, settle_steps=settle_steps)
