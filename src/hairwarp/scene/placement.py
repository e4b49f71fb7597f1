"""Rigid hair placement on a posed body: T_rigid of Section 3.1.1, Eq. 1.

    p_rigid[s, v] = M_head p_init[s, v] + dt_align + dt[s, 0]

M_head is the head joint's skinning transform (rest world -> posed world); dt_align the
mean, over the head region, of (posed head vertices - M_head rest head vertices), which
accounts for the other joints' influence on the head through LBS and, the rest head being
the template's (betas = 0, where the hair is authored), for the body shape; dt[s, 0] the
offset that projects strand s's transformed root onto the posed body surface (its closest
point), applied to every vertex of the strand.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hairwarp._validate import check_positive, check_tensor
from hairwarp.scene import _geometry
from hairwarp.scene.body import Body, PosedBody
from hairwarp.scene.rotations import transform_points
from hairwarp.scene.scalp import Scalp

# The root projection searches the body vertices within this distance [m] of some rest root
# (LBS moves the skin under a root by a couple of centimetres at most), ...
SEARCH_RADIUS = 0.05
# ... and, for each posed root, the triangles around its this many nearest of them.
_NEAR_VERTICES = 8
# Elements of the largest temporary evaluated at once: root_search's cdist (roots x vertices),
# the projection's cdist (frames x roots x search vertices) and its candidate triangles
# (frames x roots x candidates x 3). Those hold ~33 MB of temporaries a frame at 600 roots on the
# body of 49 primitives (192 candidates a root): 2^23 let 55 frames through at once (60 frames
# placed: 2.14 GB peak), 2^21 lets 6 (0.61 GB; the same positions; docs/contact.md 18).
_CHUNK = 1 << 21


@dataclass(frozen=True)
class RigidHair:
    """Rigidly posed hair (Eq. 1) and its parts.

    Attributes:
        positions: (B, M, N, 3) rigidly posed strands p_rigid [m].
        normals: (B, M, 3) posed outward unit scalp normals at the roots (the rest normals
            rotated by M_head), for the root alignment loss (Eq. 15).
        align: (B, 3) dt_align [m].
        root_offsets: (B, M, 3) dt[s, 0] [m].
    """

    positions: torch.Tensor
    normals: torch.Tensor
    align: torch.Tensor
    root_offsets: torch.Tensor


@dataclass(frozen=True)
class RootSearch:
    """Where the projection of roots onto posed versions of a body looks (see `root_search`).

    Attributes:
        vertex_ids: (S,) int64 body vertices within `SEARCH_RADIUS` of some rest root.
        incident_faces: (S, K) int64 faces around each of them (padded by repetition).
    """

    vertex_ids: torch.Tensor
    incident_faces: torch.Tensor


def root_search(body: Body, roots: torch.Tensor, radius: float = SEARCH_RADIUS) -> RootSearch:
    """The search structure for projecting roots onto posed versions of `body` (Eq. 1's
    dt[s, 0]). `rigid_placement` builds it when not given; build it once with this function
    to place the same hairstyle on many batches.

    Args:
        body: the body.
        roots: (M, 3) rest-pose root positions [m] (on or near the rest surface).
        radius: search radius around the rest roots [m].

    Returns:
        `RootSearch` on the roots' device.
    """
    check_tensor("roots", roots, shape=(None, 3), allow_empty=False)
    radius = check_positive("radius", radius)
    device = roots.device
    vertices = body.rest_vertices.to(device=device, dtype=torch.float64)
    faces = body.faces.long().to(device)
    r = roots.detach().to(torch.float64)
    near = torch.zeros(vertices.shape[0], dtype=torch.bool, device=device)
    for chunk in r.split(max(1, _CHUNK // vertices.shape[0])):
        near |= (torch.cdist(chunk, vertices) < radius).any(0)
    ids = torch.nonzero(near)[:, 0]
    if ids.numel() < _NEAR_VERTICES:
        raise ValueError(f"roots: fewer than {_NEAR_VERTICES} body vertices within {radius} m of the roots; "
                         "are they in rest-pose world coordinates?")
    # Vertex -> incident faces, padded with the vertex's last face (duplicates are harmless).
    corner = faces.reshape(-1)
    order = torch.argsort(corner, stable=True)
    counts = torch.bincount(corner, minlength=vertices.shape[0])
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(int(counts.max()), device=device)
    pos = starts[ids, None] + torch.minimum(slot[None], (counts[ids, None] - 1).clamp_min(0))
    return RootSearch(vertex_ids=ids, incident_faces=order[pos] // 3)


def project_onto_body(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, search: RootSearch):
    """Closest points of points (B, M, 3) on the body meshes vertices (B, V, 3), among the
    triangles around each point's nearest search vertices.

    Returns:
        (q, face, bary): closest points (B, M, 3) (differentiable with respect to both
        inputs for the chosen triangles), face indices (B, M), barycentric coordinates (B, M, 3).
    """
    batch, num_points = points.shape[0], points.shape[1]
    faces = faces.long()
    per_frame = num_points * max(search.vertex_ids.numel(), 3 * _NEAR_VERTICES * search.incident_faces.shape[1])
    per = max(1, _CHUNK // max(1, per_frame))
    out_q, out_f, out_b = [], [], []
    for start in range(0, batch, per):
        p = points[start:start + per]
        v = vertices[start:start + per]
        with torch.no_grad():
            nearest = torch.cdist(p, v[:, search.vertex_ids]).topk(_NEAR_VERTICES, largest=False).indices
        cand = search.incident_faces[nearest].reshape(p.shape[0], num_points, -1)  # (b, M, C)
        corners = faces[cand]  # (b, M, C, 3)
        frame = torch.arange(p.shape[0], device=p.device)[:, None, None]
        a, b_, c = (v[frame, corners[..., k]] for k in range(3))
        q, bary = _geometry.closest_point_on_triangles(p[:, :, None], a, b_, c)
        best = ((q - p[:, :, None]) ** 2).sum(-1).argmin(-1)  # (b, M)
        pick = best[..., None, None].expand(*best.shape, 1, 3)
        out_q.append(torch.gather(q, 2, pick)[:, :, 0])
        out_b.append(torch.gather(bary, 2, pick)[:, :, 0])
        out_f.append(torch.gather(cand, 2, best[..., None])[..., 0])
    return torch.cat(out_q), torch.cat(out_f), torch.cat(out_b)


def _strand_normals(body, scalp, root_uv, roots, search, dtype):
    """Rest outward normals (M, 3) at the strands' roots."""
    device = roots.device
    if scalp is not None:
        if root_uv is None:
            if scalp.num_roots != roots.shape[0]:
                raise ValueError(
                    f"root_uv: needed when the strands ({roots.shape[0]}) are not the scalp's "
                    f"{scalp.num_roots} roots"
                )
            return scalp.normals.to(device=device, dtype=dtype)
        check_tensor("root_uv", root_uv, shape=(roots.shape[0], 2), device=device)
        grid = scalp.uv.to(device=device, dtype=torch.float64)
        nearest = torch.cdist(root_uv.detach().to(torch.float64), grid).argmin(1)
        return scalp.normals.to(device=device, dtype=dtype)[nearest]
    vertices = body.rest_vertices.to(device=device, dtype=torch.float64)
    faces = body.faces.long().to(device)
    _, face, bary = project_onto_body(roots.detach().to(torch.float64)[None], vertices[None], faces, search)
    normals_v = _geometry.vertex_normals(vertices, faces)
    n = (bary[0, :, :, None] * normals_v[faces[face[0]]]).sum(1)
    return (n / n.norm(dim=-1, keepdim=True)).to(dtype)


def rigid_placement(
    strands: torch.Tensor,
    posed: PosedBody,
    body: Body,
    scalp: Scalp | None = None,
    root_uv: torch.Tensor | None = None,
    search: RootSearch | None = None,
) -> RigidHair:
    """Rigidly pose hair authored on the rest body onto posed bodies (Eq. 1).

    Differentiable with respect to `strands` (the projection's triangle choice is not).

    Args:
        strands: (M, N, 3) float32/float64 strands P_init in rest-pose world coordinates [m],
            vertex 0 the root (on or near the rest scalp).
        posed: `body.pose(...)` for B frames, same dtype and device as `strands`.
        body: the body that was posed (its rest mesh and head region).
        scalp: the scalp the strands grow from; its normals give the root normals. Without
            it the normals come from the rest mesh at the roots' closest points.
        root_uv: (M, 2) root UVs on `scalp` (nearest grid cell); not needed when the strands
            are exactly the scalp's roots in order.
        search: `root_search(body, strands[:, 0])`, to skip building it in repeated calls.

    Returns:
        `RigidHair`: positions (B, M, N, 3), normals (B, M, 3), align (B, 3),
        root_offsets (B, M, 3).

    Raises:
        ValueError: naming the argument on wrong shapes, dtypes, devices or NaN/Inf.
    """
    check_tensor("strands", strands, shape=(None, None, 3), allow_empty=False)
    device, dtype = strands.device, strands.dtype
    if not isinstance(posed, PosedBody):
        raise ValueError(f"posed: expected a PosedBody, got {type(posed).__name__}")
    check_tensor("posed.vertices", posed.vertices, shape=(None, body.num_vertices, 3), dtypes=(dtype,),
                 device=device, allow_empty=False)
    batch = posed.vertices.shape[0]
    check_tensor("posed.head_transform", posed.head_transform, shape=(batch, 4, 4), dtypes=(dtype,),
                 device=device)
    num_strands, num_vertices = strands.shape[0], strands.shape[1]
    roots_rest = strands[:, 0]
    faces = body.faces.long().to(device)
    if search is None:
        search = root_search(body, roots_rest)
    elif not isinstance(search, RootSearch) or search.vertex_ids.device != device:
        raise ValueError(f"search: expected a RootSearch on {device} from root_search(body, strands[:, 0])")
    elif (int(search.vertex_ids.max()) >= body.num_vertices
          or int(search.incident_faces.max()) >= body.num_faces):
        raise ValueError("search: built for another body (indices out of range)")

    m_head = posed.head_transform
    head = body.head_vertex_indices.to(device)
    rest_head = body.rest_vertices.to(device=device, dtype=dtype)[head]
    # dt_align: what LBS does to the head beyond M_head (Section 3.1.1).
    align = (posed.vertices[:, head] - transform_points(m_head, rest_head.expand(batch, -1, -1))).mean(1)
    moved = transform_points(m_head, strands.reshape(1, -1, 3).expand(batch, -1, -1)) + align[:, None]
    moved = moved.reshape(batch, num_strands, num_vertices, 3)
    roots = moved[:, :, 0]
    surface, _, _ = project_onto_body(roots, posed.vertices, faces, search)
    root_offsets = surface - roots
    positions = moved + root_offsets[:, :, None]

    rest_normals = _strand_normals(body, scalp, root_uv, roots_rest, search, dtype)
    normals = rest_normals @ m_head[:, :3, :3].transpose(1, 2)
    return RigidHair(positions=positions, normals=normals, align=align, root_offsets=root_offsets)
