"""numpy float64 references of the strand energies, written term by term from HairFormer
Section 3.4 (Eq. 7-11, 15, 16) with plain loops. Positions `x` are `(B, M, N, 3)`; every
function returns a `(B,)` array. Auxiliary inputs are given per batch item (the tests broadcast
shared ones before calling)."""

import numpy as np


def stretch(x, rest, weight):
    """Eq. 7: k_s / (M (N-1)) sum_s sum_{i=0}^{N-2} (|p_{i+1} - p_i| - l0_{s,i})^2; rest (B, M, N-1)."""
    b_count, m, n, _ = x.shape
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for i in range(n - 1):
                total += (np.linalg.norm(x[b, s, i + 1] - x[b, s, i]) - rest[b, s, i]) ** 2
        out[b] = weight / (m * (n - 1)) * total
    return out


def bending(x, weight, eps):
    """Eq. 8: k_b sum_s sum_{i=0}^{N-3} alpha_{s,i} with the clamp and C_valid."""
    b_count, m, n, _ = x.shape
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for i in range(n - 2):
                e0 = x[b, s, i + 1] - x[b, s, i]
                e1 = x[b, s, i + 2] - x[b, s, i + 1]
                l0, l1 = np.linalg.norm(e0), np.linalg.norm(e1)
                if l0 > eps and l1 > eps:
                    theta = np.dot(e0 / (l0 + eps), e1 / (l1 + eps))
                    total += np.arccos(np.clip(theta, -1.0 + eps, 1.0 - eps))
        out[b] = weight * total
    return out


def auxiliary(x, rigid, weight):
    """Eq. 9: lambda_aux / (3 M N) sum_s sum_{v=0}^{N-1} |p_v - p_v^rigid|^2; rigid (B, M, N, 3)."""
    b_count, m, n, _ = x.shape
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for v in range(n):
                d = x[b, s, v] - rigid[b, s, v]
                total += np.dot(d, d)
        out[b] = weight / (3 * m * n) * total
    return out


def smoothness(x, weight):
    """Eq. 10: lambda_smooth / (M (N-2)) sum_s sum_{v=1}^{N-2} |p_{v+1} - 2 p_v + p_{v-1}|^2."""
    b_count, m, n, _ = x.shape
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for v in range(1, n - 1):
                r = x[b, s, v + 1] - 2.0 * x[b, s, v] + x[b, s, v - 1]
                total += np.dot(r, r)
        out[b] = weight / (m * (n - 2)) * total
    return out


def gravity(x, mass, g, weight):
    """Eq. 11: -weight sum_s sum_{v'} (m_{s,v'} g) . p_{s,v'} over the moving vertices v >= 2.

    mass: (M, N) array (entries of vertices 0 and 1 unused).
    """
    b_count, m, n, _ = x.shape
    g = np.asarray(g, dtype=np.float64)
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for v in range(2, n):
                total += np.dot(mass[s, v] * g, x[b, s, v])
        out[b] = -weight * total
    return out


def root_alignment(x, normals, weight, segments, eps):
    """Eq. 15: lambda_root (1 - 1/(M k') sum_s sum_{i=1}^{k'} d_hat_{s,i} . n_s); normals (B, M, 3).

    k' = min(segments, N - 2): segment i joins p_i to p_{i+1}, and p_{N-1} is the last vertex.
    """
    b_count, m, n, _ = x.shape
    k = min(segments, n - 2)
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for i in range(1, k + 1):
                e = x[b, s, i + 1] - x[b, s, i]
                d_hat = e / (np.linalg.norm(e) + eps)
                total += np.dot(d_hat, normals[b, s])
        out[b] = weight * (1.0 - total / (m * k))
    return out


def inertia(x, prev, prev2, mass, time_step, weight):
    """Eq. 16: lambda / (M N_mov) sum_s sum_{v'} m / (2 dt^2) |p - (2 p^{t-1} - p^{t-2})|^2, v >= 2."""
    b_count, m, n, _ = x.shape
    n_mov = n - 2
    out = np.zeros(b_count)
    for b in range(b_count):
        total = 0.0
        for s in range(m):
            for v in range(2, n):
                d = x[b, s, v] - (2.0 * prev[b, s, v] - prev2[b, s, v])
                total += mass[s, v] / (2.0 * time_step**2) * np.dot(d, d)
        out[b] = weight / (m * n_mov) * total
    return out
