"""Small triangle-mesh queries in plain torch, for scene set-up (scalp, rigid placement).

Batched over small candidate sets chosen by the callers; the physics' own mesh queries live
in the Warp kernels.
"""

from __future__ import annotations

import torch

def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted (unnormalised, twice the area) normals (..., F, 3) of triangles."""
    a, b, c = (vertices[..., faces[:, k], :] for k in range(3))
    return torch.linalg.cross(b - a, c - a)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit outward vertex normals (..., V, 3): area-weighted means of the incident faces'.

    Args:
        vertices: (..., V, 3) positions [m].
        faces: (F, 3) int vertex indices, counter-clockwise seen from outside.
    """
    fn = face_normals(vertices, faces)
    out = torch.zeros_like(vertices)
    index = faces.long()
    for k in range(3):
        out = out.index_add(-2, index[:, k], fn)
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (..., 3) broadcast together.

    Ericson, Real-Time Collision Detection, 5.1.5, branch-free with torch.where.

    Returns:
        (q, bary): closest points (..., 3) and their barycentric coordinates (..., 3).
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = (ab * ap).sum(-1)
    d2 = (ac * ap).sum(-1)
    bp = p - b
    d3 = (ab * bp).sum(-1)
    d4 = (ac * bp).sum(-1)
    cp = p - c
    d5 = (ab * cp).sum(-1)
    d6 = (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    tiny = torch.finfo(p.dtype).tiny

    def safe_div(n, d):
        return n / torch.where(d.abs() > tiny, d, torch.ones_like(d))

    denom = va + vb + vc
    v_in = safe_div(vb, denom)
    w_in = safe_div(vc, denom)
    one, zero = torch.ones_like(d1), torch.zeros_like(d1)
    # Start from the interior solution, then override by region in the reverse of Ericson's
    # test order (A, B, AB, C, AC, BC), so the first region that matches there wins here.
    u, v, w = 1 - v_in - w_in, v_in, w_in
    # Edge BC.
    t_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    u, v, w = torch.where(m, zero, u), torch.where(m, 1 - t_bc, v), torch.where(m, t_bc, w)
    # Edge AC.
    t_ac = safe_div(d2, d2 - d6)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    u, v, w = torch.where(m, 1 - t_ac, u), torch.where(m, zero, v), torch.where(m, t_ac, w)
    # Vertex C.
    m = (d6 >= 0) & (d5 <= d6)
    u, v, w = torch.where(m, zero, u), torch.where(m, zero, v), torch.where(m, one, w)
    # Edge AB.
    t_ab = safe_div(d1, d1 - d3)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    u, v, w = torch.where(m, 1 - t_ab, u), torch.where(m, t_ab, v), torch.where(m, zero, w)
    # Vertex B.
    m = (d3 >= 0) & (d4 <= d3)
    u, v, w = torch.where(m, zero, u), torch.where(m, one, v), torch.where(m, zero, w)
    # Vertex A.
    m = (d1 <= 0) & (d2 <= 0)
    u, v, w = torch.where(m, one, u), torch.where(m, zero, v), torch.where(m, zero, w)
    bary = torch.stack([u, v, w], -1)
    q = u[..., None] * a + v[..., None] * b + w[..., None] * c
    return q, bary


def ray_mesh_first_exit(origins, directions, vertices, faces, candidates):
    """Where each ray first leaves a closed mesh: its nearest hit on a triangle that faces
    along the ray (Moller-Trumbore). From inside the head, that is the scalp, whatever else
    lies further out (shoulders, arms).

    Args:
        origins: (R, 3) ray origins [m], inside the mesh.
        directions: (R, 3) unit directions.
        vertices: (V, 3) mesh vertices [m].
        faces: (F, 3) triangles, counter-clockwise seen from outside.
        candidates: (R, C) indices into `faces` of the triangles each ray tests.

    Returns:
        (t, face, bary): distances (R,) along the rays (NaN where a ray finds no exit), the
        index into `faces` (R,) (-1 then) and the barycentric coordinates (R, 3) of the hit.
    """
    tri = vertices[faces.long()[candidates]]  # (R, C, 3, 3)
    v0, e1, e2 = tri[..., 0, :], tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    o = origins[:, None, :]
    d = directions[:, None, :].expand_as(e2)
    pvec = torch.linalg.cross(d, e2)
    det = (e1 * pvec).sum(-1)
    ok = det.abs() > 1e-12
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    tvec = o - v0
    u = (tvec * pvec).sum(-1) * inv
    qvec = torch.linalg.cross(tvec, e1)
    v = (d * qvec).sum(-1) * inv
    t = (e2 * qvec).sum(-1) * inv
    exiting = (d * torch.linalg.cross(e1, e2)).sum(-1) > 0
    hit = ok & exiting & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t_hit = torch.where(hit, t, torch.full_like(t, float("inf")))
    best_t, best = t_hit.min(1)
    rows = torch.arange(best.shape[0], device=best.device)
    bu, bv = u[rows, best], v[rows, best]
    missed = torch.isinf(best_t)
    t_out = torch.where(missed, torch.full_like(best_t, float("nan")), best_t)
    face = torch.where(missed, torch.full_like(best, -1), candidates[rows, best])
    return t_out, face, torch.stack([1 - bu - bv, bu, bv], -1)
