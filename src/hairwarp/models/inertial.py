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
removes that drag; trained the same way it swung less and later than the physics on every
held-out motion (docs/network_diagnosis.md, "The hair's own state"), so the drag stays the default.
G and beta are read from each vertex's rest arc length (the distance from the root s, the strand's
length L, s / L) by a small MLP, so that one step serves any hairstyle, strand count and vertex count.

Trained on physics trajectories (`hairwarp.training.inertial`): rollouts from the first frame, on
the step's own predictions, back-propagated through the whole clip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from hairwarp._validate import check_tensor
from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.models.config import _DictConfig
from hairwarp.ops.strand_projection import follow_the_leader

# Features of a vertex read by the coefficient MLP: s / L, s [m], L [m].
NUM_VERTEX_FEATURES = 3
# What beta damps (`InertialConfig.damping`).
DAMPINGS = ("relative", "absolute")


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
    """

    hidden_dim: int = 32
    gate_init: float = 0.98
    retention_init: float = 0.9
    fps: float = 60.0
    damping: str = "absolute"

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


def vertex_features(rigid: torch.Tensor) -> torch.Tensor:
    """What the coefficient MLP reads per vertex: (s / L, s, L) from the rest segment lengths.

    Args:
        rigid: (..., M, N, 3) strands at their rest lengths [m] (any frame of the rigid placement).

    Returns:
        (M, N, 3) features (of the first frame when `rigid` has leading dimensions).
    """
    strands = rigid.reshape(-1, *rigid.shape[-3:])[0]
    seg = (strands[:, 1:] - strands[:, :-1]).norm(dim=-1)
    s = torch.cat([torch.zeros_like(seg[:, :1]), seg.cumsum(dim=1)], dim=1)  # (M, N)
    length = s[:, -1:].clamp_min(1e-9).expand_as(s)
    return torch.stack([s / length, s, length], dim=-1)


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
        h = config.hidden_dim
        self.net = nn.Sequential(nn.Linear(NUM_VERTEX_FEATURES, h), nn.SiLU(), nn.Linear(h, h), nn.SiLU(),
                                 nn.Linear(h, 2))
        # The last layer starts at zero: every vertex starts at (gate_init, retention_init).
        nn.init.zeros_(self.net[-1].weight)
        with torch.no_grad():
            self.net[-1].bias.copy_(torch.tensor([math.log(config.gate_init / (1 - config.gate_init)),
                                                  math.log(config.retention_init / (1 - config.retention_init))]))

    def coefficients(self, rigid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(G, beta) of every vertex, each (M, N, 1), in (0, 1); 0 for the fixed vertices 0, 1.

        Args:
            rigid: (..., M, N, 3) the rigid placement (its segment lengths are the rest lengths) [m].
        """
        dtype = next(self.parameters()).dtype
        features = vertex_features(rigid).to(dtype)
        out = torch.sigmoid(self.net(features))
        fixed = torch.ones_like(out[..., :1])
        fixed[:, :NUM_FIXED_VERTICES] = 0.0
        out = out * fixed
        return out[..., :1].to(rigid.dtype), out[..., 1:].to(rigid.dtype)

    def step(self, equilibrium: torch.Tensor, rigid: torch.Tensor, prev: torch.Tensor, prev2: torch.Tensor,
             head_velocity: torch.Tensor, coefficients: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """One frame: x(t) from the frame's equilibrium and rigid placement and the last two states.

        Args:
            equilibrium: (B, M, N, 3) E(t) [m].
            rigid: (B, M, N, 3) P_rigid(t) [m].
            prev, prev2: (B, M, N, 3) x(t-1), x(t-2) [m].
            head_velocity: (B, M, N, 3) u(t) [m per frame]: P_rigid(t-1) - P_rigid(t-2) for
                `damping="relative"`, zeros for "absolute".
            coefficients: `coefficients(rigid)`, to reuse over a sequence.

        Returns:
            (B, M, N, 3) x(t) [m], differentiable w.r.t. the inputs and the MLP.
        """
        gate, retention = self.coefficients(rigid) if coefficients is None else coefficients
        predicted = prev + head_velocity + retention * (prev - prev2 - head_velocity)
        target = equilibrium + gate * (predicted - equilibrium)
        return follow_the_leader(rigid, target, check=False)

    def rollout(self, equilibrium: torch.Tensor, rigid: torch.Tensor, initial: tuple | None = None) -> torch.Tensor:
        """A whole sequence, frame by frame, each step on the step's own previous states.

        Args:
            equilibrium: (T, M, N, 3) E(t) of every frame [m].
            rigid: (T, M, N, 3) P_rigid(t) [m], same shape.
            initial: (x(-1), x(-2)), each (M, N, 3): the states before the first frame; None: the
                first frame's equilibrium, at rest.

        Returns:
            (T, M, N, 3) positions [m].

        Raises:
            ValueError: on shapes that differ, an empty sequence, NaN or Inf.
        """
        check_tensor("rigid", rigid, shape=[None, None, None, 3], allow_empty=False)
        check_tensor("equilibrium", equilibrium, shape=tuple(rigid.shape), dtypes=(rigid.dtype,), device=rigid.device)
        if rigid.shape[2] <= NUM_FIXED_VERTICES:
            raise ValueError(f"rigid: expected more than {NUM_FIXED_VERTICES} vertices per strand, got {rigid.shape[2]}")
        if initial is None:
            prev = prev2 = equilibrium[0]
        else:
            prev, prev2 = initial
            for name, value in (("initial[0]", prev), ("initial[1]", prev2)):
                check_tensor(name, value, shape=tuple(rigid.shape[1:]), dtypes=(rigid.dtype,), device=rigid.device)
        coefficients = self.coefficients(rigid)
        # The head at rest before the first frame; then how the rigid placement moved a frame ago.
        head_velocity = torch.cat([torch.zeros_like(rigid[:2]), rigid[1:-1] - rigid[:-2]])
        if self.config.damping == "absolute":
            head_velocity = torch.zeros_like(rigid)
        out = []
        for t in range(rigid.shape[0]):
            x = self.step(equilibrium[t:t + 1], rigid[t:t + 1], prev[None], prev2[None], head_velocity[t:t + 1],
                          coefficients)[0]
            out.append(x)
            prev2, prev = prev, x
        return torch.stack(out)


__all__ = ["DAMPINGS", "InertialConfig", "InertialStep", "NUM_VERTEX_FEATURES", "vertex_features"]
