"""numpy float64 reference of the hair-hair contact energy (HairFormer Eq. 12, d = distance
between hair segments), and the hair builders the tests and the benchmark share.

Reference: every pair of segments of different strands of one batch item, both with index
>= skip_root_segments, measured with the brute-force segment distance of
`references.distances`; energy = weight * sum of B(d) over pairs with d < xi + dhat.
"""

from __future__ import annotations

import numpy as np

from references import barrier as barrier_ref
from references import distances as distance_ref


def segment_pairs(x, xi, dhat, skip_root_segments=2):
    """(P, 2) flat segment ids (i < j, sorted) of pairs closer than xi + dhat, and their distances.

    x: (B, M, N, 3) float64; segment (b, m, i) has flat id (b * M + m) * (N - 1) + i.
    """
    x = np.asarray(x, dtype=np.float64)
    b, m, n, _ = x.shape
    ids, p0, p1, q0, q1 = [], [], [], [], []
    for item in range(b):
        for s1 in range(m):
            for s2 in range(s1 + 1, m):
                i, j = np.meshgrid(np.arange(skip_root_segments, n - 1), np.arange(skip_root_segments, n - 1))
                i, j = i.ravel(), j.ravel()
                ids.append(np.stack([(item * m + s1) * (n - 1) + i, (item * m + s2) * (n - 1) + j], axis=1))
                p0.append(x[item, s1, i])
                p1.append(x[item, s1, i + 1])
                q0.append(x[item, s2, j])
                q1.append(x[item, s2, j + 1])
    if not ids:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    ids = np.concatenate(ids)
    d, _, _ = distance_ref.edge_edge_distance(*(np.concatenate(v) for v in (p0, p1, q0, q1)))
    close = d < xi + dhat
    ids, d = ids[close], d[close]
    order = np.lexsort((ids[:, 1], ids[:, 0]))
    return ids[order], d[order]


def energy(x, xi, dhat, bp, weight=1.0, variant="quadratic", skip_root_segments=2):
    """(B,) energy = weight * sum over close pairs of B(d), and the pairs (P, 2)."""
    x = np.asarray(x, dtype=np.float64)
    b, m, n, _ = x.shape
    pairs, d = segment_pairs(x, xi, dhat, skip_root_segments)
    per_pair = weight * barrier_ref.barrier(d, xi, dhat, bp, variant)
    out = np.zeros(b)
    np.add.at(out, pairs[:, 0] // ((n - 1) * m), per_pair)
    return out, pairs


def crossing_strands(gap, num_vertices=12, length=0.06, angle=np.pi / 2):
    """Two straight strands hanging in parallel planes, crossing at `gap` [m] apart (M=2, N, 3).

    Strand 0 runs along x at z = 0, strand 1 along a direction at `angle` to it in the plane
    z = gap; they cross above the origin, where the closest segments are interior
    (both mid-strand), so the distance there is exactly `gap`.
    """
    t = np.linspace(-0.5, 0.5, num_vertices) * length
    # Offset by a quarter segment so the crossing is inside a segment on both strands.
    t = t + 0.25 * length / (num_vertices - 1)
    a = np.stack([t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    direction = np.array([np.cos(angle), np.sin(angle), 0.0])
    b = t[:, None] * direction + np.array([0.0, 0.0, gap])
    return np.stack([a, b]) + np.array([0.1, 1.6, 0.05])


def random_hair(rng, batch, strands, vertices, extent=0.02, segment=4e-3):
    """Small random-walk strands in a box of `extent` [m]: many contacts among few segments."""
    roots = rng.uniform(0.0, extent, size=(batch, strands, 1, 3))
    steps = rng.normal(size=(batch, strands, vertices - 1, 3))
    steps *= segment / np.linalg.norm(steps, axis=-1, keepdims=True)
    walk = np.concatenate([np.zeros((batch, strands, 1, 3)), np.cumsum(steps, axis=2)], axis=2)
    return roots + walk


def hanging_hair(side=32, vertices=100, length=0.3, spacing=5e-3, radius=0.1, seed=0):
    """A plausible hairstyle: side^2 strands from a sphere cap falling over the head (M, N, 3).

    Roots: a side x side grid of `spacing` [m] arc length on a sphere of `radius` [m] around
    (0, 1.6, 0), centred on the crown. Each strand leaves along the scalp normal, lifts to a
    layer 1.5 mm + 1.5 mm per 10 mm of arc below the crown (strands from the crown lie on
    top), follows its meridian (azimuth jittered so no two strands are coplanar) down the
    sphere to the equator, then falls straight, with a small random wave; segments are
    length / (vertices - 1).
    """
    rng = np.random.default_rng(seed)
    g = (np.arange(side) - (side - 1) / 2) * spacing
    gx, gz = np.meshgrid(g, g, indexing="ij")
    rho = np.hypot(gx, gz).ravel()
    # Jitter the azimuth: grid roots on one ray from the crown would otherwise give coplanar
    # strands that intersect exactly (d = 0), which real hair does not do.
    jitter = rng.uniform(-0.25, 0.25, size=rho.size) * spacing / np.maximum(rho, spacing)
    phi = np.arctan2(gz, gx).ravel() + jitter
    theta0 = rho / radius
    theta_max = theta0.max()
    layer = radius + 1.5e-3 + 0.15 * (theta_max - theta0) * radius  # [m]: crown strands outermost
    # A dense path, resampled below at equal arc length so every segment is length / (N - 1).
    fine = 8 * vertices
    ell = np.linspace(0.0, 1.5 * length, fine)[None, :]
    u = np.minimum(ell / 0.01, 1.0)
    r = radius + (layer[:, None] - radius) * u * u * (3.0 - 2.0 * u)  # smoothstep lift off the scalp
    theta = theta0[:, None] + ell / layer[:, None]
    ell_eq = (np.pi / 2 - theta0[:, None]) * layer[:, None]  # path length at the equator
    below = theta > np.pi / 2
    theta = np.minimum(theta, np.pi / 2)
    phase = rng.uniform(0, 2 * np.pi, size=(rho.size, 1))
    wave = 1.5e-3 * np.sin(ell / 0.02 + phase) * np.minimum(ell / 0.05, 1.0)
    horizontal = r * np.sin(theta) + wave
    y = r * np.cos(theta) - np.where(below, ell - ell_eq, 0.0)
    cos_phi, sin_phi = np.cos(phi)[:, None], np.sin(phi)[:, None]
    path = np.stack([horizontal * cos_phi, y + 1.6, horizontal * sin_phi], axis=-1)
    arc = np.concatenate(
        [np.zeros((rho.size, 1)), np.cumsum(np.linalg.norm(np.diff(path, axis=1), axis=-1), axis=1)], axis=1
    )
    target = np.linspace(0.0, length, vertices)
    out = np.empty((rho.size, vertices, 3))
    for k in range(rho.size):
        for c in range(3):
            out[k, :, c] = np.interp(target, arc[k], path[k, :, c])
    return out
