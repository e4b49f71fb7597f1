"""numpy float64 references of the primitive distances (segment-segment, point-triangle).

Brute force, independent of the kernel's candidate enumeration: the distance is the minimum of
a jointly convex function of the parameters. Fixing the first parameter, the second has an
exact answer (a clamped projection onto a segment), and the partial minimum f(s) is a convex
function of the first parameter alone. So: f on a dense 1-D grid, then a ternary search on the
bracket around the grid minimum (for a convex f the minimiser lies within one grid step of the
best grid point), vectorised over K queries.
"""

from __future__ import annotations

import numpy as np

GRID = 1025
TERNARY_STEPS = 90  # (2/3)^90 ~ 1e-16 of the bracket width


def point_segment(points, a, b):
    """Distance from points (..., 3) to segments a-b (..., 3) and the clamped parameter."""
    e = b - a
    ee = np.sum(e * e, axis=-1)
    t = np.where(ee > 0, np.sum((points - a) * e, axis=-1) / np.where(ee > 0, ee, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    diff = points - (a + t[..., None] * e)
    return np.sqrt(np.sum(diff * diff, axis=-1)), t


def _minimise_convex_1d(f, k):
    """argmin over [0, 1] of K convex functions f(x (K, G)) -> (K, G), by grid + ternary search."""
    grid = np.broadcast_to(np.linspace(0.0, 1.0, GRID), (k, GRID))
    values = f(grid)
    i = np.argmin(values, axis=1)
    step = 1.0 / (GRID - 1)
    lo = np.clip(grid[np.arange(k), i] - step, 0.0, 1.0)
    hi = np.clip(grid[np.arange(k), i] + step, 0.0, 1.0)
    for _ in range(TERNARY_STEPS):
        m1 = lo + (hi - lo) / 3.0
        m2 = hi - (hi - lo) / 3.0
        f12 = f(np.stack([m1, m2], axis=1))
        left = f12[:, 0] <= f12[:, 1]
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
    x = 0.5 * (lo + hi)
    # Keep the better of the refined point and the best grid point (exact ties at a flat
    # minimum, e.g. parallel segments).
    fx = f(x[:, None])[:, 0]
    fg = values[np.arange(k), i]
    better = fg < fx
    return np.where(better, grid[np.arange(k), i], x), np.where(better, fg, fx)


def edge_edge_distance(p0, p1, q0, q1):
    """Segment-segment distance (K,) and closest parameters s, t (K,) for (K, 3) float64 inputs."""
    p0, p1, q0, q1 = (np.asarray(v, dtype=np.float64) for v in (p0, p1, q0, q1))
    k = p0.shape[0]

    def f(s):
        points = p0[:, None] + s[..., None] * (p1 - p0)[:, None]
        return point_segment(points, q0[:, None], q1[:, None])[0]

    s, d = _minimise_convex_1d(f, k)
    points = p0 + s[:, None] * (p1 - p0)
    _, t = point_segment(points, q0, q1)
    return d, s, t


def point_triangle_distance(p, a, b, c):
    """Point-triangle distance (K,) and barycentrics (K, 3) for (K, 3) float64 inputs."""
    p, a, b, c = (np.asarray(v, dtype=np.float64) for v in (p, a, b, c))
    k = p.shape[0]

    # Closest point a + v (b - a) + w (c - a) with v, w >= 0, v + w <= 1. For fixed v the
    # feasible points form the segment from a + v (b - a) to a + v (b - a) + (1 - v)(c - a).
    def segment_at(v):
        start = a[:, None] + v[..., None] * (b - a)[:, None]
        end = start + (1.0 - v)[..., None] * (c - a)[:, None]
        return start, end

    def f(v):
        start, end = segment_at(v)
        return point_segment(p[:, None], start, end)[0]

    v, d = _minimise_convex_1d(f, k)
    start, end = segment_at(v[:, None])
    _, t = point_segment(p[:, None], start, end)
    w = t[:, 0] * (1.0 - v)
    return d, np.stack([1.0 - v - w, v, w], axis=1)
