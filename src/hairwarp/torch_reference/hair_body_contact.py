"""Plain-torch hair-body contact (HairFormer Eq. 12 with d = signed distance to the body).

The plain-torch peer of `hairwarp.ops.hair_body_contact` for benchmarks and cross-checks:
brute force over every triangle (no BVH), differentiable by autograd.

Method:
    1. Closest face per point, without autograd, in chunks of points x all triangles: the
       closest point on each triangle by Voronoi regions (Ericson, Real-Time Collision
       Detection 5.1.5), then the argmin of the squared distance.
    2. With autograd: the closest point on that one face again, d = sign * |p - c|, so the
       graph holds (P, 3) tensors, not (P, F).
    3. Sign by the angle-weighted pseudo-normal of the closest feature (Baerentzen & Aanaes
       2005): the face normal if the closest point is inside the face, the sum of the two
       adjacent face normals on an edge, the corner-angle-weighted sum of the incident face
       normals at a vertex; inside (d < 0) when (p - c) . N < 0. Exact on closed, consistently
       oriented meshes; the same rule as `wp.mesh_query_point_sign_normal`.

Cost: O(P F) time; memory bounded by `chunk_pairs` point-triangle pairs at a time.
"""

from __future__ import annotations

import torch

from hairwarp.torch_reference.barrier import barrier

# Region codes of the closest point on triangle (a, b, c).
_FACE, _VERTEX_A, _VERTEX_B, _VERTEX_C, _EDGE_AB, _EDGE_BC, _EDGE_CA = range(7)

CHUNK_PAIRS = 1 << 20


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (u * v).sum(-1)


def closest_point_on_triangle(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """Closest point on triangles (a, b, c) to points p (broadcast (..., 3)), and region codes.

    Returns:
        (closest (..., 3), region (...) int64: 0 face, 1-3 vertex a/b/c, 4-6 edge ab/bc/ca).
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    # Each region's closest point, with denominators kept away from zero where unused.
    one = torch.ones_like(d1)
    t_ab = d1 / torch.where(d1 - d3 != 0, d1 - d3, one)
    t_ac = d2 / torch.where(d2 - d6 != 0, d2 - d6, one)
    den_bc = (d4 - d3) + (d5 - d6)
    t_bc = (d4 - d3) / torch.where(den_bc != 0, den_bc, one)
    den = va + vb + vc
    den = torch.where(den != 0, den, one)
    v_face, w_face = vb / den, vc / den

    closest = a + v_face[..., None] * ab + w_face[..., None] * ac
    region = torch.full(d1.shape, _FACE, dtype=torch.int64, device=p.device)
    # Ericson's tests, applied in reverse order so the first matching test wins.
    tests = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + t_bc[..., None] * (c - b), _EDGE_BC),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[..., None] * ac, _EDGE_CA),
        ((d6 >= 0) & (d5 <= d6), c.expand_as(closest), _VERTEX_C),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[..., None] * ab, _EDGE_AB),
        ((d3 >= 0) & (d4 <= d3), b.expand_as(closest), _VERTEX_B),
        ((d1 <= 0) & (d2 <= 0), a.expand_as(closest), _VERTEX_A),
    ]
    for mask, point, code in tests:
        closest = torch.where(mask[..., None], point, closest)
        region = torch.where(mask, torch.full_like(region, code), region)
    return closest, region


def pseudo_normals(vertices: torch.Tensor, faces: torch.Tensor):
    """Angle-weighted pseudo-normals of a mesh.

    Args:
        vertices: (V, 3) [m]; faces: (F, 3) int.

    Returns:
        (face normals (F, 3), per face-edge normals (F, 3, 3) for edges ab, bc, ca, vertex
        normals (V, 3)); not normalised except the face normals (only signs are read).
    """
    f = faces.long()
    a, b, c = vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]]
    face_n = torch.nn.functional.normalize(torch.cross(b - a, c - a, dim=-1), dim=-1)

    def corner(p, q, r):
        u = torch.nn.functional.normalize(q - p, dim=-1)
        w = torch.nn.functional.normalize(r - p, dim=-1)
        return torch.acos(_dot(u, w).clamp(-1.0, 1.0))

    vertex_n = torch.zeros_like(vertices)
    for k, (p, q, r) in enumerate(((a, b, c), (b, c, a), (c, a, b))):
        vertex_n.index_add_(0, f[:, k], corner(p, q, r)[:, None] * face_n)
    pairs = torch.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=1)  # (F, 3, 2)
    keys = pairs.sort(dim=-1).values
    keys = keys[..., 0] * vertices.shape[0] + keys[..., 1]
    _, inverse = torch.unique(keys.reshape(-1), return_inverse=True)
    edge_sum = torch.zeros(int(inverse.max()) + 1, 3, dtype=vertices.dtype, device=vertices.device)
    edge_sum.index_add_(0, inverse, face_n.repeat_interleave(3, dim=0))
    edge_n = edge_sum[inverse].reshape(-1, 3, 3)
    return face_n, edge_n, vertex_n


@torch.no_grad()
def closest_faces(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, chunk_pairs: int = CHUNK_PAIRS
) -> torch.Tensor:
    """Index of the closest triangle for each point (P,), by brute force in chunks."""
    f = faces.long()
    a, b, c = vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]]
    chunk = max(1, chunk_pairs // f.shape[0])
    out = torch.empty(points.shape[0], dtype=torch.int64, device=points.device)
    for start in range(0, points.shape[0], chunk):
        p = points[start : start + chunk, None, :]
        closest, _ = closest_point_on_triangle(p, a[None], b[None], c[None])
        out[start : start + chunk] = ((p - closest) ** 2).sum(-1).argmin(dim=1)
    return out


def point_mesh_signed_distance(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, chunk_pairs: int = CHUNK_PAIRS
) -> torch.Tensor:
    """Signed distance [m] from points (P, 3) to a closed mesh (V, 3) / (F, 3), negative inside.

    Differentiable w.r.t. `points` (and `vertices`) by autograd; the face choice and the sign
    are piecewise constant. At d = 0 the autograd gradient of |p - c| is NaN-free only off the
    surface: points exactly on the mesh get a zero gradient here.
    """
    face = closest_faces(points.detach(), vertices.detach(), faces, chunk_pairs)
    f = faces.long()[face]
    a, b, c = vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]]
    closest, region = closest_point_on_triangle(points, a, b, c)
    with torch.no_grad():
        face_n, edge_n, vertex_n = pseudo_normals(vertices.detach(), faces)
        normal = face_n[face]
        for k, code in enumerate((_EDGE_AB, _EDGE_BC, _EDGE_CA)):
            normal = torch.where((region == code)[:, None], edge_n[face, k], normal)
        for k, code in enumerate((_VERTEX_A, _VERTEX_B, _VERTEX_C)):
            normal = torch.where((region == code)[:, None], vertex_n[f[:, k]], normal)
        sign = torch.where(_dot(points.detach() - closest.detach(), normal) < 0, -1.0, 1.0).to(points.dtype)
    offset = points - closest
    sq = (offset * offset).sum(-1)
    # sqrt'(0) is infinite: evaluate at a safe value where the point is on the surface.
    on_surface = sq <= 0
    safe = torch.where(on_surface, torch.ones_like(sq), sq)
    dist = torch.where(on_surface, torch.zeros_like(sq), torch.sqrt(safe))
    return sign * dist


def hair_body_signed_distance(x: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Signed distance of every hair vertex [m]: x (M, N, 3) or (B, M, N, 3) against
    vertices (V, 3) (shared) or (B, V, 3) (one pose per batch item); returns x.shape[:-1].
    """
    if x.dim() == 3 or vertices.dim() == 2:
        return point_mesh_signed_distance(x.reshape(-1, 3), vertices, faces).reshape(x.shape[:-1])
    per_pose = [
        point_mesh_signed_distance(x[i].reshape(-1, 3), vertices[i], faces) for i in range(x.shape[0])
    ]
    return torch.stack(per_pose).reshape(x.shape[:-1])


def hair_body_contact_energy(
    x: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    xi: float,
    dhat: float,
    bp: float,
    weight: float = 1.0,
    variant: str = "quadratic",
) -> torch.Tensor:
    """Eq. 12 contact energy: weight * sum over moving vertices (v >= 2) of B(d), per batch item.

    Args:
        x: (M, N, 3) or (B, M, N, 3) hair [m].
        vertices: (V, 3) or (B, V, 3) body [m]; faces: (F, 3), closed and outward.
        xi, dhat, bp, weight, variant: as `hairwarp.ops.hair_body_contact_energy`.

    Returns:
        (B,) energies, or a 0-dim tensor for unbatched `x`.
    """
    d = hair_body_signed_distance(x[..., 2:, :], vertices, faces)
    return weight * barrier(d, xi, dhat, bp, variant).sum(dim=(-2, -1))


def nearest_vertex_signed_distance(x: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor,
                                   chunk: int = 8192) -> torch.Tensor:
    """The collision query neural cloth simulators write in plain torch: the nearest body vertex
    (chunked `torch.cdist`) and the sign and distance along that vertex's normal,
    d = (p - v_nearest) . n_nearest.

    An approximation of the signed distance (exact for points right above a vertex, off by the
    tangential offset elsewhere), but what a user without a BVH writes; it is the plain-torch
    peer of the hair-body term in the energy benchmark, where the exact brute force of
    `hair_body_signed_distance` would take minutes.

    Args:
        x: (B, M, N, 3) hair [m]; vertices: (B, V, 3) or (V, 3) body [m]; faces (F, 3).

    Returns:
        (B, M, N) approximate signed distances [m], differentiable w.r.t. x.
    """
    xb = x if x.dim() == 4 else x.unsqueeze(0)
    vb = vertices if vertices.dim() == 3 else vertices.unsqueeze(0).expand(xb.shape[0], -1, -1)
    f = faces.long()
    out = []
    for b in range(xb.shape[0]):
        v = vb[b].detach()
        fn = torch.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=1)
        vn = torch.zeros_like(v).index_add_(0, f.reshape(-1), fn.repeat_interleave(3, dim=0))
        vn = vn / vn.norm(dim=1, keepdim=True).clamp_min(1e-20)
        p = xb[b].reshape(-1, 3)
        nearest = torch.cat([torch.cdist(p[i:i + chunk].detach(), v).argmin(dim=1)
                             for i in range(0, p.shape[0], chunk)])
        out.append(((p - v[nearest]) * vn[nearest]).sum(dim=1).reshape(xb.shape[1:-1]))
    return torch.stack(out)
