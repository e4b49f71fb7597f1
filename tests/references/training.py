"""numpy float64 references for the training loops (HairFormer Sections 3.4.5, 4.2.1).

Written from the paper, independent of the library's code:
- the contact join fraction b_p, "0.9 ... gradually decreased to 0.01 throughout training"
  (Section 4.2.1), interpolated linearly or geometrically over the steps;
- the gradient of the inertia loss (Eq. 16) of a rollout with respect to each frame's positions
  when the previous states are held constant (stop-gradient, Section 3.4.5): frame t receives
  only its own term, lambda m / (M N_mov dt^2) (p(t) - 2 p(t-1) + p(t-2)), on moving vertices.
"""

from __future__ import annotations

import math

import numpy as np


def barrier_join_fraction(step: int, total_steps: int, start: float = 0.9, end: float = 0.01,
                          kind: str = "linear") -> float:
    """b_p at 0-based `step` of `total_steps`: `start` at the first step, `end` at the last."""
    t = 1.0 if total_steps == 1 else min(step / (total_steps - 1), 1.0)
    if kind == "linear":
        return (1.0 - t) * start + t * end
    return start * (end / start) ** t


def inertia_energy(x, prev, prev2, mass, time_step, weight):
    """Eq. 16 per frame: lambda / (M N_mov) sum_s sum_{v >= 2} m / (2 dt^2) |x - (2 prev - prev2)|^2.

    x, prev, prev2: (F, M, N, 3). Returns (F,).
    """
    f, m, n, _ = x.shape
    out = np.zeros(f)
    for k in range(f):
        total = 0.0
        for s in range(m):
            for v in range(2, n):
                d = x[k, s, v] - (2.0 * prev[k, s, v] - prev2[k, s, v])
                total += mass / (2.0 * time_step**2) * float(d @ d)
        out[k] = weight / (m * (n - 2)) * total
    return out


def rollout_inertia_gradient(warmup, x, mass, time_step, weight):
    """d/dx of the summed Eq. 16 over a rollout with stop-gradient previous states.

    Args:
        warmup: (2, M, N, 3) the two states before the rollout.
        x: (R, M, N, 3) the rollout states.

    Returns:
        (R, M, N, 3): frame t's gradient is its own term's only, zero on vertices 0 and 1.
    """
    history = np.concatenate([warmup, x], axis=0)
    r, m, n, _ = x.shape
    grad = np.zeros_like(x)
    scale = weight * mass / (m * (n - 2) * time_step**2)
    for t in range(r):
        for s in range(m):
            for v in range(2, n):
                grad[t, s, v] = scale * (history[t + 2, s, v] - 2.0 * history[t + 1, s, v] + history[t, s, v])
    return grad


def head_rotation_fraction(rotation, radii) -> float:
    """The ellipsoid scale of a head rotation vector: |r / radii| (1 on the full ellipsoid)."""
    return math.sqrt(sum((float(a) / float(b)) ** 2 for a, b in zip(rotation, radii)))
