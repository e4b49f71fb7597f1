"""Torch bridge of hair-body contact (HairFormer Eq. 12 with d = signed distance to the body);
device code in `hairwarp.kernels.hair_body_contact`.

`BodyMesh` owns the posed body's `wp.Mesh`(es): validated once, refitted in place when the body
deforms (`update`), and cropped to the triangles the hair can reach (`crop`, `crop_for_hair`).
`hair_body_contact_energy` is the contact term, `hair_body_signed_distance` the per-vertex
distance for metrics, `point_mesh_signed_distance` the one-shot signed distance of points,
`hair_body_keep_out_push` the body pass's push (`hairwarp.methods.keep_out`).

Sign convention: d < 0 inside the body, by the angle-weighted pseudo-normal of the closest
feature (face, edge or vertex; see the kernel module for why, and why not the winding number).
The edge and vertex pseudo-normals are computed here, on the device, from the mesh's adjacency
(found once when the body is built) and recomputed when the body moves (`update`); a crop keeps
the one-ring of its faces (extra vertices and "normal faces" outside its BVH) so its normals
are those of the full body. Meshes must be watertight, edge-manifold and
consistently oriented with outward normals (counter-clockwise seen from outside). A mesh that
passes through itself (a posed arm into the chest) is queried as the boundary of the union of
its parts: the faces inside another part left out, the crossing faces cut into pieces, and the
pieces on the crossing signed by the uncut mesh's winding number (`BodyMesh`'s
`split_self_intersections`; docs/contact.md 14).
Gradients flow to the hair/points only: `wp.Mesh` queries give none to the body vertices.
"""

from __future__ import annotations

import math
import threading

import torch
import warp as wp

from hairwarp import _warp
from hairwarp._validate import check_positive, check_tensor
from hairwarp.kernels import hair_body_contact as kernels
from hairwarp.ops.barrier import barrier_variant_id, check_barrier_parameters, join_fraction_tensor
from hairwarp.ops.reductions import row_sums

INDEX_DTYPES = (torch.int32, torch.int64)

# Below this distance [m] a point counts as on the surface and gets the face normal as the
# gradient: in float32 the closest point carries ~1e-7 m of rounding at body scale.
_ZERO_DISTANCE = {torch.float32: 1.0e-6, torch.float64: 1.0e-12}

# Kernel choice: one thread per vertex in two passes (capped queries, then the misses' sides
# along each strand; `kernels.hair_body_contact`) on every device. It replaced, on the CPU, the
# per-strand walk that skips the queries of vertices proven outside by wide Lipschitz balls:
# as fast there (1024 x 100 hair, head turn, one CPU thread: 77 vs 75 ms per call; the L-BFGS
# drape of docs/contact.md 1 024-1 031 vs 1 174 ms per frame), 3x faster on an H100, and exact
# on a body cropped to the hair's reach, where a wide ball can pass through the crop's open
# border and the walk called 604 vertices inside the torso "outside" (docs/contact.md). The
# walk stays selectable ("strand") for the benchmarks.
def _strategy(device: torch.device, num_strands: int) -> str:
    return "vertex"


# The body's BVH (`wp.Mesh`), by `BodyMesh(bvh=...)`: "sah" (built on the CPU, also for a GPU
# mesh: the best tree, 2 faces per leaf) or "lbvh" (built on the GPU, Warp's default there:
# fast to build, slower to query). On an H100, the default body cropped, 1024 x 100 hair:
# hair-body fwd+bwd at batch 32 7.97 ms (lbvh) -> 5.63 ms (sah, 2 per leaf), the whole energy
# replayed at batch 1 1.22 -> 1.00 ms; the build 2.7 -> 12 ms per mesh (docs/contact.md 6).
# "sah" where one body serves many queries (drapes, optimizers, benchmarks), "lbvh" for a
# training batch's bodies, built every step.
BVH_CONSTRUCTORS = ("sah", "lbvh")
_BVH_LEAF_SIZE = {"sah": 2, "lbvh": 4}


def _check_mesh(vertices: torch.Tensor, faces: torch.Tensor, *, require_watertight: bool) -> None:
    """Topology and orientation checks on a body mesh (reads results back to the host)."""
    num_vertices = vertices.shape[-2]
    if num_vertices >= 2**31:
        raise ValueError(f"vertices: at most 2^31 - 1 vertices are supported, got {num_vertices}")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= num_vertices:
        bad = lo if lo < 0 else hi
        raise ValueError(f"faces: vertex index out of range [0, {num_vertices}): found {bad}")
    f = faces.long()
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    if bool(repeated.any()):
        first = int(repeated.nonzero()[0, 0])
        raise ValueError(f"faces: {int(repeated.sum())} faces repeat a vertex index (first: face {first})")
    v = vertices.detach().to(torch.float64).reshape(-1, num_vertices, 3)
    a, b, c = v[:, f[:, 0]], v[:, f[:, 1]], v[:, f[:, 2]]
    area2 = torch.linalg.vector_norm(torch.cross(b - a, c - a, dim=-1), dim=-1)
    if bool((area2.sum(-1) <= 0).any()):
        raise ValueError("vertices: every face is degenerate (zero total area)")
    if not require_watertight:
        return
    directed = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    undirected = torch.sort(directed, dim=1).values
    _, counts = torch.unique(undirected[:, 0] * num_vertices + undirected[:, 1], return_counts=True)
    open_edges = int((counts == 1).sum())
    crowded_edges = int((counts > 2).sum())
    if open_edges or crowded_edges:
        raise ValueError(
            f"faces: the mesh is not watertight: {open_edges} edges belong to one face only (holes) and "
            f"{crowded_edges} to more than two faces; the sign of the distance needs a closed surface "
            "whose every edge is shared by exactly two faces (pass require_watertight=False to BodyMesh "
            "only if no hair vertex can be nearest to an open border)"
        )
    if torch.unique(directed[:, 0] * num_vertices + directed[:, 1]).numel() != directed.shape[0]:
        raise ValueError(
            "faces: inconsistent orientation: some edge is traversed twice in the same direction; "
            "orient every face counter-clockwise seen from outside"
        )
    volume = (a * torch.cross(b, c, dim=-1)).sum(-1).sum(-1) / 6.0
    if bool((volume <= 0).any()):
        raise ValueError(
            "faces: the mesh encloses a negative volume: its normals point inward; "
            "orient every face counter-clockwise seen from outside"
        )


def _edge_inverse(faces: torch.Tensor) -> tuple[torch.Tensor, int]:
    """(3 F,) id of the undirected edge of each face edge (edge k joins corners k, k + 1), and
    the number of distinct edges. Reads the count back to the host (`torch.unique`).
    """
    f = faces.long()
    directed = torch.stack([f, f.roll(-1, dims=1)], dim=-1).reshape(-1, 2)
    undirected = torch.sort(directed, dim=1).values
    keys = undirected[:, 0] * (int(f.max()) + 1) + undirected[:, 1]
    unique, inverse = torch.unique(keys, return_inverse=True)
    return inverse, int(unique.numel())


def _edge_slots(faces: torch.Tensor) -> torch.Tensor:
    """(E, 2) the two face edges (index 3 f + k: edge k of face f) of each edge of a watertight
    mesh's (F, 3) faces.
    """
    inverse, _ = _edge_inverse(faces)
    return torch.argsort(inverse, stable=True).view(-1, 2)


class _RowSums:
    """out[:, index[j]] += values[:, j], the sum a mesh's normals take over its faces' corners or
    edges, for a fixed `index` (a topology). On the CPU a product with the (rows, n) 0/1 incidence
    matrix in CSR form (one per dtype, made at the first sum): torch's `index_add_` adds serially
    there, and the vertex and edge sums were 12 of the 15 ms a body's pseudo-normals took on the
    2-core CPU (30 156 faces), 5 ms as products. The CSR rows keep the index order, so the sums
    are `index_add_`'s bit for bit. On CUDA `index_add_` itself.

    Args:
        index: (n,) int64 target row of each value.
        rows: the number of rows summed into.
    """

    def __init__(self, index: torch.Tensor, rows: int):
        self.index, self.rows = index, int(rows)
        self._csr: dict[torch.dtype, torch.Tensor] = {}
        self._layout = None
        if index.device.type == "cpu":
            crow = torch.zeros(self.rows + 1, dtype=torch.int64)
            crow[1:] = torch.bincount(index, minlength=self.rows).cumsum(0)
            self._layout = (crow, torch.argsort(index, stable=True))

    def __call__(self, values: torch.Tensor) -> torch.Tensor:
        """(B, n, k) values -> (B, rows, k) sums."""
        batch, n, k = values.shape
        if self._layout is None or values.device.type != "cpu":
            out = torch.zeros(batch, self.rows, k, dtype=values.dtype, device=values.device)
            return out.index_add_(1, self.index, values)
        matrix = self._csr.get(values.dtype)
        if matrix is None:
            import warnings

            crow, col = self._layout
            with warnings.catch_warnings():
                # torch's notes that CSR is in beta and that its invariant checks are off (the
                # indices are made here, valid by construction)
                warnings.filterwarnings("ignore", message="Sparse (CSR tensor support|invariant checks)")
                matrix = torch.sparse_csr_tensor(crow, col, torch.ones(n, dtype=values.dtype), size=(self.rows, n))
            self._csr[values.dtype] = matrix
        columns = values.permute(1, 0, 2).reshape(n, batch * k)
        return (matrix @ columns).reshape(self.rows, batch, k).permute(1, 0, 2)


class _NormalSums:
    """The topology of a mesh's pseudo-normals (`_pseudo_normals`): its (R, 3) int64 faces, each
    face edge's undirected edge id (`_edge_inverse`: a host read, once) and the sums over
    corners and edges (`_RowSums`).
    """

    def __init__(self, faces: torch.Tensor, num_vertices: int):
        self.faces = faces.long()
        self.edge_inverse, self.num_edges = _edge_inverse(self.faces)
        self.vertex_sum = _RowSums(self.faces.reshape(-1), num_vertices)
        self.edge_sum = _RowSums(self.edge_inverse, self.num_edges)


def _pseudo_normals(points: torch.Tensor, sums: _NormalSums, face_rows: torch.Tensor | None):
    """Vertex and edge pseudo-normals (Baerentzen & Aanaes 2005) of B posed meshes.

    Args:
        points: (B, V, 3) vertices.
        sums: `_NormalSums` of the (R, 3) faces the normals are summed over (a crop's one-ring).
        face_rows: (F,) rows of those faces that the BVH holds (None: all of them).

    Returns:
        vertex normals (B, V, 3) (angle-weighted sums of unit face normals) and edge normals
        (B, F, 3, 3) (per face edge, the sum of the unit normals of the faces sharing it); not
        normalised: only their direction's side matters. Zero-area faces contribute nothing.
    """
    batch = points.shape[0]
    faces = sums.faces
    a, b, c = points[:, faces[:, 0]], points[:, faces[:, 1]], points[:, faces[:, 2]]
    normal = torch.cross(b - a, c - a, dim=-1)
    length = torch.linalg.vector_norm(normal, dim=-1, keepdim=True)
    unit = torch.where(length > 0, normal / length.clamp_min(torch.finfo(points.dtype).tiny), 0.0)

    def angle(e0, e1):
        return torch.atan2(torch.linalg.vector_norm(torch.cross(e0, e1, dim=-1), dim=-1), (e0 * e1).sum(-1))

    corner = torch.stack([angle(b - a, c - a), angle(c - b, a - b), angle(a - c, b - c)], dim=-1)
    weighted = (corner[..., None] * unit[:, :, None, :]).reshape(batch, -1, 3)
    vertex = sums.vertex_sum(weighted)
    per_edge = sums.edge_sum(unit[:, :, None, :].expand(-1, -1, 3, -1).reshape(batch, -1, 3))
    inverse = sums.edge_inverse.view(-1, 3)
    if face_rows is not None:
        inverse = inverse[face_rows]
    return vertex, per_edge[:, inverse]


# Self-intersections (`kernels.hair_body_contact`): a face that crosses another part of the
# mesh is cut into pieces, down to this fraction of the body's bounding-box diagonal where they
# straddle the other part (1 mm on the default body, 1.91 m: the union's boundary is followed to
# about that); the pieces inside the body are left out. A fraction: a body in centimetres gets
# the same surface.
SELF_INTERSECTION_PIECE_FRACTION = 1.0e-3 / 1.91
# A piece's children: its corners (a, b, c) and edge midpoints, as barycentric weights of
# (a, b, c), oriented like it; and at most this many halvings of a cut face's edges.
_MIDPOINT_SPLIT = (
    ((1.0, 0.0, 0.0), (0.5, 0.5, 0.0), (0.5, 0.0, 0.5)),
    ((0.5, 0.5, 0.0), (0.0, 1.0, 0.0), (0.0, 0.5, 0.5)),
    ((0.5, 0.0, 0.5), (0.0, 0.5, 0.5), (0.0, 0.0, 1.0)),
    ((0.5, 0.5, 0.0), (0.0, 0.5, 0.5), (0.5, 0.0, 0.5)),
)
_MAX_SPLIT_LEVELS = 6
# At most this many pieces in all: a body whose parts overlap everywhere (a character built from
# primitives) crosses itself along metres of seams, and 1 mm pieces along all of them were
# 168 571 pieces and 14 s a pose on the 2-core CPU (3 065 crossing faces; the default body's
# armpits: 91 and 4 720 pieces). Past the budget the refinement stops a level early: the pieces
# left on the crossing are larger, and those whose side of the other part the seam-side pass
# cannot read are signed by the winding number at query time, so the sign stays exact.
SELF_INTERSECTION_MAX_PIECES = 16384
# The winding number is read this far outside a face or piece (times the pose's bounding-box
# diagonal): past float32's rounding at body scale, well inside the pieces' size.
_WINDING_OFFSET = 1.0e-6


class _SplitSurface:
    """Where the pieces of the faces split at self-intersections lie: piece p has corners
    sum_j weights[p, c, j] * vertex[faces[parent[p], j]].
    """

    def __init__(self, num_vertices: int, faces: torch.Tensor, parent: torch.Tensor, weights: torch.Tensor):
        self.num_vertices, self.faces, self.parent, self.weights = num_vertices, faces, parent, weights
        self.first_piece_face = None  # index of the first piece among the uncut body's BVH faces
        self.touches_inside = torch.zeros(parent.shape[0], dtype=torch.bool, device=parent.device)

    def mark_pieces_touching(self, inside_faces: torch.Tensor) -> None:
        """Mark the pieces with a corner on a face left out inside the other part
        (`touches_inside`): on their parent's edge next to one, or at a corner one shares. The
        union's boundary leaves there through a hole the uncut mesh's pseudo-normals know
        nothing of, and no face need cross the piece: the winding number signs them.

        Args:
            inside_faces: (F,) bool, the uncut faces left out (inside in every pose).
        """
        on_inside = torch.zeros(self.num_vertices, dtype=torch.bool, device=self.faces.device)
        on_inside[self.faces[inside_faces].reshape(-1)] = True
        slots = _edge_slots(self.faces)
        across = torch.empty(slots.numel(), dtype=torch.long, device=slots.device)
        across[slots[:, 0]], across[slots[:, 1]] = slots[:, 1] // 3, slots[:, 0] // 3
        across = across.view(-1, 3)  # across[f, e]: the face sharing edge e of face f
        zero = self.weights == 0  # (P, 3 corners, 3 parent weights)
        count = zero.sum(dim=-1)
        parent = self.parent[:, None].expand(-1, 3)
        # One zero weight k: on the parent's edge (k + 1) % 3; two: at the parent's other corner.
        edge = (zero.long().argmax(dim=-1) + 1) % 3
        corner = (~zero).long().argmax(dim=-1)
        at_edge = (count == 1) & inside_faces[across[parent, edge]]
        at_corner = (count == 2) & on_inside[self.faces[parent, corner]]
        self.touches_inside = (at_edge | at_corner).any(dim=1)

    def piece_corners(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) vertices -> (B, 3 P, 3) the pieces' corners, in their dtype."""
        corners = vertices[:, self.faces[self.parent]]  # (B, P, 3, 3): parent's corners
        weights = self.weights.to(device=vertices.device, dtype=vertices.dtype)
        return torch.einsum("pcj,bpjk->bpck", weights, corners).reshape(vertices.shape[0], -1, 3)

    def augment(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) the mesh's vertices -> (B, V + 3 P, 3) with the pieces' corners after them."""
        return torch.cat([vertices, self.piece_corners(vertices)], dim=1)

    def piece_pseudo_normals(self, source: torch.Tensor, vertex_map: torch.Tensor | None,
                             face_map: torch.Tensor | None, vertex: torch.Tensor, edge: torch.Tensor) -> None:
        """The pieces' vertex and edge pseudo-normals, written in place: a piece's corners and
        edges are its own (no other face shares them), so `_pseudo_normals` gives them its face
        normal alone; where one lies on its parent face's edge or corner, the uncut mesh's pseudo-
        normal there is the right one (a point on a sharp fold signed by one side's normal alone
        can be called outside from deep inside), elsewhere the parent's face normal.

        Args:
            source: (B, V, 3) the uncut mesh's vertices.
            vertex_map, face_map: the body's vertices and BVH faces in the uncut body with pieces
                (None: that body itself), to find the pieces.
            vertex: (B, V', 3) the body's vertex pseudo-normals; edge: (B, F', 3, 3) its BVH faces'.
        """
        if self.first_piece_face is None:
            raise RuntimeError("piece_pseudo_normals: first_piece_face is not set")
        if getattr(self, "_source_sums", None) is None:
            self._source_sums = _NormalSums(self.faces, self.num_vertices)  # topology: once (a host read)
        source_vertex, source_edge = _pseudo_normals(source, self._source_sums, None)
        corners = source[:, self.faces]  # (B, F, 3, 3)
        face_normal = torch.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0], dim=-1)
        face_normal = torch.nn.functional.normalize(face_normal, dim=-1)
        # Every normal a piece's corner or edge can take, in one table: the parent's face normal
        # (F), the uncut mesh's edge normals (3 F) and vertex normals (V).
        table = torch.cat([face_normal, source_edge.reshape(source.shape[0], -1, 3), source_vertex], dim=1)
        plan = self._normal_plan(vertex_map, face_map, vertex.shape[1], edge.shape[1], vertex.device)
        if plan["vertex_rows"].numel():
            vertex[:, plan["vertex_rows"]] = table[:, plan["vertex_source"]]
        if plan["edge_rows"].numel():
            for e in range(3):
                edge[:, plan["edge_rows"], e] = table[:, plan["edge_source"][e]]

    def _normal_plan(self, vertex_map: torch.Tensor | None, face_map: torch.Tensor | None, num_vertices: int,
                     num_faces: int, device: torch.device) -> dict:
        """Which normal of `piece_pseudo_normals`' table each piece corner and piece edge of a
        body takes: topology alone, so found once per body layout (host reads there) and then
        gathered at every `BodyMesh.update` with no host read (an H200 spent ~5 ms an update on
        the reads when found anew each time, twenty-fourth session).
        """
        key = (None if vertex_map is None else vertex_map.data_ptr(), None if face_map is None else face_map.data_ptr(),
               num_vertices, num_faces)
        plans = self.__dict__.setdefault("_normal_plans", {})
        if key in plans:
            return plans[key]
        num_source_faces = self.faces.shape[0]

        def feature_source(piece: torch.Tensor, zero: torch.Tensor) -> torch.Tensor:
            # zero: (n, 3) bool, the parent's barycentric weights that are 0 at the feature:
            # none, the parent's face normal; one (k), its edge (k + 1) % 3; two, the corner left.
            parent = self.parent[piece]
            source = parent.clone()
            on_edge = zero.sum(dim=1) == 1
            k = zero.long().argmax(dim=1)
            source[on_edge] = num_source_faces + 3 * parent[on_edge] + (k[on_edge] + 1) % 3
            at_corner = zero.sum(dim=1) == 2
            corner = (~zero).long().argmax(dim=1)
            source[at_corner] = 4 * num_source_faces + self.faces[parent[at_corner], corner[at_corner]]
            return source

        ids = torch.arange(num_vertices, device=device) if vertex_map is None else vertex_map
        corner_of = ids - self.num_vertices
        vertex_rows = (corner_of >= 0).nonzero().reshape(-1)
        piece, corner = corner_of[vertex_rows] // 3, corner_of[vertex_rows] % 3
        vertex_source = feature_source(piece, self.weights[piece, corner] == 0)
        faces = torch.arange(num_faces, device=device) if face_map is None else face_map
        piece_of = faces - self.first_piece_face
        edge_rows = (piece_of >= 0).nonzero().reshape(-1)
        piece = piece_of[edge_rows]
        # Edge e joins the piece's corners e and e + 1: on the parent's boundary where both have
        # the same zero weight.
        edge_source = [feature_source(piece, (self.weights[piece, e] == 0) & (self.weights[piece, (e + 1) % 3] == 0))
                       for e in range(3)]
        # The maps are held with their plan: no other layout can take their addresses (the key).
        plans[key] = {"vertex_rows": vertex_rows, "vertex_source": vertex_source, "edge_rows": edge_rows,
                      "edge_source": edge_source, "maps": (vertex_map, face_map)}
        return plans[key]


def _winding_inside(mesh: wp.Mesh, points: torch.Tensor) -> torch.Tensor:
    """(P,) bool: points (P, 3) inside `mesh`: winding number >= 1, by three rays
    (`hairwarp.kernels.hair_body_contact.ray_inside`).
    """
    inside = torch.zeros(points.shape[0], dtype=torch.int32, device=points.device)
    if points.shape[0]:
        _warp.launch(kernels.winding_inside_kernel, dim=points.shape[0],
                     inputs=[mesh.id, _warp.as_warp(points.to(torch.float32).contiguous(), vec3=True)],
                     outputs=[_warp.as_warp(inside)], device=_warp.warp_device(points.device))
    return inside.bool()


def _outside_sample(corners: torch.Tensor, offset: float) -> torch.Tensor:
    """(..., 3, 3) triangles -> (..., 3) their centroids moved `offset` [m] along the unit normal."""
    a, b, c = corners.unbind(-2)
    normal = torch.nn.functional.normalize(torch.cross(b - a, c - a, dim=-1), dim=-1)
    return (a + b + c) / 3.0 + offset * normal


def _split_self_intersections(vertices: torch.Tensor, faces: torch.Tensor):
    """The contact surface of a closed mesh that passes through itself: the boundary of the
    union of its parts (points inside any part inside), approximated.

    Per pose: the faces that cross another face (`self_intersecting_faces_kernel`), then the
    faces wholly inside another part, found by the winding number from the crossing faces'
    neighbours outward (a face that crosses nothing lies wholly on one side). A crossing face is
    cut into pieces, down to `SELF_INTERSECTION_PIECE_FRACTION` of the body's size where they
    straddle the other part;
    the pieces and the faces inside the body are left out. Poses share the topology: a face is cut if it crosses or lies
    inside in any pose, and a piece (or a face inside) is left out only if it lies inside in
    every pose.

    Args:
        vertices: (B, V, 3) the posed meshes [m]; faces: (F, 3) int32, watertight.

    Returns:
        None when the mesh does not pass through itself; else (vertices (B, V + 3 P, 3) with
        the kept pieces' corners appended, BVH faces (F', 3) int32 (the faces not cut, then the
        pieces), normal faces (F + P, 3) int64 (every face, then the pieces: the pseudo-normals
        of the faces around a cut keep their neighbours), face rows (F',) int64 (the BVH faces
        among the normal faces), the `_SplitSurface`, counts, (float32 vertices (B, V, 3), the
        B uncut `wp.Mesh` on them: the body's winding meshes)).
    """
    batch, num_vertices = vertices.shape[:2]
    device = vertices.device
    f = faces.long()
    num_faces = f.shape[0]
    wp_device = _warp.warp_device(device)
    faces_wp = _warp.as_warp(faces.contiguous())
    # Faces adjacent across each edge (watertight: every edge has exactly two faces).
    pairs = _edge_slots(f) // 3
    # A copy: the meshes built on it become the body's winding meshes, moved by `update`.
    points32 = vertices.to(torch.float32, copy=True).contiguous()
    crossing, inside, meshes, offsets, diagonals = [], [], [], [], []
    for b in range(batch):
        mesh = wp.Mesh(points=_warp.as_warp(points32[b], vec3=True), indices=faces_wp)
        flags = torch.empty(num_faces, dtype=torch.int32, device=device)
        _warp.launch(kernels.self_intersecting_faces_kernel, dim=num_faces,
                     inputs=[mesh.id, _warp.as_warp(points32[b], vec3=True), faces_wp],
                     outputs=[_warp.as_warp(flags)], device=wp_device)
        cross = flags.bool()
        diagonals.append(float(torch.linalg.vector_norm(points32[b].amax(0) - points32[b].amin(0))))
        offset = _WINDING_OFFSET * diagonals[-1]
        embedded = torch.zeros_like(cross)
        tested = cross.clone()
        front = cross
        while bool(front.any()):
            reached = torch.cat([pairs[front[pairs[:, 0]], 1], pairs[front[pairs[:, 1]], 0]])
            candidates = torch.unique(reached[~tested[reached]])
            if candidates.numel() == 0:
                break
            tested[candidates] = True
            sample = _outside_sample(vertices[b, f[candidates]].to(torch.float64), offset)
            inner = candidates[_winding_inside(mesh, sample)]
            embedded[inner] = True
            front = torch.zeros_like(cross)
            front[inner] = True
        # A face that shares a corner with a face inside touches the other part there (a graze
        # the crossing test can miss): cut it too, so the pieces at that corner are checked.
        touching = torch.zeros(num_vertices, dtype=torch.bool, device=device)
        touching[f[embedded].reshape(-1)] = True
        cross = cross | (touching[f].any(dim=1) & ~embedded)
        crossing.append(cross)
        inside.append(embedded)
        meshes.append(mesh)
        offsets.append(offset)
    crossing, inside = torch.stack(crossing), torch.stack(inside)
    cut = (crossing | inside).any(dim=0)
    if not bool(cut.any()):
        return None
    # Pieces: each cut face split 1-to-4 at its edges' midpoints, again where a piece straddles
    # the other part (its corners' and centre's outer sides disagree on the winding number in
    # some pose; a crossing face at least once), down to SELF_INTERSECTION_PIECE_FRACTION of the
    # largest pose's diagonal; a piece is left out if it lies inside in every pose. Pieces away
    # from the crossing stay large: few small faces for the BVH's walks.
    cut_faces = cut.nonzero().reshape(-1)
    piece_size = SELF_INTERSECTION_PIECE_FRACTION * max(diagonals)
    split_weights = torch.tensor(_MIDPOINT_SPLIT, dtype=torch.float64, device=device)
    parent = cut_faces
    weight = torch.eye(3, dtype=torch.float64, device=device).expand(cut_faces.numel(), 3, 3)
    kept_parent, kept_weight, seam_parent, seam_weight = [], [], [], []
    positions64 = vertices.to(torch.float64)
    face_corners = positions64[:, f[cut_faces]]  # (B, C, 3, 3)
    face_normal = torch.zeros(batch, num_faces, 3, dtype=torch.float64, device=device)
    face_normal[:, cut_faces] = torch.nn.functional.normalize(torch.cross(
        face_corners[:, :, 1] - face_corners[:, :, 0], face_corners[:, :, 2] - face_corners[:, :, 0], dim=-1), dim=-1)
    # Samples are read off the cut face's plane (a piece's corner is shared by up to six pieces,
    # and by its parent a level up): each sample is tested once per pose, keyed by its face and
    # barycentric weights (multiples of 1 / (3 2^levels): exact in float64).
    weight_scale = 3 * 2 ** _MAX_SPLIT_LEVELS
    known = [(torch.empty(0, dtype=torch.int64, device=device), torch.empty(0, dtype=torch.bool, device=device))
             for _ in range(batch)]
    for level in range(_MAX_SPLIT_LEVELS + 1):
        corners = torch.einsum("pcj,bpjk->bpck", weight, positions64[:, f[parent]])  # (B, N, 3, 3)
        sample_weight = torch.cat([weight, weight.mean(dim=1, keepdim=True)], dim=1)  # (N, 4, 3)
        quantized = (sample_weight[..., :2] * weight_scale).round().long()
        sample_key = (parent[:, None] * (weight_scale + 1) + quantized[..., 0]) * (weight_scale + 1) + quantized[..., 1]
        sample_inside = inside[:, parent, None].expand(-1, -1, 4).clone()
        for b in range(batch):
            test = crossing[b, parent].nonzero().reshape(-1)
            keys, first = torch.unique(sample_key[test].reshape(-1), return_inverse=True)
            known_keys, known_inside = known[b]
            at = torch.searchsorted(known_keys, keys).clamp_max(max(known_keys.numel() - 1, 0))
            found = known_keys[at] == keys if known_keys.numel() else torch.zeros_like(keys, dtype=torch.bool)
            result = torch.zeros(keys.shape, dtype=torch.bool, device=device)
            result[found] = known_inside[at[found]]
            new = (~found).nonzero().reshape(-1)
            if new.numel():
                owner = torch.empty_like(keys)
                owner[first] = torch.arange(first.numel(), device=device)  # one sample per new key
                row = owner[new]
                piece, slot = test[row // 4], row % 4
                points = (torch.einsum("sj,sjk->sk", sample_weight[piece, slot], positions64[b, f[parent[piece]]])
                          + offsets[b] * face_normal[b, parent[piece]])
                result[new] = _winding_inside(meshes[b], points)
                merged_keys, order = torch.sort(torch.cat([known_keys, keys[new]]))
                known[b] = (merged_keys, torch.cat([known_inside, result[new]])[order])
            sample_inside[b, test] = result[first].view(-1, 4)
        straddles = (sample_inside.any(dim=2) & ~sample_inside.all(dim=2)).any(dim=0)
        if level == 0:
            straddles |= crossing[:, parent].any(dim=0)
        longest = torch.linalg.vector_norm(corners - corners.roll(1, dims=2), dim=-1).amax(dim=(0, 2))
        split = straddles & (longest > piece_size) & (level < _MAX_SPLIT_LEVELS)
        pieces_so_far = sum(int(p.numel()) for p in kept_parent + seam_parent)
        if pieces_so_far + int((~split).sum()) + 4 * int(split.sum()) > SELF_INTERSECTION_MAX_PIECES:
            split = torch.zeros_like(split)  # the budget: these pieces are the last
        final = ~split & ~sample_inside.all(dim=2).all(dim=0)
        # On the crossing (or inside in some pose): signed by the winding number, so kept last.
        seam = straddles | sample_inside.all(dim=2).any(dim=0)
        kept_parent.append(parent[final & ~seam])
        kept_weight.append(weight[final & ~seam])
        seam_parent.append(parent[final & seam])
        seam_weight.append(weight[final & seam])
        if not bool(split.any()):
            break
        parent = parent[split].repeat_interleave(4)
        weight = torch.einsum("scj,pjk->psck", split_weights, weight[split]).reshape(-1, 3, 3)
    parent, weight = torch.cat(kept_parent + seam_parent), torch.cat(kept_weight + seam_weight)
    seam_pieces = sum(int(p.numel()) for p in seam_parent)
    split = _SplitSurface(num_vertices, f, parent, weight)
    num_pieces = parent.numel()
    piece_faces = num_vertices + torch.arange(3 * num_pieces, device=device).view(num_pieces, 3)
    uncut = (~cut).nonzero().reshape(-1)
    bvh_faces = torch.cat([f[uncut], piece_faces]).to(torch.int32).contiguous()
    normal_faces = torch.cat([f, piece_faces])
    face_rows = torch.cat([uncut, num_faces + torch.arange(num_pieces, device=device)])
    counts = {"crossing_faces": int(crossing.any(dim=0).sum()), "inside_faces": int(inside.any(dim=0).sum()),
              "pieces": num_pieces, "seam_pieces": seam_pieces}
    return split.augment(vertices), bvh_faces, normal_faces, face_rows, split, counts, (points32, meshes)


class BodyMesh:
    """A posed body surface (one mesh, or B meshes of one topology) for hair-body contact.

    Validation runs once here, the BVHs are built at the first query; `update` refits them in
    place for a deforming body, and `crop` / `crop_for_hair` return a smaller BodyMesh with only
    the triangles hair can reach.
    Vertices [m]: (V, 3) or (B, V, 3) float32/float64 (one pose per batch item); faces (F, 3)
    int32/int64, counter-clockwise seen from outside. The meshes are float32 (`wp.Mesh`); a
    float64 copy of the vertices is kept for float64 queries. No gradient reaches the vertices.

    Args:
        vertices: (V, 3) or (B, V, 3) body vertices [m].
        faces: (F, 3) triangle vertex indices.
        require_watertight: check that every edge is shared by exactly two faces, consistently
            oriented, enclosing a positive volume (the sign of the distance needs it). Turn off
            only for meshes whose open borders no hair vertex can be nearest to.
        bvh: "sah" (default: the faster tree to query, built on the CPU) or "lbvh" (CUDA only,
            built on the GPU: 4x faster to build, for bodies built every training step). Crops
            keep their parent's.
        split_self_intersections: for a watertight mesh, find where it passes through itself
            (a posed arm into the chest) and query the boundary of the union of its parts
            instead: the faces inside another part left out, the faces that cross one cut into
            pieces (down to `SELF_INTERSECTION_PIECE_FRACTION` of its size) and the pieces inside left out
            (`self_intersections` says what was found). Without it a point inside one part whose
            closest face lies inside the other is signed "outside". Poses share the topology: a
            piece is left out only where it lies inside in every pose; `update` moves the pieces
            with the mesh but does not look for new crossings.
        split_poses: optional (K, V, 3) more poses of the same mesh [m] that the split also
            cuts where they pass through themselves (not held or queried): a body built once
            and moved by `update` through these poses (a motion's) knows every crossing they
            make. A walk's arm swing crosses the chest in poses its first frame does not, and a
            body split at the first frame alone signed hair pinched there wrongly (the physics
            flung it at 8 m/s; docs/physics.md, "Twenty-third session"). Ignored without
            `split_self_intersections`.

    Raises:
        ValueError: naming the argument, for bad shapes, dtypes, devices, NaN/Inf, empty or
            out-of-range faces, repeated indices in a face, and (when required) a mesh that is
            not watertight, not consistently oriented or oriented inward.
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, *, require_watertight: bool = True,
                 bvh: str = "sah", split_self_intersections: bool = True, split_poses: torch.Tensor | None = None):
        if bvh not in BVH_CONSTRUCTORS:
            raise ValueError(f"bvh: expected one of {list(BVH_CONSTRUCTORS)}, got {bvh!r}")
        check_tensor("vertices", vertices, allow_empty=False)
        # "lbvh" is built on the GPU only; the CPU's tree is the SAH one.
        self._bvh = "sah" if vertices.device.type != "cuda" else bvh
        if vertices.dim() not in (2, 3) or vertices.shape[-1] != 3:
            raise ValueError(f"vertices: expected shape (V, 3) or (B, V, 3), got {tuple(vertices.shape)}")
        if vertices.shape[-2] < 3:
            raise ValueError(f"vertices: expected at least 3 vertices, got {vertices.shape[-2]}")
        check_tensor(
            "faces", faces, shape=(None, 3), dtypes=INDEX_DTYPES, device=vertices.device, allow_empty=False
        )
        _warp.warp_device(vertices.device)
        _check_mesh(vertices, faces, require_watertight=require_watertight)
        batched = vertices.dim() == 3
        v = vertices.detach().reshape(-1, vertices.shape[-2], 3)
        faces = faces.to(torch.int32).contiguous()
        split = None
        if require_watertight and split_self_intersections:
            poses = v
            if split_poses is not None:
                check_tensor("split_poses", split_poses, shape=(None, v.shape[1], 3), device=vertices.device)
                poses = torch.cat([v, split_poses.detach().to(v.dtype)])
            with _warp.launch_scope(vertices.device):
                split = _split_self_intersections(poses, faces)
            if split is not None and poses is not v:
                # The topology covers every pose; the vertices and winding meshes kept are the body's own.
                held = v.shape[0]
                augmented, *rest, (points32, meshes) = split
                split = (augmented[:held], *rest, (points32[:held], meshes[:held]))
        if split is None:
            self._setup(v, faces, batched, bool(require_watertight), None, None, faces.long(), None)
            self._surface, self._self_intersections = None, {"crossing_faces": 0, "inside_faces": 0, "pieces": 0,
                                                             "seam_pieces": 0}
            self._face_parent = None
            self._setup_winding(None, self.num_faces)
        else:
            augmented, bvh_faces, normal_faces, face_rows, self._surface, self._self_intersections, winding = split
            self._setup(augmented, bvh_faces, batched, True, None, None, normal_faces, face_rows)
            # The uncut face each BVH face lies on (rows past the uncut faces are pieces).
            num_source = self._surface.faces.shape[0]
            pieces = (face_rows - num_source).clamp_min(0)
            self._face_parent = torch.where(face_rows < num_source, face_rows,
                                            self._surface.parent[pieces]).to(torch.int32).contiguous()
            self._surface.first_piece_face = self.num_faces - self._self_intersections["pieces"]
            kept = torch.zeros(num_source, dtype=torch.bool, device=faces.device)
            kept[self._face_parent.long()] = True
            self._surface.mark_pieces_touching(~kept)
            self._setup_winding(v, self.num_faces - self._self_intersections["seam_pieces"], winding)

    @classmethod
    def _from_parts(cls, vertices, faces, batched, watertight, vertex_map, face_map, normal_faces, face_rows,
                    bvh="sah", surface=None, self_intersections=None, face_parent=None):
        body = cls.__new__(cls)
        body._bvh = bvh
        body._surface, body._self_intersections, body._face_parent = surface, self_intersections, face_parent
        body._setup(vertices, faces, batched, watertight, vertex_map, face_map, normal_faces, face_rows)
        return body

    def _setup(self, vertices, faces, batched, watertight, vertex_map, face_map, normal_faces, face_rows):
        self._batched = batched
        self._watertight = watertight
        self._faces = faces
        # Indices into the mesh this one was cropped from (None: not cropped), composed over
        # repeated crops so `update` accepts the full body's vertices.
        self._vertex_map = vertex_map
        self._face_map = face_map
        # Faces the pseudo-normals are summed over: every face, or for a crop the one-ring of
        # its faces (which may reach vertices outside its BVH); `_face_rows` picks the BVH's
        # faces among them (None: the same faces).
        self._normal_faces = normal_faces
        self._face_rows = face_rows
        self._normal_sums = _NormalSums(normal_faces, vertices.shape[1])
        self._normals = {}  # dtype -> (vertex normals, edge normals), dropped by `update`
        self._points32 = vertices.to(torch.float32).contiguous().clone()
        self._points64 = None
        if vertices.dtype == torch.float64:
            self._points64 = vertices.contiguous().clone()
        self._dtype = vertices.dtype
        with _warp.launch_scope(vertices.device):
            self._faces_wp = _warp.as_warp(self._faces)
        # The BVHs are built at the first query (`_query_ready`): a body built only to be cropped
        # (`Scene.frames`, the stability runs) never builds its own.
        self._meshes, self._mesh_ids = None, None
        self._build_lock = threading.Lock()

    def prepare(self) -> BodyMesh:
        """Build now what construction leaves to the first query (the BVHs, the winding meshes,
        the pieces' sides): for a caller that times its queries and not the body's making.
        Returns the body.
        """
        self._query_ready()
        return self

    def _query_ready(self) -> None:
        """Build what queries read and construction leaves for later: the BVHs, the winding
        meshes of a self-intersecting body and the pieces' sides of the other part.
        Builds on the host (and reads a count back): called before a query, never inside a
        captured graph (`CapturedEnergy` warms up eagerly first). Under a lock: two threads
        querying a new body (the CPU runs contact terms side by side) build it once.
        """
        if self._meshes is not None and self._winding_meshes is not None and not self._seam_sides_stale:
            return
        with self._build_lock:
            self._build_for_queries()

    def _build_for_queries(self) -> None:
        device = self.device
        if self._meshes is None:
            with _warp.launch_scope(device):
                self._meshes = [
                    wp.Mesh(points=_warp.as_warp(self._points32[b], vec3=True), indices=self._faces_wp,
                            bvh_constructor=self._bvh, bvh_leaf_size=_BVH_LEAF_SIZE[self._bvh])
                    for b in range(self._points32.shape[0])
                ]
                self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64,
                                          device=_warp.warp_device(device))
        if self._source_points is not None and self._winding_meshes is None:
            with _warp.launch_scope(device):
                points = self._source_points.to(torch.float32).contiguous().clone()
                self._set_winding_meshes(points, [wp.Mesh(points=_warp.as_warp(points[b], vec3=True),
                                                          indices=self._winding_faces())
                                                  for b in range(points.shape[0])])
        if self._seam_sides_stale:
            self._setup_seam_sides()

    def _kernel_arrays(self, dtype: torch.dtype) -> list:
        """The body's arrays as the kernels take them, after the query points: mesh ids,
        vertices, faces, vertex and edge pseudo-normals (`kernels.hair_body_contact`).
        """
        self._query_ready()
        vertex_normals, edge_normals = self._normals_as(dtype)
        winding_ids = self._mesh_ids if self._winding_ids is None else self._winding_ids
        return [self._mesh_ids, _warp.as_warp(self._vertices_as(dtype), vec3=True), self._faces_wp,
                _warp.as_warp(vertex_normals, vec3=True), _warp.as_warp(edge_normals, vec3=True),
                winding_ids, self._first_piece, self._seam_sides_wp]

    def _setup_winding(self, source_points: torch.Tensor | None, first_piece: int, winding=None) -> None:
        """The closed meshes a self-intersecting body was built from, with winding numbers, for
        the sign near the pieces (`kernels.hair_body_contact.body_signed_distance`): faces from
        `first_piece` on are pieces. Without pieces the kernels never read them (the BVH's own
        meshes stand in). The meshes and the pieces' sides are built at the first query
        (`_query_ready`), or refit and recomputed at once by `update` once built.

        Args:
            source_points: (B, V, 3) the uncut mesh's vertices, or None without pieces.
            first_piece: index of the first piece among the BVH's faces.
            winding: None, or (float32 points (B, V, 3), their B `wp.Mesh`) already built on
                `source_points` (the self-intersection search's), taken as they are.
        """
        self._first_piece = int(first_piece)
        self._seam_sides_stale = True
        if source_points is None:
            self._source_points = None
            self._winding_points, self._winding_meshes, self._winding_ids = None, [], None
            return
        if getattr(self, "_winding_meshes", None) and self._winding_points.shape == source_points.shape:
            # `update`: moved in place and refit, so a captured graph keeps reading these meshes.
            with _warp.launch_scope(self.device):
                self._source_points.copy_(source_points.detach())
                self._winding_points.copy_(source_points.detach())
                for mesh in self._winding_meshes:
                    mesh.refit()
            self._setup_seam_sides()
            return
        self._source_points = source_points.detach().clone()
        self._winding_points, self._winding_meshes, self._winding_ids = None, None, None
        if winding is not None:
            self._set_winding_meshes(*winding)

    def _winding_faces(self) -> wp.array:
        """The uncut closed mesh's faces, as the winding meshes and the pieces' sides take them."""
        return _warp.as_warp(self._surface.faces.to(torch.int32).contiguous())

    def _set_winding_meshes(self, points: torch.Tensor, meshes: list) -> None:
        self._winding_points, self._winding_meshes = points, meshes
        self._winding_ids = wp.array([m.id for m in meshes], dtype=wp.uint64, device=_warp.warp_device(self.device))

    def _give_winding_meshes(self):
        """(points, meshes) of the winding meshes, handed over (a crop takes them rather than
        build the same again); this body builds its own again if it is ever queried. None if
        not built.
        """
        if not self._winding_meshes:
            return None
        winding = (self._winding_points, self._winding_meshes)
        self._winding_points, self._winding_meshes, self._winding_ids = None, None, None
        self._seam_sides_stale = True
        return winding

    def _setup_seam_sides(self) -> None:
        """Per pose, where the other part lies across each piece on a self-intersection's
        crossing (`kernels.hair_body_contact.seam_piece_crossings_kernel` and the rays after
        it): (B F, 4) float32, read from `first_piece` on; `_winding_unknown` marks those left to
        the winding number (`_winding_pass`). Reads nothing back from the device.
        """
        device = self.device
        seam = self.num_faces - self._first_piece
        rows = self.batch_size * self.num_faces if seam > 0 else 1
        if getattr(self, "_seam_sides", None) is None or self._seam_sides.shape[0] != rows:
            self._seam_sides = torch.zeros(rows, 4, dtype=torch.float32, device=device)
            self._seam_sides_wp = wp.from_torch(self._seam_sides, dtype=wp.vec4)
        self._seam_sides_stale = False
        self._winding_piece_count = 0
        if seam > 0:
            source_faces = self._winding_faces()
            faces = torch.arange(self.num_faces, device=device) if self._face_map is None else self._face_map
            piece = (faces - self._surface.first_piece_face).clamp_min(0)
            unknown = _warp.as_warp((self._surface.touches_inside[piece] & (faces >= self._surface.first_piece_face))
                                    .to(torch.int32).contiguous())
            # Per pose the offset out of the pieces (`_WINDING_OFFSET` times the pose's bounding-box
            # diagonal), kept on the device: an update reads nothing back for it.
            source = self._winding_points
            offsets = (torch.linalg.vector_norm(source.amax(1) - source.amin(1), dim=-1).double()
                       * _WINDING_OFFSET).float()
            samples, need, winding = self._seam_buffers(seam)
            wp_device = _warp.warp_device(device)
            lanes = 1 if device.type == "cpu" else 2  # rays a sample, one a thread (`seam_piece_rays_kernel`)
            with _warp.launch_scope(device):
                for b, mesh in enumerate(self._winding_meshes):
                    _warp.launch(
                        kernels.seam_piece_crossings_kernel, dim=seam,
                        inputs=[_warp.as_warp(self._points32[b], vec3=True), self._faces_wp,
                                _warp.as_warp(self._face_parent), self._first_piece, mesh.id,
                                _warp.as_warp(source[b], vec3=True), source_faces, _warp.as_warp(offsets[b:b + 1]),
                                b * self.num_faces, unknown],
                        outputs=[self._seam_sides_wp, samples, need], device=wp_device)
                    _warp.launch(kernels.seam_piece_rays_kernel, dim=(seam, kernels.SEAM_SAMPLES, lanes),
                                 inputs=[mesh.id, samples, need, lanes], outputs=[winding], device=wp_device)
                    if lanes == 2:
                        _warp.launch(kernels.seam_piece_third_rays_kernel, dim=(seam, kernels.SEAM_SAMPLES),
                                     inputs=[mesh.id, samples, need], outputs=[winding], device=wp_device)
                    _warp.launch(kernels.seam_piece_sides_from_rays_kernel, dim=seam,
                                 inputs=[self._first_piece, b * self.num_faces, need, winding],
                                 outputs=[self._seam_sides_wp], device=wp_device)
            self._winding_unknown = (self._seam_sides[:, 3] != 0).view(self.batch_size, self.num_faces).any(dim=0)
            # Counted when asked (`_winding_pieces`): on a GPU the count is a wait for the device
            # at every update, and the queries' winding pass runs wherever there are pieces.
            self._winding_piece_count = None

    def _seam_buffers(self, seam: int):
        """The pieces' sides' work buffers for `seam` pieces (kept while the count stays): the
        samples (seam, 4) vec3, their flags (seam, 4) int32 and their rays' winding numbers
        (seam, 4, 3) int32 (`kernels.hair_body_contact.seam_piece_crossings_kernel`).
        """
        buffers = getattr(self, "_seam_work", None)
        if buffers is None or buffers[1].shape[0] != seam:
            device = _warp.warp_device(self.device)
            samples = kernels.SEAM_SAMPLES
            buffers = (wp.zeros((seam, samples), dtype=wp.vec3, device=device),
                       wp.zeros((seam, samples), dtype=wp.int32, device=device),
                       wp.zeros((seam, samples, 3), dtype=wp.int32, device=device))
            self._seam_work = buffers
        return buffers

    @property
    def _winding_pieces(self) -> int:
        """Pieces signed by the winding number at query time in some pose (reads the device)."""
        self._query_ready()
        if self._winding_piece_count is None:
            self._winding_piece_count = int(self._winding_unknown.sum())
        return self._winding_piece_count

    @property
    def _winding_pass(self) -> bool:
        """Whether the queries run their winding pass (`signed_distance_winding_kernel`, ...): on
        the CPU where a piece is signed by the winding number (`_winding_pieces`), on a GPU
        wherever there are pieces (the pass's threads return at once where no query's closest face
        is such a piece): an update then reads nothing back from the device for it, and a graph
        captured before an update runs the pass an update may come to need.
        """
        self._query_ready()
        if self.num_faces == self._first_piece:
            return False
        return self._winding_pieces > 0 if self.device.type == "cpu" else True

    def _normals_as(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(B V, 3) vertex and (3 B F, 3) face-edge pseudo-normals in `dtype`, contiguous."""
        if dtype not in self._normals:
            self._normals[dtype] = self._compute_normals(dtype)
        return self._normals[dtype]

    def _compute_normals(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        vertex, edge = _pseudo_normals(
            self._vertices_as(dtype), self._normal_sums, self._face_rows
        )
        if self._surface is not None:
            self._surface.piece_pseudo_normals(
                self._source_points.to(dtype), self._vertex_map, self._face_map, vertex, edge
            )
        return vertex.reshape(-1, 3).contiguous(), edge.reshape(-1, 3).contiguous()

    @property
    def batch_size(self) -> int:
        """B, the number of posed meshes (1 for an unbatched body)."""
        return self._points32.shape[0]

    @property
    def batched(self) -> bool:
        """Whether the body was given as (B, V, 3)."""
        return self._batched

    @property
    def num_vertices(self) -> int:
        """V, vertices per mesh."""
        return self._points32.shape[1]

    @property
    def num_faces(self) -> int:
        """F, triangles per mesh."""
        return self._faces.shape[0]

    @property
    def device(self) -> torch.device:
        """The torch device the meshes live on."""
        return self._points32.device

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of the vertices the body was built from."""
        return self._dtype

    @property
    def watertight(self) -> bool:
        """Whether the mesh was checked closed (False for crops: they are open by design)."""
        return self._watertight

    @property
    def vertices(self) -> torch.Tensor:
        """A copy of the vertices [m], (V, 3) or (B, V, 3), in the dtype the body was built from."""
        v = self._points64 if self._points64 is not None else self._points32
        v = v.clone()
        return v if self._batched else v[0]

    @property
    def faces(self) -> torch.Tensor:
        """A copy of the faces, (F, 3) int32."""
        return self._faces.clone()

    @property
    def self_intersections(self) -> dict:
        """What `split_self_intersections` found: faces that cross another part
        ("crossing_faces") or lie inside one ("inside_faces") in some pose, the pieces kept
        of the cut faces ("pieces"), those of them on the crossing ("seam_pieces"), and of
        those the ones signed by the winding number at query time in some pose
        ("winding_pieces": more than one face of the other part crosses them, a corner lies on
        a face left out inside, or the winding number near a corner disagrees with the side
        found; the others know the other part's side across them); all 0 for a mesh that does
        not pass through itself. A crop reports its parent's counts and its own
        "winding_pieces". `vertices` and `faces` are the surface queried: the faces not cut,
        then the kept pieces (their corners appended to the vertices).
        """
        return dict(self._self_intersections, winding_pieces=self._winding_pieces)

    @property
    def source_triangle_count(self) -> int:
        """How many of the triangles the body was built from its queried faces lie on: a cut
        face's pieces count once, a crop counts what it kept (what "triangles within reach" means).
        """
        if self._face_parent is not None:
            return int(torch.unique(self._face_parent).numel())
        return self.num_faces

    @property
    def face_indices(self) -> torch.Tensor | None:
        """For a crop: (F,) int64 indices of its faces in the uncropped body; None otherwise."""
        return None if self._face_map is None else self._face_map.clone()

    def _vertices_as(self, dtype: torch.dtype) -> torch.Tensor:
        """(B, V, 3) contiguous vertices in `dtype` for the kernels' refinement step."""
        if dtype == torch.float32:
            return self._points32
        if self._points64 is None:
            self._points64 = self._points32.to(torch.float64)
        return self._points64

    def update(self, vertices: torch.Tensor) -> None:
        """Move the vertices (same topology) and refit the BVHs in place, no rebuild.

        Everything a query reads stays where it was (vertices, trees, pseudo-normals, the winding
        meshes and pieces' sides): a CUDA graph captured before (`CapturedEnergy`) follows the
        moved body.

        Args:
            vertices: new positions [m], shaped like the body's own vertices ((V, 3) or
                (B, V, 3)); a cropped body also accepts the uncropped body's vertices and
                picks its own.

        Raises:
            ValueError: naming `vertices` for a wrong shape, dtype, device or NaN/Inf.
        """
        check_tensor("vertices", vertices, device=self.device, allow_empty=False)
        count = vertices.shape[-2] if vertices.dim() >= 2 else -1
        want_dims = 3 if self._batched else 2
        if vertices.dim() != want_dims or vertices.shape[-1] != 3:
            want = "(B, V, 3)" if self._batched else "(V, 3)"
            raise ValueError(f"vertices: expected shape {want} like the body, got {tuple(vertices.shape)}")
        if self._batched and vertices.shape[0] != self.batch_size:
            raise ValueError(f"vertices: expected batch size {self.batch_size}, got {vertices.shape[0]}")
        v = vertices.detach().reshape(-1, count, 3)
        source = None  # the uncut mesh's vertices, for a body with pieces
        if self._surface is not None and count == self._surface.num_vertices != self.num_vertices:
            # The mesh the body was built from: the pieces of its cut faces follow it.
            source = v
            v = self._surface.augment(v.to(self._dtype))
            count = v.shape[1]
        elif self._surface is not None and self._vertex_map is None:
            source = v[:, : self._surface.num_vertices]  # the uncut mesh's vertices come first
        if count != self.num_vertices:
            if self._vertex_map is None or count <= int(self._vertex_map.max()):
                raise ValueError(f"vertices: expected {self.num_vertices} vertices per mesh, got {count}")
            v = v[:, self._vertex_map]
        with _warp.launch_scope(self.device):
            self._points32.copy_(v)
            if self._points64 is not None:
                self._points64.copy_(v)
            for mesh in self._meshes or ():
                mesh.refit()
        if self._surface is not None:
            # The winding numbers' meshes, rebuilt from the uncut mesh's vertices.
            if source is None:
                raise ValueError(
                    f"vertices: a crop of a body that passes through itself moves through the uncut body's "
                    f"{self._surface.num_vertices} vertices per mesh, got {vertices.shape[-2]}")
            self._setup_winding(source, self._first_piece)
        # The pseudo-normals recomputed into the same tensors: a graph captured before `update`
        # (`CapturedEnergy`) reads the moved body's (after the pieces' source points moved).
        with _warp.launch_scope(self.device):
            for dtype, (vertex, edge) in self._normals.items():
                new_vertex, new_edge = self._compute_normals(dtype)
                vertex.copy_(new_vertex)
                edge.copy_(new_edge)

    def crop(self, reach_centers: torch.Tensor, reach_radii: torch.Tensor, bvh: str | None = None) -> "BodyMesh":
        """A BodyMesh with only the triangles that meet the union of balls B(center_k, radius_k).

        The test is conservative (a triangle's bounding box against each ball): it may keep a
        few triangles outside the balls, never drops one inside. The crop shares the body's
        topology across the batch (a triangle kept for one pose is kept for all) and is an
        open mesh: signed distances on it are those of the full body for every point whose
        closest body point lies inside the balls (the pseudo-normal sign is local).
        This reads the kept-triangle count back to the host (a synchronisation on CUDA).

        Args:
            reach_centers: (K, 3), or (B, K, 3) per pose, ball centres [m].
            reach_radii: (K,) ball radii [m], >= 0.
            bvh: the crop's BVH ("sah" or "lbvh", see the class); None: the body's.

        Returns:
            The cropped BodyMesh (same batch size; `face_indices` maps its faces back).

        Raises:
            ValueError: naming the argument for bad inputs, or `reach_centers` when no triangle
                lies within reach.
        """
        if bvh is not None and bvh not in BVH_CONSTRUCTORS:
            raise ValueError(f"bvh: expected one of {list(BVH_CONSTRUCTORS)} or None, got {bvh!r}")
        bvh = self._bvh if bvh is None or self.device.type != "cuda" else bvh
        check_tensor("reach_centers", reach_centers, device=self.device, allow_empty=False)
        if reach_centers.dim() not in (2, 3) or reach_centers.shape[-1] != 3:
            raise ValueError(
                f"reach_centers: expected shape (K, 3) or (B, K, 3), got {tuple(reach_centers.shape)}"
            )
        if reach_centers.dim() == 3 and reach_centers.shape[0] not in (1, self.batch_size):
            raise ValueError(
                f"reach_centers: expected batch size {self.batch_size} like the body, "
                f"got {reach_centers.shape[0]}"
            )
        num_balls = reach_centers.shape[-2]
        check_tensor("reach_radii", reach_radii, shape=(num_balls,), device=self.device)
        if bool((reach_radii < 0).any()):
            raise ValueError("reach_radii: expected non-negative radii")
        batch = self.batch_size
        centers = reach_centers.detach().to(torch.float32).reshape(-1, num_balls, 3)
        centers_stride = 1 if centers.shape[0] > 1 else 0
        # Slack for float32 rounding of the box test: the crop must stay conservative.
        radii = reach_radii.detach().to(torch.float32) * (1.0 + 1.0e-5) + 1.0e-6
        bound_centers = centers.mean(dim=1)
        bound_radii = (torch.linalg.vector_norm(centers - bound_centers[:, None], dim=-1) + radii).amax(dim=1)
        bound_centers = bound_centers.expand(batch, 3).contiguous()
        bound_radii = (bound_radii * (1.0 + 1.0e-5)).expand(batch).contiguous()
        keep = torch.empty(batch * self.num_faces, dtype=torch.int32, device=self.device)
        with _warp.launch_scope(self.device):
            _warp.launch(
                kernels.crop_mark_faces_kernel,
                dim=batch * self.num_faces,
                inputs=[
                    _warp.as_warp(self._points32, vec3=True),
                    self._faces_wp,
                    self.num_faces,
                    self.num_vertices,
                    _warp.as_warp(centers.contiguous(), vec3=True),
                    _warp.as_warp(radii.contiguous()),
                    num_balls,
                    centers_stride,
                    _warp.as_warp(bound_centers, vec3=True),
                    _warp.as_warp(bound_radii),
                ],
                outputs=[_warp.as_warp(keep)],
                device=_warp.warp_device(self.device),
            )
        kept = keep.view(batch, self.num_faces).any(dim=0).nonzero().reshape(-1)
        if kept.numel() == 0:
            raise ValueError("reach_centers: no body triangle lies within reach of any ball: nothing to keep")
        # The BVH holds the kept faces; the pseudo-normals also need the faces around them (the
        # one-ring of every kept vertex, among this mesh's own normal faces), so the crop keeps
        # those faces and their vertices for the normals only.
        kept_rows = kept if self._face_rows is None else self._face_rows[kept]
        parent_normal_faces = self._normal_faces
        kept_mask = torch.zeros(self.num_vertices, dtype=torch.bool, device=self.device)
        kept_mask[parent_normal_faces[kept_rows].reshape(-1)] = True
        ring = kept_mask[parent_normal_faces].any(dim=1).nonzero().reshape(-1)
        used_mask = torch.zeros(self.num_vertices, dtype=torch.bool, device=self.device)
        used_mask[parent_normal_faces[ring].reshape(-1)] = True
        used = used_mask.nonzero().reshape(-1)
        remap = torch.full((self.num_vertices,), -1, dtype=torch.int64, device=self.device)
        remap[used] = torch.arange(used.numel(), device=self.device)
        new_faces = remap[self._faces[kept].long()].to(torch.int32).contiguous()
        normal_faces = remap[parent_normal_faces[ring]]
        ring_position = torch.full((parent_normal_faces.shape[0],), -1, dtype=torch.int64, device=self.device)
        ring_position[ring] = torch.arange(ring.numel(), device=self.device)
        face_rows = ring_position[kept_rows]
        source = self._points64 if self._points64 is not None else self._points32
        vertex_map = used if self._vertex_map is None else self._vertex_map[used]
        face_map = kept if self._face_map is None else self._face_map[kept]
        crop = BodyMesh._from_parts(
            source[:, used], new_faces, self._batched, False, vertex_map, face_map, normal_faces, face_rows, bvh,
            self._surface, self._self_intersections, None if self._face_parent is None else self._face_parent[kept]
        )
        # The pieces on the crossing stay last (the kept faces keep their order); the crop is open,
        # so the winding number is the uncut closed mesh's.
        first_piece = int((kept < self._first_piece).sum()) if self._surface is not None else crop.num_faces
        # A body not queried yet (one built to be cropped) hands its winding meshes over.
        crop._setup_winding(self._source_points, first_piece,
                            self._give_winding_meshes() if self._meshes is None else None)
        return crop

    def crop_for_hair(
        self, roots: torch.Tensor, strand_lengths: torch.Tensor, margin: float = 0.1, bvh: str | None = None
    ) -> "BodyMesh":
        """Crop to the triangles any vertex of the given strands can be nearest to.

        A hair vertex p at arc length <= L from its root r, with r on the body surface, has its
        closest body point c within |p - c| <= |p - r| <= L, hence |c - r| <= 2 L: keeping every
        triangle that meets B(r, 2 L (1 + margin)) changes no closest point, and (the sign being
        the local pseudo-normal) no signed distance, for any vertex of the strand. The margin
        absorbs roots slightly off the surface and strands stretched a little beyond L.

        Args:
            roots: (M, 3) or (B, M, 3) strand roots [m] (vertex 0 of each strand).
            strand_lengths: (M,) arc length of each strand [m] (e.g. its rest length).
            margin: relative safety margin on the radius, >= 0.
            bvh: the crop's BVH ("sah" or "lbvh"); None: the body's.

        Returns:
            The cropped BodyMesh.
        """
        check_tensor("strand_lengths", strand_lengths, device=self.device)
        margin = check_positive("margin", margin, allow_zero=True)
        return self.crop(roots, 2.0 * strand_lengths * (1.0 + margin), bvh=bvh)

    def __repr__(self) -> str:
        kind = "watertight" if self._watertight else "cropped/open"
        cut = self._self_intersections
        split = "" if not cut["pieces"] and not cut["inside_faces"] else (
            f", self-intersections: {cut['crossing_faces']} faces cut into {cut['pieces']} kept pieces "
            f"({cut['seam_pieces']} on the crossing, {self._winding_pieces} of them signed by the winding number), "
            f"{cut['inside_faces']} inside")
        return (
            f"BodyMesh(batch={self.batch_size}, vertices={self.num_vertices}, faces={self.num_faces}, "
            f"{kind}{split}, device={self.device})"
        )


def _check_body(body) -> BodyMesh:
    if not isinstance(body, BodyMesh):
        raise ValueError(f"body: expected a BodyMesh, got {type(body).__name__}")
    return body


def _body_stride(body: BodyMesh, batch: int) -> int:
    if body.batch_size == 1:
        return 0
    if body.batch_size != batch:
        raise ValueError(f"body: batch size {body.batch_size} does not match the hair's batch size {batch}")
    return 1


def _signed_distance_forward(points: torch.Tensor, body: BodyMesh, points_per_batch: int,
                             max_distance: float | None = None, points_per_line: int = 1, line_stride: int = 1):
    """Flat (P, 3) points -> (P,) signed distances and (P, 3) gradients (no autograd).

    With `max_distance`, the points are polylines of `points_per_line` points, `line_stride`
    apart in the flat order, and distances above max_distance are reported as max_distance with
    a zero gradient (capped queries, the side of a miss read along its polyline; see the
    kernels).
    """
    batch = points.shape[0] // points_per_batch
    stride = _body_stride(body, batch)
    distance = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    gradient = torch.empty_like(points)
    mesh = [_warp.as_warp(points, vec3=True)] + body._kernel_arrays(points.dtype)
    counts = [points_per_batch, body.num_vertices, body.num_faces, stride]
    zero_dist = _warp.scalar(_ZERO_DISTANCE[points.dtype], points.dtype)
    outputs = [_warp.as_warp(distance), _warp.as_warp(gradient, vec3=True)]
    device = _warp.warp_device(points.device)
    count = points.shape[0]
    winding = _warp.as_warp(torch.empty(count, dtype=torch.int32, device=points.device))
    side = _warp.as_warp(torch.empty(count, dtype=torch.int32, device=points.device))
    cap = _warp.scalar(kernels.FAR if max_distance is None else max_distance, points.dtype)

    def settle_winding_signs():
        # Points whose closest face is a piece on a self-intersection's crossing whose side of the
        # other part is not known, signed by the winding number in a launch of their own
        # (`kernels.hair_body_contact.winding_signed`).
        if body._winding_pass:
            _warp.launch(kernels.signed_distance_winding_kernel, dim=count,
                         inputs=mesh + counts + [cap, zero_dist, winding], outputs=outputs + [side], device=device)

    with _warp.launch_scope(points.device):
        if max_distance is None:
            _warp.launch(kernels.signed_distance_kernel, dim=count, inputs=mesh + counts + [zero_dist],
                         outputs=outputs + [winding], device=device)
            settle_winding_signs()
        else:
            inputs = mesh + [points_per_line, line_stride] + counts + [_warp.scalar(max_distance, points.dtype), zero_dist]
            hits = [side, _warp.as_warp(torch.empty(count, dtype=torch.float32, device=points.device))]
            _warp.launch(kernels.signed_distance_capped_kernel, dim=count, inputs=inputs,
                         outputs=outputs + hits + [winding], device=device)
            settle_winding_signs()  # before pass 2 reads the sides
            _warp.launch(kernels.signed_distance_far_kernel, dim=count, inputs=inputs + hits,
                         outputs=outputs, device=device)
    return distance, gradient


class _SignedDistance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, body, points_per_batch):
        distance, gradient = _signed_distance_forward(points, body, points_per_batch)
        ctx.save_for_backward(gradient)
        return distance

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_distance):
        (gradient,) = ctx.saved_tensors
        return grad_distance[:, None] * gradient, None, None


def point_mesh_signed_distance(
    points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor
) -> torch.Tensor:
    """Signed distance from points to a closed triangle mesh, negative inside.

    Exact closest point over the whole mesh (BVH query, no distance cap), sign by the
    angle-weighted pseudo-normal. For repeated queries against one body build a `BodyMesh`
    once and use `hair_body_signed_distance`.

    Args:
        points: (P, 3) float32/float64 query points [m].
        vertices: (V, 3) float32/float64 mesh vertices [m].
        faces: (F, 3) int32/int64 triangles, counter-clockwise seen from outside; the mesh
            must be watertight (every edge shared by exactly two faces).

    Returns:
        (P,) signed distances [m] in the dtype of `points`, differentiable w.r.t. `points`
        (gradient: the unit outward direction from the closest point; the face normal on the
        surface). In float64 the closest face is found in float32 and the distance refined in
        float64 on it (see `hairwarp.kernels.hair_body_contact`).

    Raises:
        ValueError: naming the argument for a wrong shape/dtype/device, NaN/Inf, empty input,
            out-of-range faces or a mesh that is not watertight / consistently outward.
    """
    check_tensor("points", points, shape=(None, 3), allow_empty=False)
    check_tensor("vertices", vertices, shape=(None, 3), device=points.device, allow_empty=False)
    check_tensor(
        "faces", faces, shape=(None, 3), dtypes=INDEX_DTYPES, device=points.device, allow_empty=False
    )
    body = BodyMesh(vertices, faces)
    return _SignedDistance.apply(points.contiguous(), body, points.shape[0])


def _check_hair(x: torch.Tensor, body: BodyMesh) -> torch.Tensor:
    check_tensor("x", x, device=body.device, allow_empty=False)
    if x.dim() not in (3, 4) or x.shape[-1] != 3:
        raise ValueError(f"x: expected shape (M, N, 3) or (B, M, N, 3), got {tuple(x.shape)}")
    return x


def hair_body_signed_distance(x: torch.Tensor, body: BodyMesh) -> torch.Tensor:
    """Signed distance of every hair vertex to the body [m], negative inside (for metrics).

    Args:
        x: (M, N, 3) or (B, M, N, 3) hair vertices [m], float32/float64.
        body: the posed body; batch size 1 (shared by every hair batch item) or B.

    Returns:
        (M, N) or (B, M, N) signed distances (all vertices, fixed ones included),
        differentiable w.r.t. `x`.

    Raises:
        ValueError: naming the argument for bad shapes, dtypes, devices, NaN/Inf or a body
            whose batch size matches neither 1 nor B.
    """
    _check_body(body)
    _check_hair(x, body)
    points = x.contiguous().reshape(-1, 3)
    per_batch = x.shape[-3] * x.shape[-2]
    return _SignedDistance.apply(points, body, per_batch).reshape(x.shape[:-1])


@torch.no_grad()
def hair_body_signed_distance_and_normal(
    x: torch.Tensor, body: BodyMesh, max_distance: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of every hair vertex to the body and the outward unit direction there.

    The direction is the distance's gradient: from the closest surface point towards the vertex
    (outside), the other way inside; the face normal on the surface. No autograd (features).

    Args:
        x: (M, N, 3) or (B, M, N, 3) hair vertices [m], float32/float64: polylines along N.
        body: the posed body; batch size 1 (shared by every hair batch item) or B.
        max_distance: optional [m] > 0: distances above it are reported as max_distance with a
            zero direction, and the queries are capped (faster: far outside points skip the
            unbounded query). Points inside are exact at any depth.

    Returns:
        (distance (..., M, N) [m], negative inside; direction (..., M, N, 3) unit vectors).

    Raises:
        ValueError: as `hair_body_signed_distance`, or for a max_distance that is not > 0.
    """
    _check_body(body)
    _check_hair(x, body)
    if max_distance is not None and not (float(max_distance) > 0.0 and math.isfinite(float(max_distance))):
        raise ValueError(f"max_distance: expected a finite number > 0 or None, got {max_distance}")
    if max_distance is None:
        points = x.contiguous().reshape(-1, 3)
        distance, direction = _signed_distance_forward(points, body, x.shape[-3] * x.shape[-2])
        return distance.reshape(x.shape[:-1]), direction.reshape(x.shape)
    # Capped: threads in (vertex, strand) order, so a warp queries neighbouring strands' points
    # (near each other, similar BVH walks) rather than one strand's, centimetres apart.
    m, n = x.shape[-3], x.shape[-2]
    points = x.transpose(-3, -2).contiguous()
    distance, direction = _signed_distance_forward(points.reshape(-1, 3), body, m * n, float(max_distance), n, m)
    return distance.reshape(points.shape[:-1]).transpose(-2, -1), direction.reshape(points.shape).transpose(-3, -2)


def hair_body_keep_out_push(
    x: torch.Tensor, body: BodyMesh, *, margin: float, push_below: float, push_above: float = -math.inf,
    max_distance: float, pushed_count: torch.Tensor | None = None, active_strands: torch.Tensor | None = None,
    pushed_strands: torch.Tensor | None = None, check: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hair vertices near or inside the body pushed to `margin` outside it (the body pass's push).

    Every moving vertex (index >= `hairwarp.config.NUM_FIXED_VERTICES`) whose signed distance d
    (the capped query of `hair_body_signed_distance_and_normal(x, body, max_distance)`) lies in
    (push_above, push_below) moves by (margin - d) along the outward direction; the other
    vertices are copied. A capped query (pass 1) and one kernel that settles the misses, pushes
    and counts (pass 2), with no host synchronisation: the count stays on the device.

    Args:
        x: (M, N, 3) or (B, M, N, 3) hair vertices [m], float32/float64.
        body: the posed body; batch size 1 (shared by every hair batch item) or B.
        margin: [m], finite, >= 0: where a pushed vertex lands (its signed distance then).
        push_below: [m], finite, <= max_distance: vertices with d below it (and above
            `push_above`) are pushed.
        push_above: [m] < push_below (-inf: every vertex below `push_below`, at any depth).
        max_distance: [m] > 0, finite: the query's cap (distances above it are not needed).
        pushed_count: optional (1,) int32 tensor on x's device that the number of pushed
            vertices is added to (a caller's counter, e.g. one slot per round); default a new
            zeroed one.
        active_strands: optional (M,) or (B, M) int32 flags like `x`'s strands: only the strands
            flagged non-zero are queried and pushed, the others copied (None: every strand).
        pushed_strands: optional (M,) or (B, M) int32 tensor, zeroed by the caller: each strand
            with a pushed vertex is set to 1 (the next round's `active_strands`).
        check: validate the arguments (False: a caller that validated them once; checking the
            values of a CUDA tensor waits for the GPU).

    Returns:
        (pushed positions like `x` [m] (no autograd), `pushed_count` (1,) int32 on the device).

    Raises:
        ValueError: naming the argument for a wrong shape, dtype or device, NaN/Inf, a body whose
            batch size matches neither 1 nor B, or numbers out of range.
    """
    if check:
        _check_body(body)
        _check_hair(x, body)
        numbers = {"margin": margin, "push_below": push_below, "max_distance": max_distance}
        for name, value in numbers.items():
            if not math.isfinite(float(value)):
                raise ValueError(f"{name}: expected a finite number, got {value}")
        if not float(margin) >= 0.0:
            raise ValueError(f"margin: expected a number >= 0, got {margin}")
        if not float(max_distance) > 0.0:
            raise ValueError(f"max_distance: expected a number > 0, got {max_distance}")
        if not float(push_below) <= float(max_distance):
            raise ValueError(f"push_below: expected a number <= max_distance ({max_distance}), got {push_below}")
        if not float(push_above) < float(push_below):
            raise ValueError(f"push_above: expected a number < push_below ({push_below}), got {push_above}")
        if pushed_count is not None:
            check_tensor("pushed_count", pushed_count, shape=(1,), dtypes=(torch.int32,), device=x.device)
            if not pushed_count.is_contiguous():
                raise ValueError("pushed_count: expected a contiguous tensor")
        for name, flags in (("active_strands", active_strands), ("pushed_strands", pushed_strands)):
            if flags is not None:
                check_tensor(name, flags, shape=tuple(x.shape[:-2]), dtypes=(torch.int32,), device=x.device)
                if not flags.is_contiguous():
                    raise ValueError(f"{name}: expected a contiguous tensor")
    if pushed_count is None:
        pushed_count = torch.zeros(1, dtype=torch.int32, device=x.device)
    hair = x.contiguous()
    pushed = torch.empty_like(hair)
    scalars = [_warp.scalar(margin, hair.dtype), _warp.scalar(push_above, hair.dtype),
               _warp.scalar(push_below, hair.dtype)]
    none = torch.empty(0, dtype=torch.int32, device=x.device)
    active = _warp.as_warp(none if active_strands is None else active_strands)
    flagged = _warp.as_warp(none if pushed_strands is None else pushed_strands)
    with _warp.launch_scope(hair.device):
        queried = _capped_hair_signed_distance(hair, body, float(max_distance), active)
        _warp.launch(kernels.hair_body_keep_out_push_kernel, dim=hair.numel() // 3, inputs=queried + scalars,
                     outputs=[_warp.as_warp(pushed, vec3=True), _warp.as_warp(pushed_count), flagged],
                     device=_warp.warp_device(hair.device))
    return pushed, pushed_count


def _capped_hair_signed_distance(x: torch.Tensor, body: BodyMesh, max_distance: float, active_strands) -> list:
    """Pass 1 of the capped query of contiguous (..., M, N, 3) hair in its own layout
    (`kernels.hair_capped_signed_distance_kernel`; `active_strands` a Warp int32 array of the
    strands to query, empty for all), and the winding pass where the body has pieces signed by
    it; inside `_warp.launch_scope`. Returns the arguments of a pass 2
    (`kernels.hair_body_keep_out_push_kernel`) up to its own: the hair, the body, the counts,
    the cap and pass 1's distance, gradient, side and hit distance (Warp views that keep their
    tensors alive).
    """
    m, n = x.shape[-3], x.shape[-2]
    count = x.numel() // 3
    device = _warp.warp_device(x.device)
    hair = _warp.as_warp(x, vec3=True)
    counts = [body.num_vertices, body.num_faces, _body_stride(body, count // (m * n))]
    scalars = [_warp.scalar(max_distance, x.dtype), _warp.scalar(_ZERO_DISTANCE[x.dtype], x.dtype)]
    per_vertex = x.shape[:-1]
    results = [_warp.as_warp(torch.empty(per_vertex, dtype=x.dtype, device=x.device)),
               _warp.as_warp(torch.empty_like(x), vec3=True),
               _warp.as_warp(torch.empty(per_vertex, dtype=torch.int32, device=x.device)),
               _warp.as_warp(torch.empty(per_vertex, dtype=torch.float32, device=x.device))]
    winding = _warp.as_warp(torch.empty(per_vertex, dtype=torch.int32, device=x.device))
    mesh = body._kernel_arrays(x.dtype)
    _warp.launch(kernels.hair_capped_signed_distance_kernel, dim=count,
                 inputs=[hair] + mesh + [m, n] + counts + scalars + [active_strands], outputs=results + [winding],
                 device=device)
    if body._winding_pass:
        # Points whose closest face is a piece on a self-intersection's crossing whose side of the
        # other part is not known, signed by the winding number before pass 2 reads the sides.
        _warp.launch(kernels.signed_distance_winding_kernel, dim=count,
                     inputs=[hair] + mesh + [m * n] + counts + scalars + [winding], outputs=results[:3],
                     device=device)
    return [hair] + mesh + [m, n] + counts + scalars + results


class HairBodyDistanceCache:
    """What the hair-body energy's last queries proved, per vertex, for a caller that evaluates
    the energy again and again against one body (an L-BFGS solve: `hairwarp.solvers.physics`).

    Each vertex keeps where it was last queried and a lower bound on its distance to the body
    there (the hit's |d|, or the query radius on a miss). The signed distance is 1-Lipschitz, so
    a vertex that has since moved less than that bound less its query radius would miss again:
    its query is skipped with the same outcome. Valid while the body stays where it was:
    `reset()` whenever the body moves (graph-safe: in place). Vertex strategy only (the CPU and
    wide CUDA launches); a cache of another size is reallocated (and starts empty).

    On the 2-core CPU the queries were 55 % of a physics iteration at 256 x 100
    (docs/physics.md, section 2).
    """

    def __init__(self):
        self.points = None
        self.distance = None

    def reset(self) -> None:
        """Forget every bound (the next evaluation queries every vertex)."""
        if self.distance is not None:
            self.distance.fill_(-math.inf)

    def arrays(self, count: int, device: torch.device):
        """(points (count, 3) float32, distance (count,) float32), allocated empty at a new size."""
        if self.distance is None or self.distance.numel() != count or self.distance.device != device:
            self.points = torch.zeros(count, 3, dtype=torch.float32, device=device)
            self.distance = torch.full((count,), -math.inf, dtype=torch.float32, device=device)
        return self.points, self.distance


def _energy_forward(x, body, xi, dhat, bp, weight, variant_id, strategy, cache=None):
    """(B, M, N, 3) hair -> (B,) energy, (B, M, N, 3) gradient, query counts (no autograd)."""
    batch, num_strands, num_vertices = x.shape[:3]
    stride = _body_stride(body, batch)
    gradient = torch.empty_like(x)
    device = _warp.warp_device(x.device)
    common = [_warp.as_warp(x, vec3=True)] + body._kernel_arrays(x.dtype) + [
        num_strands,
        num_vertices,
        body.num_vertices,
        body.num_faces,
        stride,
        _warp.scalar(xi, x.dtype),
        _warp.scalar(dhat, x.dtype),
        _warp.as_warp(join_fraction_tensor(bp, x)),
        _warp.scalar(weight, x.dtype),
        variant_id,
        _warp.scalar(_ZERO_DISTANCE[x.dtype], x.dtype),
    ]
    if strategy == "strand":
        count = batch * num_strands
    elif strategy == "vertex":
        count = batch * num_strands * num_vertices
    else:
        raise ValueError(f"strategy: expected 'strand' or 'vertex', got {strategy!r}")
    partial = torch.empty(count, dtype=x.dtype, device=x.device)
    queries = torch.empty(count, dtype=torch.int32, device=x.device)
    outputs = [_warp.as_warp(partial), _warp.as_warp(gradient, vec3=True), _warp.as_warp(queries)]
    with _warp.launch_scope(x.device):
        if strategy == "strand":
            _warp.launch(kernels.hair_body_energy_strand_kernel, dim=count, inputs=common, outputs=outputs,
                         device=device)
        else:
            # Capped queries, then the misses' sides along each strand (kernel docstrings).
            side = _warp.as_warp(torch.empty(count, dtype=torch.int32, device=x.device))
            hit_distance = _warp.as_warp(torch.empty(count, dtype=torch.float32, device=x.device))
            deep_flag = torch.empty(count, dtype=torch.int32, device=x.device)
            hit = _warp.as_warp(torch.empty(count, dtype=torch.int32, device=x.device))
            # Hits whose closest face is a crossing piece whose side of the other part is not known,
            # signed by the winding number in a launch of their own before pass 2 reads the sides (pass 2's deep
            # vertices are inside by the chain of misses).
            winding = _warp.as_warp(torch.empty(count, dtype=torch.int32, device=x.device))
            pieces = body._winding_pass
            if cache is None:
                cached = [0, _warp.as_warp(torch.zeros(1, 3, dtype=torch.float32, device=x.device), vec3=True),
                          _warp.as_warp(torch.zeros(1, dtype=torch.float32, device=x.device))]
            else:
                points, distance = cache.arrays(count, x.device)
                cached = [1, _warp.as_warp(points, vec3=True), _warp.as_warp(distance)]
            _warp.launch(kernels.hair_body_energy_vertex_kernel, dim=count, inputs=common + cached,
                         outputs=outputs + [side, hit_distance, winding], device=device)
            if pieces:
                _warp.launch(kernels.hair_body_energy_winding_kernel, dim=count, inputs=common + [winding],
                             outputs=[outputs[0], outputs[1], side], device=device)
            _warp.launch(kernels.hair_body_deep_flags_kernel, dim=count, inputs=[side, num_vertices],
                         outputs=[_warp.as_warp(deep_flag), hit], device=device)
            # The deep vertices listed in vertex order by a prefix sum (its last entry: the count).
            deep_end = torch.cumsum(deep_flag, 0, dtype=torch.int32)
            deep = [_warp.as_warp(deep_end[-1:]), _warp.as_warp(torch.empty(count, dtype=torch.int32, device=x.device)),
                    _warp.as_warp(torch.empty(count, dtype=torch.int32, device=x.device))]
            _warp.launch(kernels.hair_body_deep_list_kernel, dim=count,
                         inputs=[_warp.as_warp(deep_flag), _warp.as_warp(deep_end), hit], outputs=deep[1:],
                         device=device)
            _warp.launch(kernels.hair_body_energy_far_kernel, dim=count, inputs=common + [hit_distance] + deep,
                         outputs=outputs, device=device)
    # Per-strand (or per-vertex) partial sums, reduced per batch item here: no atomics.
    return row_sums(partial.view(batch, -1)), gradient, queries


class _HairBodyContactEnergy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, body, xi, dhat, bp, weight, variant_id, strategy, cache):
        energy, gradient, _ = _energy_forward(x, body, xi, dhat, bp, weight, variant_id, strategy, cache)
        ctx.save_for_backward(gradient)
        return energy

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_energy):
        (gradient,) = ctx.saved_tensors
        return grad_energy[:, None, None, None] * gradient, None, None, None, None, None, None, None, None


def hair_body_contact_energy(
    x: torch.Tensor,
    body: BodyMesh,
    xi: float,
    dhat: float,
    bp: float | torch.Tensor,
    weight: float = 1.0,
    variant: str = "quadratic",
    distance_cache: HairBodyDistanceCache | None = None,
) -> torch.Tensor:
    """Hair-body contact energy, HairFormer Eq. 12 with d = signed distance to the body.

    E_b = weight * sum over strands s and moving vertices v >= 2 of B(d(p_{s,v})): a sum over
    vertices (not a mean), per batch item; the fixed vertices 0 and 1 contribute nothing and
    get zero gradient. B is the barrier of `hairwarp.ops.barrier` (zero for d >= xi + dhat).
    Vertices inside the body get the extrapolated barrier at any depth. Two kernel passes write
    the energy and gradient per vertex (`kernels.hair_body_contact`); torch sums the partial
    energies per batch item (no atomics).

    Args:
        x: (M, N, 3) or (B, M, N, 3) hair vertices [m], float32/float64.
        body: the posed body (`BodyMesh`, full or cropped with `crop_for_hair`); batch size 1
            (shared by every hair batch item) or B.
        xi: hard barrier [m] (1 mm for hair-body contact in the paper).
        dhat: soft barrier width [m] (1.5 mm in the paper).
        bp: join fraction in (0, 1) (annealed 0.9 -> 0.01 in the paper): a float, or a
            one-element tensor the kernels read at launch (a captured graph follows its value).
        weight: lambda_hb, the weight per vertex [J].
        variant: "quadratic" (default), "monotone" or "paper" (Eq. 12-14 literally), see `barrier`.
        distance_cache: a `HairBodyDistanceCache` the caller keeps across evaluations against
            the same body (reset when the body moves): queries it proves misses are skipped,
            the energy and gradient unchanged.

    Returns:
        (B,) energies [J] for batched `x`, a 0-dim tensor for unbatched `x`, in the dtype of
        `x`, differentiable w.r.t. `x` (hand-written gradient computed in the same pass).

    Raises:
        ValueError: naming the argument for bad shapes, dtypes, devices, NaN/Inf, bad barrier
            parameters or a body whose batch size matches neither 1 nor B.
    """
    _check_body(body)
    _check_hair(x, body)
    xi, dhat, bp = check_barrier_parameters(xi, dhat, bp)
    weight = float(weight)
    if weight != weight or abs(weight) == float("inf"):
        raise ValueError(f"weight: expected a finite number, got {weight}")
    variant_id = barrier_variant_id(variant)
    batched = x.dim() == 4
    xb = (x if batched else x.unsqueeze(0)).contiguous()
    strategy = _strategy(x.device, xb.shape[0] * xb.shape[1])
    energy = _HairBodyContactEnergy.apply(xb, body, xi, dhat, bp, weight, variant_id, strategy, distance_cache)
    return energy if batched else energy[0]
