"""Torch bridge of hair-body contact (HairFormer Eq. 12 with d = signed distance to the body);
device code in `hairwarp.kernels.hair_body_contact`.

`BodyMesh` owns the posed body's `wp.Mesh`(es): validated once, refitted in place when the body
deforms (`update`), and cropped to the triangles the hair can reach (`crop`, `crop_for_hair`).
`hair_body_contact_energy` is the contact term, `hair_body_signed_distance` the per-vertex
distance for metrics, `point_mesh_signed_distance` the one-shot signed distance of points.

Sign convention: d < 0 inside the body, by the angle-weighted pseudo-normal of the closest
feature (face, edge or vertex; see the kernel module for why, and why not the winding number).
The edge and vertex pseudo-normals are computed here, on the device, from the mesh's adjacency
(found once when the body is built) and recomputed when the body moves (`update`); a crop keeps
the one-ring of its faces (extra vertices and "normal faces" outside its BVH) so its normals
are those of the full body. Meshes must be watertight, edge-manifold and
consistently oriented with outward normals (counter-clockwise seen from outside).
Gradients flow to the hair/points only: `wp.Mesh` queries give none to the body vertices.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from hairwarp import _warp
from hairwarp._validate import check_positive, check_tensor
from hairwarp.kernels import hair_body_contact as kernels
from hairwarp.ops.barrier import barrier_variant_id, check_barrier_parameters

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


def _pseudo_normals(points: torch.Tensor, faces: torch.Tensor, edge_inverse: torch.Tensor, num_edges: int,
                    face_rows: torch.Tensor | None):
    """Vertex and edge pseudo-normals (Baerentzen & Aanaes 2005) of B posed meshes.

    Args:
        points: (B, V, 3) vertices.
        faces: (R, 3) int64 faces the normals are summed over (a crop's one-ring).
        edge_inverse: (3 R,) undirected edge id of each face edge (`_edge_inverse`).
        num_edges: number of distinct edges.
        face_rows: (F,) rows of `faces` that the BVH holds (None: all of them).

    Returns:
        vertex normals (B, V, 3) (angle-weighted sums of unit face normals) and edge normals
        (B, F, 3, 3) (per face edge, the sum of the unit normals of the faces sharing it); not
        normalised: only their direction's side matters. Zero-area faces contribute nothing.
    """
    batch, count = points.shape[:2]
    a, b, c = points[:, faces[:, 0]], points[:, faces[:, 1]], points[:, faces[:, 2]]
    normal = torch.cross(b - a, c - a, dim=-1)
    length = torch.linalg.vector_norm(normal, dim=-1, keepdim=True)
    unit = torch.where(length > 0, normal / length.clamp_min(torch.finfo(points.dtype).tiny), 0.0)

    def angle(e0, e1):
        return torch.atan2(torch.linalg.vector_norm(torch.cross(e0, e1, dim=-1), dim=-1), (e0 * e1).sum(-1))

    corner = torch.stack([angle(b - a, c - a), angle(c - b, a - b), angle(a - c, b - c)], dim=-1)
    weighted = (corner[..., None] * unit[:, :, None, :]).reshape(batch, -1, 3)
    vertex = torch.zeros(batch, count, 3, dtype=points.dtype, device=points.device)
    vertex.index_add_(1, faces.reshape(-1), weighted)
    per_edge = torch.zeros(batch, num_edges, 3, dtype=points.dtype, device=points.device)
    per_edge.index_add_(1, edge_inverse, unit[:, :, None, :].expand(-1, -1, 3, -1).reshape(batch, -1, 3))
    inverse = edge_inverse.view(-1, 3)
    if face_rows is not None:
        inverse = inverse[face_rows]
    return vertex, per_edge[:, inverse]


class BodyMesh:
    """A posed body surface (one mesh, or B meshes of one topology) for hair-body contact.

    Validation runs once here; `update` refits the BVHs in place for a deforming body, and
    `crop` / `crop_for_hair` return a smaller BodyMesh with only the triangles hair can reach.
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

    Raises:
        ValueError: naming the argument, for bad shapes, dtypes, devices, NaN/Inf, empty or
            out-of-range faces, repeated indices in a face, and (when required) a mesh that is
            not watertight, not consistently oriented or oriented inward.
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, *, require_watertight: bool = True,
                 bvh: str = "sah"):
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
        self._setup(v, faces, batched, bool(require_watertight), None, None, faces.long(), None)

    @classmethod
    def _from_parts(cls, vertices, faces, batched, watertight, vertex_map, face_map, normal_faces, face_rows,
                    bvh="sah"):
        body = cls.__new__(cls)
        body._bvh = bvh
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
        self._edge_inverse, self._num_edges = _edge_inverse(normal_faces)
        self._normals = {}  # dtype -> (vertex normals, edge normals), dropped by `update`
        self._points32 = vertices.to(torch.float32).contiguous().clone()
        self._points64 = None
        if vertices.dtype == torch.float64:
            self._points64 = vertices.contiguous().clone()
        self._dtype = vertices.dtype
        device = vertices.device
        with _warp.launch_scope(device):
            self._faces_wp = _warp.as_warp(self._faces)
            self._meshes = [
                wp.Mesh(points=_warp.as_warp(self._points32[b], vec3=True), indices=self._faces_wp,
                        bvh_constructor=self._bvh, bvh_leaf_size=_BVH_LEAF_SIZE[self._bvh])
                for b in range(self._points32.shape[0])
            ]
            ids = [m.id for m in self._meshes]
            self._mesh_ids = wp.array(ids, dtype=wp.uint64, device=_warp.warp_device(device))

    def _kernel_arrays(self, dtype: torch.dtype) -> list:
        """The body's arrays as the kernels take them, after the query points: mesh ids,
        vertices, faces, vertex and edge pseudo-normals (`kernels.hair_body_contact`).
        """
        vertex_normals, edge_normals = self._normals_as(dtype)
        return [self._mesh_ids, _warp.as_warp(self._vertices_as(dtype), vec3=True), self._faces_wp,
                _warp.as_warp(vertex_normals, vec3=True), _warp.as_warp(edge_normals, vec3=True)]

    def _normals_as(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(B V, 3) vertex and (3 B F, 3) face-edge pseudo-normals in `dtype`, contiguous."""
        if dtype not in self._normals:
            vertex, edge = _pseudo_normals(
                self._vertices_as(dtype), self._normal_faces, self._edge_inverse, self._num_edges, self._face_rows
            )
            self._normals[dtype] = (vertex.reshape(-1, 3).contiguous(), edge.reshape(-1, 3).contiguous())
        return self._normals[dtype]

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
        if count != self.num_vertices:
            if self._vertex_map is None or count <= int(self._vertex_map.max()):
                raise ValueError(f"vertices: expected {self.num_vertices} vertices per mesh, got {count}")
            v = v[:, self._vertex_map]
        with _warp.launch_scope(self.device):
            self._points32.copy_(v)
            if self._points64 is not None:
                self._points64.copy_(v)
            for mesh in self._meshes:
                mesh.refit()
        self._normals = {}

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
        return BodyMesh._from_parts(
            source[:, used], new_faces, self._batched, False, vertex_map, face_map, normal_faces, face_rows, bvh
        )

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
        return (
            f"BodyMesh(batch={self.batch_size}, vertices={self.num_vertices}, faces={self.num_faces}, "
            f"{kind}, device={self.device})"
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
    with _warp.launch_scope(points.device):
        if max_distance is None:
            _warp.launch(kernels.signed_distance_kernel, dim=points.shape[0], inputs=mesh + counts + [zero_dist],
                         outputs=outputs, device=device)
        else:
            inputs = mesh + [points_per_line, line_stride] + counts + [_warp.scalar(max_distance, points.dtype), zero_dist]
            hits = [_warp.as_warp(torch.empty(points.shape[0], dtype=torch.int32, device=points.device)),
                    _warp.as_warp(torch.empty(points.shape[0], dtype=torch.float32, device=points.device))]
            _warp.launch(kernels.signed_distance_capped_kernel, dim=points.shape[0], inputs=inputs,
                         outputs=outputs + hits, device=device)
            _warp.launch(kernels.signed_distance_far_kernel, dim=points.shape[0], inputs=inputs + hits,
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


def _energy_forward(x, body, xi, dhat, bp, weight, variant_id, strategy):
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
        _warp.scalar(bp, x.dtype),
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
            _warp.launch(kernels.hair_body_energy_vertex_kernel, dim=count, inputs=common,
                         outputs=outputs + [side, hit_distance], device=device)
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
    return partial.view(batch, -1).sum(dim=1), gradient, queries


class _HairBodyContactEnergy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, body, xi, dhat, bp, weight, variant_id, strategy):
        energy, gradient, _ = _energy_forward(x, body, xi, dhat, bp, weight, variant_id, strategy)
        ctx.save_for_backward(gradient)
        return energy

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_energy):
        (gradient,) = ctx.saved_tensors
        return grad_energy[:, None, None, None] * gradient, None, None, None, None, None, None, None


def hair_body_contact_energy(
    x: torch.Tensor,
    body: BodyMesh,
    xi: float,
    dhat: float,
    bp: float,
    weight: float = 1.0,
    variant: str = "quadratic",
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
        bp: join fraction in (0, 1) (annealed 0.9 -> 0.01 in the paper).
        weight: lambda_hb, the weight per vertex [J].
        variant: "quadratic" (default), "monotone" or "paper" (Eq. 12-14 literally), see `barrier`.

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
    energy = _HairBodyContactEnergy.apply(xb, body, xi, dhat, bp, weight, variant_id, strategy)
    return energy if batched else energy[0]
