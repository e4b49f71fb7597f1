"""The hair's own state, carried frame to frame: a learned inertial step on top of a static drape.

The paper's dynamic network reads the body's motion through a GRU and fuses it with the static
features; its output is a function of the pose (docs/network_diagnosis.md, D1: zeroing the motion
moves it 0.2 mm; D2: when the head stops, it stops). The hair itself carries no state. This step
gives it one: the last two drapes x(t-1), x(t-2), as the implicit-Euler step of Eq. 16 does.

Per frame t, with E(t) the equilibrium drape of the frame (the static network's, or any method's)
and P_rigid(t) the rigid placement (Eq. 1):

    y(t) = x(t-1) + beta * (x(t-1) - x(t-2))          inertial prediction, beta the velocity kept
    p(t) = E(t) + G * (y(t) - E(t))                   pulled toward the equilibrium by 1 - G
    x(t) = follow_the_leader(P_rigid(t), p(t))        rest lengths kept, vertices 0 and 1 fixed

For a quadratic energy of stiffness k, one implicit-Euler step of Eq. 16 is exactly this blend with
G = 1 / (1 + h^2 k) and beta = 1: the step is implicit Euler with a learned, per-vertex stiffness
(G) and damping (beta), and follow-the-leader is the inextensibility constraint of position-based
hair (the projection of the static drape, `StaticConfig.length_projection`). beta < 1 damps the
velocity itself, a drag: hair carried at a steady speed (a walk) trails its equilibrium. The
option `damping="relative"` damps only the velocity relative to the head's instead,
y(t) = x(t-1) + u + beta * (x(t-1) - x(t-2) - u) with u = P_rigid(t-1) - P_rigid(t-2), which
removes that drag (hair carried at a steady u trails by G (1 - beta) / (1 - G) frames of it under
the drag). Trained as a per-vertex step it swung less and later than the physics on every held-out
motion (docs/network_diagnosis.md, "The hair's own state"), so the config's default stays the drag;
as a chain with constants chosen on full-size clips it is the shipped step's (same page,
"Twentieth session").
G and beta are read from each vertex's rest arc length (the distance from the root s, the strand's
length L, s / L) by a small MLP, so that one step serves any hairstyle, strand count and vertex count.

`coupling="chain"` couples the vertices along the strand, as a hanging strand's tension does. A
per-vertex G gives every vertex an oscillator of its own about its equilibrium; a strand under
its weight instead swings as a chain whose slowest mode moves the whole strand (the physics'
overshoot after the head stops, which the per-vertex step does not make: docs/network_diagnosis.md,
fourteenth session). With d = y - E over the free vertices, the linear implicit-Euler step of a
chain is (I + D + L_w) d' = d: D = diag((1 - G) / G) the per-vertex pull, L_w the Laplacian of the
strand's segments weighted by a tension w >= 0 (the segment to the fixed vertex 1 ties the first
free vertex to the scalp), so p = E + (I + D + L_w)^-1 d. With w = 0 this is the per-vertex step;
w is a hanging strand's (h^2 g (L - s) / l^2, `hanging_chain_tension`) times a learned factor.
The operator is one (N-2) x (N-2) inverse per strand, made once per sequence (`coefficients`).

`body_hold` holds the chain along the body's outward normal where the frame's equilibrium lies
within `body_hold_distance` of the body: the relaxation of the offsets d = y - E becomes, per
strand, (C (x) I_3 + sum_i kappa n_i n_i^T) d' = d, C = I + D + L_w + b A^T A the chain's matrix,
n_i the outward direction of the body at free vertex i of the equilibrium and the sum over the
vertices within the distance. The static network's drape lies on the body where the physics' hair
rests on it; a free chain swings those strands into and out of the body (which the body pass then
flattens) where the physics' slide along it. Along the normal only, the tangent left free: pinned
in every direction the strands on the shoulders stop swinging sideways where the physics' still do
(docs/network_diagnosis.md, T8). Solved with C's inverse and one n x n system per held strand
(Woodbury's identity, `body_held_chain_relaxation`). Off by default: at full size it brings long
hair resting on the body nearer the physics (the demo's scene) and takes swing away everywhere
else, since it damps the lift-off from the body that the physics' one-sided contact allows
(docs/network_diagnosis.md, T9: 14 -> 7 of 24 training goals at 100 @ 2 cm).

`equilibrium_speed` limits how fast E(t) - P_rigid(t), the equilibrium's offset from the rigid
placement, may change per strand: the static network's drape can jump between frames where the
hair cannot, and the step would swing every jump (`InertialConfig.equilibrium_speed`).

`projection_damping` is dynamic follow-the-leader's velocity correction (Mueller et al. 2012, "Fast
simulation of inextensible hair and fur"): follow-the-leader moves each vertex i by a correction
c_i = x_i - p_i onto its rest length, and a step that reads its velocity from the projected
positions takes that move as momentum. On a curled strand the corrections do not cancel: the
shipped step (`projection_damping` 0) held still with a 1 mm kick on long curly hair amplifies it
3x every half second, to 17 cm in 2.5 s, where straight and wavy hair settle (docs/network_diagnosis.md,
T23). With s = `projection_damping` the velocity the next step reads is
x_i(t) - x_i(t-1) - s c_(i+1)(t): each vertex gives back the correction of the vertex it leads,
which the projection took from it.

Trained on physics trajectories (`hairwarp.training.inertial`): rollouts from the first frame, on
the step's own predictions, back-propagated through the whole clip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from hairwarp._validate import check_tensor
from hairwarp.config import NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.models.config import _DictConfig
from hairwarp.ops.strand_projection import follow_the_leader

# Features of a vertex read by the coefficient MLP: s / L, s [m], L [m].
NUM_VERTEX_FEATURES = 3
# What beta damps (`InertialConfig.damping`).
DAMPINGS = ("relative", "absolute")
# How the pull toward the equilibrium couples the vertices (`InertialConfig.coupling`).
COUPLINGS = ("vertex", "chain")
# The velocity a frame pushed out of the body hands on (`InertialConfig.keep_out_velocity`).
KEEP_OUT_VELOCITIES = ("pushed", "raw", "tangential")
# Rest curliness (`strand_curliness`) where a strand starts to take the curled strands' settings
# (`InertialConfig.curl_bending`, `curl_gate`) and where it takes them whole. The procedural presets
# at full size (1 - chord / arc over 12 cm, strand means): long straight 0.000-0.027, bob 0.000-0.069,
# short straight 0.000-0.124, medium wavy 0.025-0.111, long curly 0.180-0.412.
CURL_ONSET = 0.1
CURL_FULL = 0.25
# The arc over which a strand's chord is compared to its arc length [m]: a few turns of a curl.
CURL_WINDOW = 0.12


@dataclass(frozen=True)
class InertialConfig(_DictConfig):
    """Settings of `InertialStep`.

    Attributes:
        hidden_dim: width of the two hidden layers of the coefficient MLP.
        gate_init: G of every vertex at initialisation (the pull toward the equilibrium is
            1 - G per frame): 0.98 at 60 fps, the order of a 0.4 m pendulum's h^2 g / L.
        retention_init: beta at initialisation (the share of the last frame's velocity kept).
        fps: the frame rate the step is trained for [1/s]; a motion at another rate is
            resampled to it by the caller (`hairwarp.scene.motion.resample_motion`).
        damping: what beta damps: "absolute", the velocity itself (a drag), or "relative", the
            velocity relative to the head's (the module docstring; measured worse).
        coupling: "vertex", each vertex pulled toward its equilibrium on its own, or "chain",
            the pull coupled along the strand by a learned tension (the module docstring).
        tension_init: the chain's tension at initialisation, as a multiple of a hanging strand's
            (`hanging_chain_tension`); the MLP learns the factor per vertex.
        equilibrium_speed: the fastest the equilibrium's offset from the rigid placement may move
            [m/s], per strand (the mean over its moving vertices); None, unlimited. The static
            network's drape of a strand can jump between frames (a long strand flips from one side
            of the shoulder to the other and back: up to 110 mm in one frame where the physics'
            strands move at most 17-40 mm), and the step turns every such jump into a swing that
            flings the strand out (docs/network_diagnosis.md, "Twentieth session"). The pose moves
            the resting drape slowly; the swing is the step's own.
        bending: the chain's bending stiffness b >= 0 (dimensionless): the relaxation also
            penalises b * sum (d[i-1] - 2 d[i] + d[i+1])^2, the offset's second differences along
            the strand with the root clamped (vertices 0 and 1 offset 0), so that a strand swings
            more as a lever and less as a hanging chain. 0: no bending term. With 100 vertices it
            acts from about 1e4 (docs/network_diagnosis.md, "Twentieth session", T5).
        body_hold: kappa >= 0, the stiffness (dimensionless, as D) holding a chain's free vertex along
            the body's outward normal where the frame's equilibrium lies within `body_hold_distance`
            of the body (module docstring); 0: no hold. Needs `coupling="chain"`, and the
            equilibrium's distances and normals handed to `rollout(hold=...)`.
        body_hold_distance: delta [m] > 0, how near the body the equilibrium's vertex must lie to
            be held.
        keep_out_state: the method's body pass acts on the step's state: each frame is pushed
            out of the body before the next frame's step reads it (`rollout(project=...)`), so a
            strand that swings into the shoulder stops there as the physics' does. False: the
            pass acts on the rollout's output and the state swings on through the body.
        keep_out_equilibrium: the method's body pass acts on the equilibrium too, before the
            rollout reads it: the step is pulled to the static network's drape as the static
            method shows it (the step at rest is then what `drape` returns), not to vertices
            inside the body that the pass must push out of every frame anew. False: the
            network's drape as it comes.
        keep_out_velocity: with `keep_out_state`, the velocity the next step reads from a pushed
            frame: "pushed", the pushed state's (x(t) - x(t-1) of the states as pushed: the push
            is added to it); "raw", the step's own, as it was before the push (the positions kept
            out, the swing's momentum not touched by the pass); "tangential", the step's own less
            its component into the body along each vertex's push (the contact takes the normal
            velocity, the strand slides on).
        settle_steps: at a motion's start, the physics' own implicit-Euler steps
            (`hairwarp.solvers.physics.settle_with_pose_held`) from the first frame's equilibrium
            with its pose held; the settled drape's offset from that equilibrium, turned with the
            head (M_head of Eq. 1), is added to every frame's equilibrium, and the rollout starts
            at rest on the settled drape. The static network's drape of long hair rests a
            centimetre above the physics' (docs/network_diagnosis.md, T18); a few steps take it
            down. 0: no settle.
        settle_momentum: the share of each settling step's velocity the next inherits, in (0, 1]
            (`settle_with_pose_held`'s `momentum`): 1 swings about the rest on the way there.
        projection_damping: s in [0, 1], dynamic follow-the-leader's velocity correction (module
            docstring): the share of the next vertex's projection correction taken from each
            vertex's velocity. 0: the projected positions' own velocity.
        curl_bending: the share of `bending` a curled strand keeps, in [0, 1] (1: every strand the
            same). A curl bounces as a spring, uncoiling and coiling as the head bobs, and that
            breathing is the offset's second differences that the bending term penalises
            (docs/network_diagnosis.md, T22: without bending the step's curls bounce as far as the
            physics'). Each strand's bending is b (1 - w (1 - curl_bending)), w its rest curliness
            (`strand_curliness`) mapped linearly from 0 at `CURL_ONSET` to 1 at `CURL_FULL`:
            straight and wavy hair keep b whatever this is.
        curl_gate: G of a curled strand's vertices, in (0, 1), blended with the MLP's G by the same
            weight w in logit space; None: the MLP's G for every strand. Without its bending a curl
            swings as a softer pendulum (slower and wider than the physics' along the walk,
            docs/network_diagnosis.md, T24); a stronger pull gives the pendulum back its pace.
    """

    hidden_dim: int = 32
    gate_init: float = 0.98
    retention_init: float = 0.9
    fps: float = 60.0
    damping: str = "absolute"
    coupling: str = "vertex"
    tension_init: float = 1.0
    equilibrium_speed: float | None = None
    keep_out_state: bool = False
    keep_out_equilibrium: bool = False
    keep_out_velocity: str = "pushed"
    bending: float = 0.0
    body_hold: float = 0.0
    body_hold_distance: float = 0.02
    settle_steps: int = 0
    settle_momentum: float = 0.8
    projection_damping: float = 0.0
    curl_bending: float = 1.0
    curl_gate: float | None = None

    def __post_init__(self):
        if not isinstance(self.hidden_dim, int) or isinstance(self.hidden_dim, bool) or self.hidden_dim <= 0:
            raise ValueError(f"InertialConfig.hidden_dim: expected a positive int, got {self.hidden_dim!r}")
        for name in ("gate_init", "retention_init"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not 0.0 < value < 1.0:
                raise ValueError(f"InertialConfig.{name}: expected a number in (0, 1), got {value!r}")
        if not isinstance(self.fps, (int, float)) or not self.fps > 0 or math.isinf(self.fps):
            raise ValueError(f"InertialConfig.fps: expected a positive number, got {self.fps!r}")
        if self.damping not in DAMPINGS:
            raise ValueError(f"InertialConfig.damping: expected one of {list(DAMPINGS)}, got {self.damping!r}")
        if self.coupling not in COUPLINGS:
            raise ValueError(f"InertialConfig.coupling: expected one of {list(COUPLINGS)}, got {self.coupling!r}")
        if not isinstance(self.tension_init, (int, float)) or not 0.0 < self.tension_init < math.inf:
            raise ValueError(f"InertialConfig.tension_init: expected a positive number, got {self.tension_init!r}")
        speed = self.equilibrium_speed
        if speed is not None and (not isinstance(speed, (int, float)) or isinstance(speed, bool) or not speed >= 0
                                  or math.isinf(speed)):
            raise ValueError(f"InertialConfig.equilibrium_speed: expected None or a number >= 0 [m/s], got {speed!r}")
        if (not isinstance(self.bending, (int, float)) or isinstance(self.bending, bool) or not self.bending >= 0
                or math.isinf(self.bending)):
            raise ValueError(f"InertialConfig.bending: expected a number >= 0, got {self.bending!r}")
        if (not isinstance(self.body_hold, (int, float)) or isinstance(self.body_hold, bool) or not self.body_hold >= 0
                or math.isinf(self.body_hold)):
            raise ValueError(f"InertialConfig.body_hold: expected a number >= 0, got {self.body_hold!r}")
        if self.body_hold and self.coupling != "chain":
            raise ValueError(f"InertialConfig.body_hold: holds a chain; expected coupling='chain' with it, got "
                             f"coupling={self.coupling!r}")
        distance = self.body_hold_distance
        if (not isinstance(distance, (int, float)) or isinstance(distance, bool) or not distance > 0
                or math.isinf(distance)):
            raise ValueError(f"InertialConfig.body_hold_distance: expected a number > 0 [m], got {distance!r}")
        for name in ("keep_out_state", "keep_out_equilibrium"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"InertialConfig.{name}: expected a bool, got {getattr(self, name)!r}")
        if not isinstance(self.settle_steps, int) or isinstance(self.settle_steps, bool) or self.settle_steps < 0:
            raise ValueError(f"InertialConfig.settle_steps: expected an int >= 0, got {self.settle_steps!r}")
        momentum = self.settle_momentum
        if not isinstance(momentum, (int, float)) or isinstance(momentum, bool) or not 0.0 < momentum <= 1.0:
            raise ValueError(f"InertialConfig.settle_momentum: expected a number in (0, 1], got {momentum!r}")
        damping = self.projection_damping
        if not isinstance(damping, (int, float)) or isinstance(damping, bool) or not 0.0 <= damping <= 1.0:
            raise ValueError(f"InertialConfig.projection_damping: expected a number in [0, 1], got {damping!r}")
        share = self.curl_bending
        if not isinstance(share, (int, float)) or isinstance(share, bool) or not 0.0 <= share <= 1.0:
            raise ValueError(f"InertialConfig.curl_bending: expected a number in [0, 1], got {share!r}")
        gate = self.curl_gate
        if gate is not None and (not isinstance(gate, (int, float)) or isinstance(gate, bool) or not 0.0 < gate < 1.0):
            raise ValueError(f"InertialConfig.curl_gate: expected None or a number in (0, 1), got {gate!r}")
        if self.keep_out_velocity not in KEEP_OUT_VELOCITIES:
            raise ValueError(f"InertialConfig.keep_out_velocity: expected one of {list(KEEP_OUT_VELOCITIES)}, got "
                             f"{self.keep_out_velocity!r}")


def vertex_features(rigid: torch.Tensor) -> torch.Tensor:
    """What the coefficient MLP reads per vertex: (s / L, s, L) from the rest segment lengths.

    Args:
        rigid: (..., M, N, 3) strands at their rest lengths [m] (any frame of the rigid placement).

    Returns:
        (M, N, 3) features (of the first frame when `rigid` has leading dimensions).
    """
    _, s = _rest_arc_lengths(rigid)
    length = s[:, -1:].clamp_min(1e-9).expand_as(s)
    return torch.stack([s / length, s, length], dim=-1)


def _rest_arc_lengths(rigid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(segment lengths (M, N-1), arc length from the root (M, N)) [m] of the first frame's strands."""
    strands = rigid.reshape(-1, *rigid.shape[-3:])[0]
    seg = (strands[:, 1:] - strands[:, :-1]).norm(dim=-1)
    return seg, torch.cat([torch.zeros_like(seg[:, :1]), seg.cumsum(dim=1)], dim=1)


def strand_curliness(rigid: torch.Tensor, window: float = CURL_WINDOW) -> torch.Tensor:
    """How curled each strand rests: the mean over its vertices of 1 - chord / arc, the chord from
    the vertex to the first vertex at least `window` of arc farther along the strand.

    0 for a straight strand (a wave or a droop gives a few hundredths), ~0.3 for the procedural
    long curls; vertices with less than half a window of strand left beyond them are not counted
    (a strand shorter than half a window reads 0).

    Args:
        rigid: (..., M, N, 3) strands at their rest lengths [m] (the first frame is read).
        window: the arc length compared [m], > 0.

    Returns:
        (M,) curliness in [0, 1), `rigid`'s dtype.
    """
    if not window > 0:
        raise ValueError(f"window: expected a positive arc length [m], got {window!r}")
    strands = rigid.reshape(-1, *rigid.shape[-3:])[0].double()
    _, s = _rest_arc_lengths(strands)
    ahead = torch.searchsorted(s.contiguous(), (s + window).contiguous()).clamp(max=s.shape[1] - 1)
    arc = s.gather(1, ahead) - s
    chord = (strands.gather(1, ahead[..., None].expand(-1, -1, 3)) - strands).norm(dim=-1)
    counted = arc > 0.5 * window
    straightness = torch.where(counted, chord / arc.clamp_min(1e-12), torch.ones_like(arc))
    curl = (1.0 - straightness).clamp_min(0.0).sum(dim=1) / counted.sum(dim=1).clamp_min(1)
    return curl.to(rigid.dtype)


def curl_weight(rigid: torch.Tensor) -> torch.Tensor:
    """(M,) how much of a curled strand's settings each strand takes (`InertialConfig.curl_bending`,
    `curl_gate`): its rest curliness mapped linearly from 0 at `CURL_ONSET` to 1 at `CURL_FULL`,
    float64.
    """
    curl = strand_curliness(rigid).double()
    return ((curl - CURL_ONSET) / (CURL_FULL - CURL_ONSET)).clamp(0.0, 1.0)


def strand_bending(rigid: torch.Tensor, config: InertialConfig) -> torch.Tensor:
    """(M,) each strand's bending stiffness: `config.bending`, scaled on curled strands by
    `config.curl_bending` (its docstring), float64.
    """
    return float(config.bending) * (1.0 - curl_weight(rigid) * (1.0 - float(config.curl_bending)))


def hanging_chain_tension(rigid: torch.Tensor, fps: float) -> torch.Tensor:
    """The chain's tension weight w of a strand hanging under its weight: (M, N-2), the segment
    above each free vertex (`hairwarp.ops.strand_preconditioner.hanging_tension`:
    w = h^2 g (L - s) / l^2).

    Args:
        rigid: (..., M, N, 3) the rigid placement (its segment lengths are the rest lengths) [m].
        fps: frames per second (h = 1 / fps).
    """
    from hairwarp.ops.strand_preconditioner import hanging_tension

    seg, _ = _rest_arc_lengths(rigid)
    g = math.hypot(*EnergyConfig().gravity)  # the energy's gravity (Eq. 11) [m/s^2]
    return hanging_tension(seg, 1.0 / fps, g).to(seg.dtype)[:, NUM_FIXED_VERTICES - 1:]


def chain_operator(gate_logit: torch.Tensor, tension: torch.Tensor, bending: float | torch.Tensor = 0.0) -> torch.Tensor:
    """(I + D + L_w + b A^T A)^-1 of every strand (module docstring), made in float64.

    Args:
        gate_logit: (M, n) the logit of G of the n free vertices: D = (1 - G) / G = exp(-logit).
        tension: (M, n) w >= 0 of the segment above each free vertex (the first one's ties it to
            the fixed vertex 1, whose offset is 0).
        bending: b >= 0, one for every strand or (M,) one each (`strand_bending`); A (n, n) maps
            the free vertices' offsets to the second differences d[c-1] - 2 d[c] + d[c+1] at
            c = 1 .. n (the two fixed vertices' offsets 0: a clamped root; `InertialConfig.bending`).

    Returns:
        (M, n, n) the symmetric positive definite operator's inverse (float64).
    """
    from hairwarp.ops.strand_preconditioner import chain_matrix

    matrix = chain_matrix(1.0 + torch.exp(-gate_logit.double()), tension)
    per_strand = isinstance(bending, torch.Tensor)
    if per_strand or bending:
        n = matrix.shape[-1]
        # Second differences centred on vertices 1 .. n of the strand (free vertex j is strand vertex j + 2).
        full = torch.zeros(n, n + 2, dtype=torch.float64, device=matrix.device)
        rows = torch.arange(n, device=matrix.device)
        full[rows, rows], full[rows, rows + 1], full[rows, rows + 2] = 1.0, -2.0, 1.0
        second = full[:, 2:]
        penalty = second.T @ second
        if per_strand:
            matrix = matrix + bending.to(matrix)[:, None, None] * penalty
        else:
            matrix = matrix + float(bending) * penalty
    return torch.cholesky_inverse(torch.linalg.cholesky(matrix))


def body_hold_weights(distance: torch.Tensor, config: InertialConfig) -> torch.Tensor:
    """The hold kappa at every free vertex whose equilibrium lies within `body_hold_distance` of the body, else 0.

    Args:
        distance: (..., M, N) the equilibrium's signed distance to the body [m] (negative inside).
        config: the step's `InertialConfig` (`body_hold`, `body_hold_distance`).

    Returns:
        (..., M, N - 2) weights of the free vertices, `distance`'s dtype.
    """
    near = distance[..., NUM_FIXED_VERTICES:] < config.body_hold_distance
    return near.to(distance.dtype) * float(config.body_hold)


def body_held_chain_relaxation(operator: torch.Tensor, offset: torch.Tensor, weight: torch.Tensor,
                               normal: torch.Tensor) -> torch.Tensor:
    """The chain's relaxed offsets with vertices held along a direction: per strand, the solution u of
    (C (x) I_3 + sum_i weight_i n_i n_i^T) u = offset, given C^-1 (module docstring, `body_hold`).

    Woodbury's identity with P = C^-1 and U the columns e_i (x) n_i: u = P d - P U s, where
    s = W^1/2 S^-1 W^1/2 U^T P d and S = I + W^1/2 (P o N N^T) W^1/2 (o the elementwise product,
    N N^T the normals' dot products): one n x n Cholesky solve per strand with a held vertex
    (float64) beside the 3n x 3n system, and none for the others (u = P d, the free chain).

    Args:
        operator: (M, n, n) C^-1 of every strand (`chain_operator`).
        offset: (B, M, n, 3) d, the free vertices' offsets [m].
        weight: (B, M, n) >= 0, the hold of each free vertex (0: free; `body_hold_weights`).
        normal: (B, M, n, 3) the unit direction each vertex is held along.

    Returns:
        (B, M, n, 3) u [m], `offset`'s dtype; differentiable w.r.t. offset and operator.
    """
    relaxed = operator @ offset
    held = (weight > 0).any(dim=-1)  # (B, M) strands with a held vertex
    if not bool(held.any()):
        return relaxed
    batch, strand = held.nonzero(as_tuple=True)
    p = operator[strand].double()  # (K, n, n)
    n_held = normal[batch, strand].double()  # (K, n, 3)
    root = weight[batch, strand].double().clamp_min(0.0).sqrt()  # (K, n)
    system = (root[:, :, None] * root[:, None, :]) * p * (n_held @ n_held.transpose(-1, -2))
    system = system + torch.eye(system.shape[-1], dtype=system.dtype, device=system.device)
    projected = root * (n_held * relaxed[batch, strand].double()).sum(dim=-1)  # W^1/2 U^T P d, (K, n)
    solved = torch.cholesky_solve(projected[..., None], torch.linalg.cholesky(system))[..., 0]
    correction = p @ ((root * solved)[..., None] * n_held)  # P U s, (K, n, 3)
    return relaxed.index_put((batch, strand), relaxed[batch, strand] - correction.to(relaxed.dtype))


class InertialStep(nn.Module):
    """The learned inertial step (module docstring): (equilibrium, rigid, x(t-1), x(t-2)) -> x(t).

    Args:
        config: `InertialConfig`.
    """

    kind = "inertial"

    def __init__(self, config: InertialConfig | None = None):
        super().__init__()
        config = InertialConfig() if config is None else config
        if not isinstance(config, InertialConfig):
            raise ValueError(f"config: expected an InertialConfig, got {type(config).__name__}")
        self.config = config
        # Training only: the projection's adjoint with each vertex's gain capped at this
        # (`follow_the_leader(max_gain=...)`); None, the exact gradient.
        self.projection_max_gain = None
        h = config.hidden_dim
        outputs = 3 if config.coupling == "chain" else 2  # G, beta (, the chain's tension w)
        self.net = nn.Sequential(nn.Linear(NUM_VERTEX_FEATURES, h), nn.SiLU(), nn.Linear(h, h), nn.SiLU(),
                                 nn.Linear(h, outputs))
        # The last layer starts at zero: every vertex starts at (gate_init, retention_init) and, on
        # a chain, every segment at tension_init.
        nn.init.zeros_(self.net[-1].weight)
        start = [math.log(config.gate_init / (1 - config.gate_init)),
                 math.log(config.retention_init / (1 - config.retention_init)),
                 math.log(config.tension_init)][:outputs]
        with torch.no_grad():
            self.net[-1].bias.copy_(torch.tensor(start))

    def coefficients(self, rigid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The step's coefficients, read from the rest arc lengths: (pull, beta).

        Args:
            rigid: (..., M, N, 3) the rigid placement (its segment lengths are the rest lengths) [m].

        Returns:
            pull: "vertex" coupling, G of every vertex (M, N, 1) in (0, 1); "chain", the operator
                (I + D + L_w)^-1 over the free vertices (M, N-2, N-2) (module docstring).
            beta: (M, N, 1) in (0, 1). Both 0 at the fixed vertices 0, 1.
        """
        dtype = next(self.parameters()).dtype
        features = vertex_features(rigid).to(dtype)
        raw = self.net(features)
        if self.config.curl_gate is not None:
            # Curled strands' G blended toward curl_gate in logit space (`InertialConfig.curl_gate`).
            weight = curl_weight(rigid).to(raw.dtype)[:, None, None]
            curled = math.log(self.config.curl_gate / (1.0 - self.config.curl_gate))
            raw = torch.cat([(1.0 - weight) * raw[..., :1] + weight * curled, raw[..., 1:]], dim=-1)
        out = torch.sigmoid(raw[..., :2])
        fixed = torch.ones_like(out[..., :1])
        fixed[:, :NUM_FIXED_VERTICES] = 0.0
        out = out * fixed
        gate, retention = out[..., :1].to(rigid.dtype), out[..., 1:].to(rigid.dtype)
        if self.config.coupling != "chain":
            return gate, retention
        # w: the hanging chain's tension times a learned factor (tension_init at the start).
        tension = hanging_chain_tension(rigid, self.config.fps) * torch.exp(raw[:, NUM_FIXED_VERTICES:, 2])
        bending = self.config.bending
        if bending and self.config.curl_bending != 1.0:
            bending = strand_bending(rigid, self.config)
        operator = chain_operator(raw[:, NUM_FIXED_VERTICES:, 0], tension, bending)
        return operator.to(rigid.dtype), retention

    def step(self, equilibrium: torch.Tensor, rigid: torch.Tensor, prev: torch.Tensor, prev2: torch.Tensor,
             head_velocity: torch.Tensor, coefficients: tuple[torch.Tensor, torch.Tensor] | None = None,
             hold: tuple[torch.Tensor, torch.Tensor] | None = None, return_target: bool = False):
        """One frame: x(t) from the frame's equilibrium and rigid placement and the last two states.

        Args:
            equilibrium: (B, M, N, 3) E(t) [m].
            rigid: (B, M, N, 3) P_rigid(t) [m].
            prev, prev2: (B, M, N, 3) x(t-1), x(t-2) [m].
            head_velocity: (B, M, N, 3) u(t) [m per frame]: P_rigid(t-1) - P_rigid(t-2) for
                `damping="relative"`, zeros for "absolute".
            coefficients: `coefficients(rigid)`, to reuse over a sequence (the chain's inverse is
                made there).
            hold: (distance (B, M, N) [m], normal (B, M, N, 3)) of the frame's equilibrium to the
                body (`hair_body_signed_distance_and_normal`), read where `InertialConfig.body_hold`
                > 0; None: no hold.
            return_target: also return the target p(t) before the projection.

        Returns:
            (B, M, N, 3) x(t) [m], differentiable w.r.t. the inputs and the MLP; with
            `return_target`, (x(t), p(t)).
        """
        pull, retention = self.coefficients(rigid) if coefficients is None else coefficients
        predicted = prev + head_velocity + retention * (prev - prev2 - head_velocity)
        if self.config.coupling != "chain":
            target = equilibrium + pull * (predicted - equilibrium)
        else:
            # The chain: every free vertex's offset from the equilibrium relaxed along its strand.
            offset = (predicted - equilibrium)[:, :, NUM_FIXED_VERTICES:]
            if hold is not None and self.config.body_hold:
                distance, normal = hold
                relaxed = body_held_chain_relaxation(pull, offset, body_hold_weights(distance, self.config),
                                                     normal[:, :, NUM_FIXED_VERTICES:])
            else:
                relaxed = pull @ offset
            free = equilibrium[:, :, NUM_FIXED_VERTICES:] + relaxed
            target = torch.cat([equilibrium[:, :, :NUM_FIXED_VERTICES], free], dim=2)
        projected = follow_the_leader(rigid, target, check=False, max_gain=self.projection_max_gain)
        return (projected, target) if return_target else projected

    def rollout(self, equilibrium: torch.Tensor, rigid: torch.Tensor, initial: tuple | None = None,
                project=None, carry: RolloutCarry | None = None,
                hold: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """A whole sequence, frame by frame, each step on the step's own previous states.

        Args:
            equilibrium: (T, M, N, 3) E(t) of every frame [m].
            rigid: (T, M, N, 3) P_rigid(t) [m], same shape.
            initial: (x(-1), x(-2)), each (M, N, 3): the states before the first frame; None: the
                first frame's equilibrium, at rest.
            project: optional callable (t, x (M, N, 3)) -> (M, N, 3) applied to each frame's
                result before it becomes the state the next frames read (the body pass of
                `InertialConfig.keep_out_state`); None: the step's own result.
            carry: a `RolloutCarry` for a sequence rolled out a piece at a time: empty, this call
                is the sequence's first piece; filled by the call before, this call goes on
                from it (its states, rate-limited equilibrium, head motion and coefficients,
                `initial` ignored) and leaves it for the next. The pieces give the whole
                sequence's rollout bit for bit.
            hold: (distance (T, M, N) [m], normal (T, M, N, 3)): every frame's equilibrium's
                signed distance to the body and the body's outward direction there
                (`hair_body_signed_distance_and_normal`, capped at `body_hold_distance` or not),
                required where `InertialConfig.body_hold` > 0 and unused otherwise.

        Returns:
            (T, M, N, 3) positions [m].

        Raises:
            ValueError: on shapes that differ, an empty sequence, NaN or Inf, or a step that holds
                the chain along the body without `hold`.
        """
        check_tensor("rigid", rigid, shape=[None, None, None, 3], allow_empty=False)
        check_tensor("equilibrium", equilibrium, shape=tuple(rigid.shape), dtypes=(rigid.dtype,), device=rigid.device)
        if rigid.shape[2] <= NUM_FIXED_VERTICES:
            raise ValueError(f"rigid: expected more than {NUM_FIXED_VERTICES} vertices per strand, got {rigid.shape[2]}")
        if self.config.body_hold:
            if hold is None:
                raise ValueError("hold: this step holds the chain along the body (InertialConfig.body_hold > 0); "
                                 "expected every frame's equilibrium distance (T, M, N) and normal (T, M, N, 3) to "
                                 "the body (hairwarp.ops.hair_body_signed_distance_and_normal)")
            check_tensor("hold[0]", hold[0], shape=tuple(rigid.shape[:3]), device=rigid.device)
            check_tensor("hold[1]", hold[1], shape=tuple(rigid.shape), device=rigid.device)
        else:
            hold = None
        carried = carry is not None and carry.prev is not None
        if carried:
            if tuple(carry.prev.shape) != tuple(rigid.shape[1:]):
                raise ValueError(f"rigid: expected frames of shape {tuple(carry.prev.shape)} like the carried "
                                 f"sequence's, got {tuple(rigid.shape[1:])}")
            prev, prev2, offset, coefficients = carry.prev, carry.prev2, carry.offset, carry.coefficients
            placed = torch.cat([carry.rigid_before, rigid])  # the two frames before this piece, then it
        else:
            if initial is None:
                prev = prev2 = equilibrium[0]
            else:
                prev, prev2 = initial
                for name, value in (("initial[0]", prev), ("initial[1]", prev2)):
                    check_tensor(name, value, shape=tuple(rigid.shape[1:]), dtypes=(rigid.dtype,), device=rigid.device)
            coefficients = self.coefficients(rigid)
            offset = equilibrium[0] - rigid[0]  # the equilibrium's offset from the rigid placement, rate-limited
            # The head at rest before the first frame (the first frame twice before it); then how
            # the rigid placement moved a frame ago.
            placed = torch.cat([rigid[:1], rigid[:1], rigid])
        limit = None if self.config.equilibrium_speed is None else self.config.equilibrium_speed / self.config.fps
        head_velocity = placed[1:-1] - placed[:-2]
        if self.config.damping == "absolute":
            head_velocity = torch.zeros_like(rigid)
        out = []
        for t in range(rigid.shape[0]):
            target = equilibrium[t]
            if limit is not None:
                offset = offset + limited_change(equilibrium[t] - rigid[t] - offset, limit)
                target = rigid[t] + offset
            held = None if hold is None else (hold[0][t:t + 1], hold[1][t:t + 1])
            x, wanted = self.step(target[None], rigid[t:t + 1], prev[None], prev2[None], head_velocity[t:t + 1],
                                  coefficients, hold=held, return_target=True)
            x, wanted = x[0], wanted[0]
            before = prev
            if self.config.projection_damping:
                # Dynamic follow-the-leader: each vertex's velocity gives back the projection's
                # correction of the vertex it leads (module docstring); the tip leads none.
                led = (x - wanted)[:, 1:]
                before = prev + self.config.projection_damping * torch.cat([led, torch.zeros_like(led[:, :1])], dim=1)
            if project is not None:
                pushed = project(t, x)
                if self.config.keep_out_velocity != "pushed":
                    # The next step reads its velocity as prev - prev2: prev2 is set so that it is
                    # the step's own (less what ran into the body), not the push added to it.
                    before = pushed - pushed_velocity(x - before, pushed - x, self.config.keep_out_velocity)
                x = pushed
            out.append(x)
            prev2, prev = before, x
        if carry is not None:
            carry.prev, carry.prev2, carry.offset, carry.coefficients = prev, prev2, offset, coefficients
            carry.rigid_before = placed[-2:]
        return torch.stack(out)


@dataclass
class RolloutCarry:
    """What `InertialStep.rollout` carries from one piece of a sequence to the next (its
    `carry` argument): the last two states x(t-1), x(t-2), the rate-limited equilibrium's
    offset, the last two rigid placements (the head's motion) and the step's coefficients
    (made from the sequence's first frame). Empty (all None) before the first piece.
    """

    prev: torch.Tensor | None = None
    prev2: torch.Tensor | None = None
    offset: torch.Tensor | None = None
    rigid_before: torch.Tensor | None = None
    coefficients: tuple | None = None

    def copy(self) -> RolloutCarry:
        """A copy that a rollout can advance without advancing this one (the tensors are not
        changed in place, so they are shared).
        """
        return RolloutCarry(self.prev, self.prev2, self.offset, self.rigid_before, self.coefficients)


def pushed_velocity(velocity: torch.Tensor, push: torch.Tensor, mode: str) -> torch.Tensor:
    """The velocity a pushed frame hands on (`InertialConfig.keep_out_velocity`).

    Args:
        velocity: (..., 3) the step's own velocity x(t) - x(t-1) before the push [m/frame].
        push: (..., 3) the body pass's move of each vertex [m].
        mode: "raw" (the velocity as it is) or "tangential" (less its component against the push,
            where the vertex moved into the body: n = push / |push|, v - min(v . n, 0) n).

    Returns:
        (..., 3) the velocity [m/frame].
    """
    if mode == "raw":
        return velocity
    length = push.norm(dim=-1, keepdim=True)
    normal = torch.where(length > 0, push / length.clamp_min(1e-30), torch.zeros_like(push))
    into = (velocity * normal).sum(dim=-1, keepdim=True).clamp(max=0.0)
    return velocity - into * normal


def limited_change(change: torch.Tensor, limit: float) -> torch.Tensor:
    """`change` scaled per strand so that its mean length over the moving vertices is at most `limit`.

    Args:
        change: (M, N, 3) a per-vertex change [m] (0 at the fixed vertices).
        limit: the largest mean change a strand may take [m], >= 0.

    Returns:
        (M, N, 3): `change` where a strand's mean is within `limit`, else that strand's change
        scaled down to it (direction and shape kept).
    """
    size = change[:, NUM_FIXED_VERTICES:].norm(dim=-1).mean(dim=-1)
    scale = (limit / size.clamp_min(1e-12)).clamp(max=1.0)
    return change * scale[:, None, None]


def fit_constants_by_length(step: InertialStep, anchors, *, iterations: int = 3000, seed: int = 0) -> float:
    """Fit `step`'s coefficient MLP so that its G, beta and (chain) tension factor depend on the
    strand length L alone, interpolated between anchors.

    The logits of G and beta and the log of the tension factor are interpolated linearly in L
    between the anchors and held constant beyond the first and the last; the MLP (which reads
    s / L, s and L) is fitted to them by least squares over L in [0.02, 1.2] m and s / L in
    [0, 1]. Used for constants chosen per hairstyle on training clips
    (`tools/inertial_sweep.py`: short hair wants less damping and less tension than long hair).

    Args:
        step: an `InertialStep` (its MLP is overwritten in place).
        anchors: [(L [m], G, beta, tension factor), ...], at least one, G and beta in (0, 1),
            the tension > 0 (ignored by a "vertex" step).
        iterations: Adam steps of the fit.
        seed: the fit's sampling.

    Returns:
        The largest absolute error of the fitted logits at the anchors (a check of the fit).

    Raises:
        ValueError: no anchors, or values out of range.
    """
    rows = sorted((float(a[0]), float(a[1]), float(a[2]), float(a[3])) for a in anchors)
    if not rows:
        raise ValueError("anchors: expected at least one (L, G, beta, tension)")
    for length, gate, retention, tension in rows:
        if not (length > 0 and 0 < gate < 1 and 0 < retention < 1 and tension > 0):
            raise ValueError(f"anchors: expected L > 0, G and beta in (0, 1), tension > 0, got "
                             f"{(length, gate, retention, tension)}")
    knots = torch.tensor([r[0] for r in rows], dtype=torch.float64)
    targets = torch.tensor([[math.log(g / (1 - g)), math.log(b / (1 - b)), math.log(t)] for _, g, b, t in rows],
                           dtype=torch.float64)
    outputs = step.net[-1].out_features

    def target_of(length: torch.Tensor) -> torch.Tensor:
        if len(knots) == 1:
            return targets[:, :outputs].expand(len(length), -1)
        clamped = length.clamp(float(knots[0]), float(knots[-1]))
        hi = torch.searchsorted(knots, clamped).clamp(1, len(knots) - 1)
        lo = hi - 1
        w = ((clamped - knots[lo]) / (knots[hi] - knots[lo]).clamp_min(1e-12)).clamp(0, 1)[:, None]
        return ((1 - w) * targets[lo] + w * targets[hi])[:, :outputs]

    generator = torch.Generator().manual_seed(seed)
    parameters = list(step.net.parameters())
    dtype = parameters[0].dtype
    optimizer = torch.optim.Adam(parameters, lr=3e-3)
    for _ in range(iterations):
        length = 0.02 + 1.18 * torch.rand(512, generator=generator, dtype=torch.float64)
        length = torch.cat([length, knots])
        fraction = torch.rand(len(length), generator=generator, dtype=torch.float64)
        features = torch.stack([fraction, fraction * length, length], dim=-1).to(dtype)
        loss = (step.net(features) - target_of(length).to(dtype)).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        check = torch.stack([torch.full_like(knots, 0.5), 0.5 * knots, knots], dim=-1).to(dtype)
        return float((step.net(check).double() - targets[:, :outputs]).abs().max())


__all__ = ["COUPLINGS", "CURL_FULL", "CURL_ONSET", "CURL_WINDOW", "DAMPINGS", "InertialConfig", "InertialStep",
           "NUM_VERTEX_FEATURES", "RolloutCarry", "body_held_chain_relaxation", "body_hold_weights", "chain_operator",
           "curl_weight", "fit_constants_by_length", "hanging_chain_tension", "limited_change", "strand_bending",
           "strand_curliness", "vertex_features"]
