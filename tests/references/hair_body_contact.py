"""numpy float64 reference of hair-body contact: exact point-mesh signed distance by brute force
over all triangles, and the contact energy of HairFormer Eq. 12 with d = that distance.

Written independently of `kernels/hair_body_contact.py` (which walks Ericson's Voronoi regions):
here a point is projected onto each triangle's plane; if the projection's barycentric
coordinates are all >= 0 it is the closest point, otherwise the closest point is the nearest
of the three edges' clamped closest points. The sign is that of (p - c) . N with N the
angle-weighted pseudo-normal of the closest feature (Baerentzen & Aanaes 2005): the face normal
in a face's interior, the sum of the two adjacent face normals on an edge, the sum of the
incident face normals weighted by their corner angles at a vertex. On a closed, consistently
oriented mesh that sign is exact.
"""

from __future__ import annotations

import numpy as np

from references import barrier as barrier_reference

# Region codes of the closest point on a triangle (a, b, c).
FACE = 0
EDGES = (1, 2, 3)  # edges (a, b), (b, c), (c, a)
VERTICES = (4, 5, 6)  # vertices a, b, c

_CHUNK_PAIRS = 1 << 20


def _segment_closest(p, a, b):
    """Closest points on segments [a, b] to p (broadcast), and the clamped parameters."""
    ab = b - a
    t = np.einsum("...k,...k->...", p - a, ab) / np.einsum("...k,...k->...", ab, ab)
    t = np.clip(t, 0.0, 1.0)
    return a + t[..., None] * ab, t


def point_triangle_closest(p, a, b, c):
    """Closest point on triangles (a, b, c) to points p, all broadcast to (..., 3).

    Returns:
        (closest (..., 3), squared distance (...), region code (...)).
    """
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    q = p - np.einsum("...k,...k->...", p - a, n)[..., None] * n
    # Barycentric coordinates of q from the 2x2 normal equations.
    e0, e1, w = b - a, c - a, q - a
    d00 = np.einsum("...k,...k->...", e0, e0)
    d01 = np.einsum("...k,...k->...", e0, e1)
    d11 = np.einsum("...k,...k->...", e1, e1)
    d20 = np.einsum("...k,...k->...", w, e0)
    d21 = np.einsum("...k,...k->...", w, e1)
    det = d00 * d11 - d01 * d01
    beta = (d11 * d20 - d01 * d21) / det
    gamma = (d00 * d21 - d01 * d20) / det
    alpha = 1.0 - beta - gamma
    inside = (alpha >= 0) & (beta >= 0) & (gamma >= 0)

    best = q.copy()
    best_sq = np.where(inside, np.einsum("...k,...k->...", p - q, p - q), np.inf)
    region = np.where(inside, FACE, -1)
    for code, (s0, s1), (v0, v1) in zip(EDGES, ((a, b), (b, c), (c, a)), ((4, 5), (5, 6), (6, 4))):
        point, t = _segment_closest(p, s0, s1)
        sq = np.einsum("...k,...k->...", p - point, p - point)
        better = ~inside & (sq < best_sq)
        best = np.where(better[..., None], point, best)
        best_sq = np.where(better, sq, best_sq)
        edge_region = np.where(t <= 0.0, v0, np.where(t >= 1.0, v1, code))
        region = np.where(better, edge_region, region)
    return best, best_sq, region


def pseudo_normals(vertices, faces):
    """Angle-weighted pseudo-normals: (face (F, 3), per face edge (F, 3, 3), vertex (V, 3))."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    face_n = np.cross(b - a, c - a)
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)

    def angle(p, q, r):  # corner angle at p
        u = (q - p) / np.linalg.norm(q - p, axis=1, keepdims=True)
        w = (r - p) / np.linalg.norm(r - p, axis=1, keepdims=True)
        return np.arccos(np.clip(np.einsum("ij,ij->i", u, w), -1.0, 1.0))

    vertex_n = np.zeros_like(v)
    for k, (p, q, r) in enumerate(((a, b, c), (b, c, a), (c, a, b))):
        np.add.at(vertex_n, f[:, k], angle(p, q, r)[:, None] * face_n)
    edge_pairs = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1)  # (F, 3, 2)
    keys = np.sort(edge_pairs, axis=2)
    keys = keys[..., 0] * len(v) + keys[..., 1]
    _, inverse = np.unique(keys.reshape(-1), return_inverse=True)
    edge_sum = np.zeros((inverse.max() + 1, 3))
    np.add.at(edge_sum, inverse, np.repeat(face_n, 3, axis=0))
    edge_n = edge_sum[inverse].reshape(-1, 3, 3)
    return face_n, edge_n, vertex_n


def signed_distance(points, vertices, faces):
    """Exact signed distance [m] from points (P, 3) to a closed mesh, negative inside.

    Returns:
        (d (P,), closest points (P, 3), unit gradient (P, 3)): the gradient is
        sign * (p - c) / |p - c|, the unit outward direction (undefined on the surface: NaN there).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    face_n, edge_n, vertex_n = pseudo_normals(v, f)
    chunk = max(1, _CHUNK_PAIRS // len(f))
    d = np.empty(len(p))
    closest = np.empty_like(p)
    for start in range(0, len(p), chunk):
        pc = p[start : start + chunk, None, :]
        point, sq, region = point_triangle_closest(pc, a[None], b[None], c[None])
        k = np.argmin(sq, axis=1)
        rows = np.arange(len(k))
        cp = point[rows, k]
        reg = region[rows, k]
        normal = face_n[k].copy()
        for j, code in enumerate(EDGES):
            normal[reg == code] = edge_n[k, j][reg == code]
        for j, code in enumerate(VERTICES):
            normal[reg == code] = vertex_n[f[k, j]][reg == code]
        offset = pc[:, 0] - cp
        dist = np.sqrt(sq[rows, k])
        sign = np.where(np.einsum("ij,ij->i", offset, normal) < 0.0, -1.0, 1.0)
        d[start : start + chunk] = sign * dist
        closest[start : start + chunk] = cp
    with np.errstate(invalid="ignore", divide="ignore"):
        gradient = np.sign(d)[:, None] * (p - closest) / np.abs(d)[:, None]
    return d, closest, gradient


def hair_body_contact_energy(x, vertices, faces, xi, dhat, bp, weight=1.0, variant="quadratic"):
    """Eq. 12 summed over the moving vertices (v >= 2) of each batch item.

    Args:
        x: (B, M, N, 3) hair [m]; vertices (V, 3) or (B, V, 3); faces (F, 3).

    Returns:
        (energy (B,), gradient (B, M, N, 3)) in float64.
    """
    x = np.asarray(x, dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    batch, m, n = x.shape[:3]
    energy = np.zeros(batch)
    gradient = np.zeros_like(x)
    for i in range(batch):
        v = vertices if vertices.ndim == 2 else vertices[i]
        moving = x[i, :, 2:].reshape(-1, 3)
        d, _, grad_d = signed_distance(moving, v, faces)
        e, de = barrier_reference.barrier_and_gradient(d, xi, dhat, bp, variant)
        energy[i] = weight * e.sum()
        g = np.where((de != 0.0)[:, None], weight * de[:, None] * grad_d, 0.0)
        gradient[i, :, 2:] = g.reshape(m, n - 2, 3)
    return energy, gradient
