"""Hair-body contact: signed distance to the posed body mesh and its barrier energy (Eq. 12).

The contact term of HairFormer Eq. 12 takes d = the signed distance from a hair vertex to the
body surface (negative inside), with xi = 1 mm and dhat = 1.5 mm for hair-body contact.

Sign. By the angle-weighted pseudo-normal of the closest feature (Baerentzen & Aanaes 2005):
the float32 BVH query (`wp.mesh_query_point_no_sign`) finds the closest face, the closest point
on it is recomputed in the caller's precision, its region (face interior, one of the three
edges, one of the three vertices) read from the exact zeros of its barycentrics, and the sign
is that of dot(p - closest, n) with n the face normal, the edge's pseudo-normal (the sum of the
two unit normals of the faces that share it) or the vertex's angle-weighted normal. The edge
and vertex pseudo-normals are computed on the host side from the mesh's adjacency
(`hairwarp.ops.hair_body_contact`) and passed in. This holds for *any* closest point, so a tie
between faces (the medial axis: a capsule's axis, a slab's mid-plane, a sphere's centre, where
faces from opposite sides are equally close) cannot change the sign: whichever tied face the
query keeps, its own feature signs the point correctly.
`wp.mesh_query_point_sign_normal` (used before) pools the normals of *every* face within
`epsilon` of the closest distance into one vector; on the medial axis that pools opposite sides,
the sum cancels and the sign is a coin toss (31 of 300 points on a capsule's axis and 22 of 400
on a slab's mid-plane were called outside). The winding number and ray parity are global (a
solid-angle sum or ray votes over the whole mesh): on a mesh cropped to the triangles hair can
reach (open by design) they break. The feature pseudo-normal is local: it needs only the
closest face's neighbours (a crop keeps its one-ring for the normals), is exact on ties, and
costs one dot product.

Precision. `wp.Mesh` is float32: the query finds the closest face in float32, then the closest
point on that face is recomputed in the caller's precision (float32 or float64) by the
point-triangle functions of `hairwarp.kernels.distances`. In float64 the distance is exact
on the face the float32 query picked;
where two faces tie within float32 rounding (near an edge or a vertex) it can exceed the true
distance by ~1e-7 of the coordinates, and the sign of points within that of the surface is
float32's.

Reach. The barrier is zero for d >= xi + dhat ("the reach"). A vertex outside the body and
farther than the reach needs no exact distance; a vertex inside needs one at any depth (the
extrapolated barrier keeps pushing it out), so a query capped at the reach cannot tell a far
outside vertex from a deep inside one. The per-strand kernel walks each strand from the root
and uses that the signed distance is 1-Lipschitz: after an exact query at an "anchor" vertex a
with |d(a)| = D, the open ball B(a, D) holds no surface, so a later vertex p with
r = |p - a| < D is on a's side with |d(p)| >= D - r, and in any case |d(p)| <= D + r. Vertices
proven outside and beyond the reach skip the query; the others make an exact query capped at
D + r (the cap prunes the BVH walk), which becomes the next anchor. Every vertex's result equals
that of an unbounded query. The per-vertex kernels (the GPU's choice: one thread per vertex
fills it) use the same rule link by link: pass 1 queries each vertex within max(reach, the
length of the segment that ends at it); a miss proves the vertex farther from the surface than
that segment is long, hence on its predecessor's side. Pass 2 gives each missed vertex the side
of the last vertex before it whose query hit: outside, it is beyond the reach and costs nothing
more; inside, it is listed, and one query per listed vertex, capped at that hit's |d| plus the
way to it, gives its depth. An
unbounded query from far outside walks most of the BVH, and most hair is far outside: this is
what the caps save (on an H100, 1024 x 100 hair at batch 32: 14.3 -> 7.7 ms with the inside
queries unbounded; docs/contact.md).
"""

from typing import Any

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.kernels.barrier import barrier_energy, barrier_gradient
from hairwarp.kernels.distances import point_triangle_closest_barycentric, point_triangle_distance_gradient_at

# Gradients are hand-written beside each energy: no generated adjoints to compile.
wp.set_module_options({"enable_backward": False})

# max_dist of an unbounded query [m]: finite so that (max_dist + eps)^2 stays finite in float32.
FAR = wp.constant(1.0e18)
# The body pass moves the vertices from this index on (`hair_body_keep_out_push_kernel`).
FIRST_MOVING_VERTEX = wp.constant(NUM_FIXED_VERTICES)


@wp.func
def feature_pseudo_normal(
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_offset: int,
    edge_offset: int,
    face: int,
    a: Any,
    b: Any,
    c: Any,
    u: Any,
    v: Any,
    w: Any,
):
    """Pseudo-normal of the feature of face `face` (corners a, b, c) that holds the closest
    point u a + v b + w c: a vertex (two barycentrics exactly zero), an edge (one zero) or the
    face's interior. `point_triangle_closest_barycentric` writes exact zeros on the boundary
    regions; an interior point within rounding of an edge keeps the face normal, which is then
    parallel to p - closest and signs it as well.

    Edge k of a face joins its corners k and (k + 1) % 3: edge 0 = ab, 1 = bc, 2 = ca.
    """
    zero = u * type(u)(0.0)
    if u == zero and v == zero:
        return vertex_normals[vertex_offset + faces[3 * face + 2]]
    if v == zero and w == zero:
        return vertex_normals[vertex_offset + faces[3 * face + 0]]
    if w == zero and u == zero:
        return vertex_normals[vertex_offset + faces[3 * face + 1]]
    if w == zero:
        return edge_normals[edge_offset + 3 * face + 0]
    if u == zero:
        return edge_normals[edge_offset + 3 * face + 1]
    if v == zero:
        return edge_normals[edge_offset + 3 * face + 2]
    return wp.cross(b - a, c - a)


@wp.func
def seam_inside_other_part(sides: wp.vec4, u: Any, v: Any, w: Any):
    """True where the point u a + v b + w c of a piece on a self-intersection's crossing lies
    strictly inside the other part: `sides` holds the signed distances of the piece's corners
    a, b, c to the one face of the other part that crosses it (outward positive; its plane is
    the other part's surface across the whole piece, so the side is affine in the barycentrics),
    or -1 / +1 at every corner for a piece wholly inside / outside the other parts.
    """
    s = u * type(u)(sides[0]) + v * type(u)(sides[1]) + w * type(u)(sides[2])
    return s < u * type(u)(0.0)


@wp.func
def body_signed_distance_face(
    mesh: wp.uint64,
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    vertex_offset: int,
    edge_offset: int,
    p: Any,
    max_dist: float,
    zero_dist: Any,
):
    """Signed distance d [m] from `p` to the mesh (negative inside), dd/dp and the closest face.

    Returns (found, d, gradient, face), face the mesh-local index of the closest face (-1 when
    none is found): found = 0 when no face lies strictly within `max_dist`
    (then d = 0, gradient = 0); 2 when the closest face is a piece on a self-intersection's
    crossing whose side of the other part is not known (`seam_sides`), whose sign is the winding
    number's (`winding_signed`; a pass of its own, `hair_body_energy_winding_kernel` and
    `signed_distance_winding_kernel`, so that the winding query's code stays out of the hot
    kernels); else 1. On the other pieces of the crossing the side of the other part is read
    from `seam_sides` (`seam_inside_other_part`). The gradient is the unit vector sign * (p - closest), the
    outward direction; within `zero_dist` of the surface, where that direction is rounding
    noise, it is the closest face's unit normal (the exact gradient on a face's interior).
    The sign is that of the closest feature's pseudo-normal (see the module docstring).

    Args:
        mesh: `wp.Mesh` id (float32 points).
        vertices: the mesh vertices in the caller's precision (vec3 or vec3d), for refinement.
        faces: flat triangle indices (3 F).
        vertex_normals: angle-weighted vertex pseudo-normals, like `vertices` (not unit).
        edge_normals: edge pseudo-normals per face edge, (3 F per mesh), like `vertices`.
        first_piece: faces from this index on are pieces on a self-intersection's crossing
            (see the section at the end of this module): the closest point on one may lie
            just inside the other part (`num faces` when there are none).
        seam_sides: per face of each mesh (B F), for the pieces on the crossing, the other
            part's side (`seam_piece_crossings_kernel`); not read below `first_piece`.
        vertex_offset: index of this mesh's first vertex in `vertices` (batched bodies).
        edge_offset: index of this mesh's first face edge in `edge_normals` (3 F per mesh).
        p: query point (vec3 or vec3d).
        max_dist: query radius [m].
        zero_dist: distance below which p counts as on the surface [m].
    """
    zero = zero_dist * type(zero_dist)(0.0)
    p32 = wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
    q = wp.mesh_query_point_no_sign(mesh, p32, max_dist)
    if not q.result:
        return 0, zero, p * zero, -1
    a = vertices[vertex_offset + faces[3 * q.face + 0]]
    b = vertices[vertex_offset + faces[3 * q.face + 1]]
    c = vertices[vertex_offset + faces[3 * q.face + 2]]
    u, v, w, dist2 = point_triangle_closest_barycentric(p, a, b, c)
    pseudo = feature_pseudo_normal(
        vertex_normals, edge_normals, faces, vertex_offset, edge_offset, q.face, a, b, c, u, v, w
    )
    offset = p - (u * a + v * b + w * c)
    sign = type(zero_dist)(-1.0)
    if wp.dot(offset, pseudo) > zero:
        sign = type(zero_dist)(1.0)
    found = 1
    if q.face >= first_piece:
        # A piece on the crossing: an "outside" verdict is wrong where the closest point lies
        # strictly inside the other part (the piece juts into it); "inside" is never wrong (a
        # point outside the union has its closest point on the union's boundary).
        sides = seam_sides[edge_offset // 3 + q.face]
        if sides[3] != 0.0:
            found = 2
        elif sign > zero and seam_inside_other_part(sides, u, v, w):
            sign = -sign
    if dist2 > zero_dist * zero_dist:
        # n: unit (p - closest), exactly the face normal's direction in the face region.
        dist, n, grad_a, grad_b, grad_c = point_triangle_distance_gradient_at(p, a, b, c, u, v, w)
        return found, sign * dist, sign * n, q.face
    # On the surface: the outward face normal (whatever side rounding put p on).
    normal = wp.cross(b - a, c - a)
    return found, sign * wp.sqrt(dist2), normal / wp.length(normal), q.face


@wp.func
def body_signed_distance(
    mesh: wp.uint64,
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    vertex_offset: int,
    edge_offset: int,
    p: Any,
    max_dist: float,
    zero_dist: Any,
):
    """`body_signed_distance_face` without the face: (found, d, gradient)."""
    found, d, g, face = body_signed_distance_face(
        mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset, p,
        max_dist, zero_dist,
    )
    return found, d, g


# Past a ray's hit [m] before the next query: the same face is not hit twice.
RAY_STEP = wp.constant(1.0e-6)
# The rays' directions (unit): skew, so that no face of a mesh built on axes lies along one.
RAY_DIRECTION_0 = wp.constant(wp.vec3(0.53772548, 0.72083416, 0.43732073))
RAY_DIRECTION_1 = wp.constant(wp.vec3(-0.64210189, 0.31190092, 0.70030206))
RAY_DIRECTION_2 = wp.constant(wp.vec3(0.29129140, -0.81267600, 0.50468509))


@wp.func
def ray_winding_number(mesh: wp.uint64, p: wp.vec3, direction: wp.vec3):
    """The winding number of a closed mesh at p by one ray to infinity: the faces it leaves
    through (hit from behind) minus those it enters through; 0 outside, 1 inside one layer, 2
    where two parts overlap. A walk of ray queries, each a BVH descent: far cheaper than the
    fast winding number near the surface, where its near field sums many triangles.
    """
    start = p
    winding = int(0)
    for k in range(64):
        q = wp.mesh_query_ray(mesh, start, direction, wp.float32(FAR))
        if not q.result:
            break
        if q.sign > 0.0:
            winding -= 1
        else:
            winding += 1
        start = start + direction * (q.t + RAY_STEP)
    return winding


@wp.func
def ray_inside(mesh: wp.uint64, p: wp.vec3):
    """True inside the union of a closed mesh's parts (winding number >= 1), by the majority of
    three rays in directions that no face of a mesh built on axes lies along (a ray through a
    silhouette edge miscounts; two rays rarely both do).
    """
    votes = int(0)
    if ray_winding_number(mesh, p, RAY_DIRECTION_0) > 0:
        votes += 1
    if ray_winding_number(mesh, p, RAY_DIRECTION_1) > 0:
        votes += 1
    if votes == 1 and ray_winding_number(mesh, p, RAY_DIRECTION_2) > 0:
        votes += 1
    return votes >= 2


@wp.func
def winding_signed(winding_mesh: wp.uint64, p: Any, found: int, d: Any, g: Any, zero_dist: Any):
    """(d, g) of `body_signed_distance` with the sign of the closed mesh's winding number
    (`ray_inside`) where found == 2 (a piece on a self-intersection's crossing whose side of the
    other part is not known: its pseudo-normal can face into the other part); unchanged
    otherwise. On the surface (|d| <= zero_dist) the gradient, the face normal, keeps its
    direction.
    """
    if found != 2:
        return d, g
    p32 = wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
    zero = d * type(d)(0.0)
    if ray_inside(winding_mesh, p32) == (d < zero):
        return d, g
    if wp.abs(d) <= zero_dist:
        return -d, g
    return -d, -g


@wp.kernel
def signed_distance_kernel(
    # In:
    points: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    points_per_batch: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    zero_dist: Any,
    # Out:
    distance_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    winding_out: wp.array(dtype=wp.int32),
):
    """Exact signed distance and its gradient per point (unbounded query); `winding_out` 1 where
    the sign is the winding number's (`signed_distance_winding_kernel` settles it).
    """
    i = wp.tid()
    body = (i // points_per_batch) * body_batch_stride
    found, d, g = body_signed_distance(
        mesh_ids[body],
        body_vertices,
        faces,
        vertex_normals,
        edge_normals,
        first_piece,
        seam_sides,
        body * body_vertex_count,
        body * body_face_count * 3,
        points[i],
        wp.float32(FAR),
        zero_dist,
    )
    if found == 0:
        # Only a mesh whose every face is a sliver can miss: report it as far outside.
        d = type(zero_dist)(FAR)
    distance_out[i] = d
    gradient_out[i] = g
    winding_out[i] = int(found == 2)


@wp.kernel
def hair_body_energy_strand_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    zero_dist: Any,
    # Out:
    strand_energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    query_count_out: wp.array(dtype=wp.int32),
):
    """One thread per strand: sum_v>=2 weight * B(d_v) and its gradient per vertex (Eq. 12).

    Walks the strand from the root, skipping the mesh query of vertices proven outside and
    beyond the reach (see the module docstring). Writes every vertex's gradient (zero for the
    fixed vertices 0, 1 and for vertices beyond the reach), the strand's energy and its number
    of mesh queries.
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    s = wp.tid()
    base = s * num_vertices
    body = (s // num_strands) * body_batch_stride
    mesh = mesh_ids[body]
    vertex_offset = body * body_vertex_count
    edge_offset = body * body_face_count * 3
    zero = xi * type(xi)(0.0)
    reach = xi + dhat
    # Query radius slack over the carried upper bound: the query measures in float32.
    slack = type(xi)(1.0e-4)

    energy = zero
    queries = int(0)
    for v in range(wp.min(num_vertices, 2)):
        gradient_out[base + v] = x[base + v] * zero

    # The anchor is the last vertex measured exactly: |d| there is anchor_dist, on side
    # anchor_side (+1 outside, -1 inside, 0 none yet). The open ball of that radius around it
    # holds no surface, so a vertex within it is on the same side with |d| >= anchor_dist - r.
    anchor = x[base]
    anchor_dist = zero
    anchor_side = zero
    for v in range(2, num_vertices):
        p = x[base + v]
        ub = type(xi)(FAR)
        if anchor_side != zero:
            r = wp.length(p - anchor)
            ub = anchor_dist + r
            if anchor_side > zero and anchor_dist - r >= reach:
                gradient_out[base + v] = p * zero
                continue
        # Exact query bounded by ub: its distance lets the following vertices skip theirs.
        radius = wp.float32(wp.min(ub + slack * (type(xi)(1.0) + ub), type(xi)(FAR)))
        found, d, g = body_signed_distance(
            mesh, body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
            vertex_offset, edge_offset,
            p, radius, zero_dist
        )
        queries += 1
        if found == 0 and radius < FAR:
            # A float32 miss at the bound (or a sliver skipped): retry unbounded.
            found, d, g = body_signed_distance(
                mesh, body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
                vertex_offset, edge_offset,
                p, wp.float32(FAR), zero_dist
            )
            queries += 1
        if found == 0:
            # Every face a sliver: nothing to push against.
            anchor_side = zero
            gradient_out[base + v] = p * zero
            continue
        d, g = winding_signed(winding_ids[body], p, found, d, g, zero_dist)
        anchor = p
        anchor_dist = wp.abs(d)
        anchor_side = type(xi)(1.0)
        if d < zero:
            anchor_side = type(xi)(-1.0)
        energy += weight * barrier_energy(d, xi, dhat, bp, variant)
        gradient_out[base + v] = (weight * barrier_gradient(d, xi, dhat, bp, variant)) * g
    strand_energy_out[s] = energy
    query_count_out[s] = queries


# Margin [m] of the distance cache's proof of a miss (`hair_body_energy_vertex_kernel`): float32
# query points and distances.
CACHE_SLACK = wp.constant(1.0e-5)
# How far [m] a query that fills the distance cache looks: its miss proves this much clearance,
# which a vertex then spends over the next evaluations before it is queried again.
CACHE_REACH = wp.constant(1.0e-2)


@wp.func
def chain_query_radius(x: wp.array(dtype=Any), i: int, v: int, stride: int, floor: Any):
    """Query radius of point i, index v along its polyline (its predecessor at i - stride):
    max(floor, |p_i - p_{i-1}|), with slack for the float32 query. A miss within it proves
    |d(p_i)| > |p_i - p_{i-1}|, so the open ball around p_i of radius |d| holds p_{i-1} and no
    surface: p_i is on p_{i-1}'s side of the body (the sign rule of the module docstring, link by
    link along the polyline).
    """
    radius = floor
    if v > 0:
        radius = wp.max(floor, wp.length(x[i] - x[i - stride]))
    return wp.float32(radius * type(floor)(1.001) + type(floor)(1.0e-6))


@wp.func
def chain_hit_before(side: wp.array(dtype=wp.int32), i: int, v: int, stride: int):
    """Index of the nearest point before i on its polyline (points i - stride, i - 2 stride, ...)
    whose capped query found the surface (side +1 outside, -1 inside), -1 when none did. Every
    point in between missed its own capped query, so all of them, and point i, are on that
    point's side (`chain_query_radius`).
    """
    j = i - stride
    first = i - v * stride
    hit = int(-1)
    while j >= first:
        if side[j] != 0:
            hit = j
            break
        j -= stride
    return hit


@wp.func
def depth_query_radius(points: wp.array(dtype=Any), hit_distance: wp.array(dtype=float), i: int, hit: int):
    """Radius of the exact query of a point i that missed inside: |d(p_hit)| + |p_i - p_hit| bounds
    |d(p_i)| (the distance is 1-Lipschitz), so the BVH walk prunes to it; unbounded without a hit.
    """
    if hit < 0:
        return wp.float32(FAR)
    r = hit_distance[hit] + wp.float32(wp.length(points[i] - points[hit]))
    return r * wp.float32(1.001) + wp.float32(1.0e-6)


@wp.kernel
def hair_body_energy_vertex_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    zero_dist: Any,
    use_cache: int,
    # In and out:
    cache_points: wp.array(dtype=wp.vec3),
    cache_distance: wp.array(dtype=float),
    # Out:
    vertex_energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    query_count_out: wp.array(dtype=wp.int32),
    side_out: wp.array(dtype=wp.int32),
    hit_distance_out: wp.array(dtype=float),
    winding_out: wp.array(dtype=wp.int32),
):
    """One thread per vertex (wide GPU launches), pass 1 of 2: weight * B(d) and its gradient
    (Eq. 12) for every vertex whose query, capped at max(reach, its segment's length), finds
    the surface (the root, vertex 0, is measured at any distance on a miss); `side_out` = +1/-1
    for those (fixed vertices 0, 1 included: they carry the side along the strand), 0 for a miss
    (energy and gradient 0 until pass 2 decides); `hit_distance_out` their |d|; `winding_out` 1
    where the sign is the winding number's (`hair_body_energy_winding_kernel` settles it before
    pass 2 reads the sides).

    The cap keeps the BVH walk short: an unbounded query from a vertex far outside visits most
    of the tree, and most hair is far outside.
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    i = wp.tid()
    v = i % num_vertices
    zero = xi * type(xi)(0.0)
    p = x[i]
    body = (i // (num_strands * num_vertices)) * body_batch_stride
    radius = chain_query_radius(x, i, v, 1, xi + dhat)
    p32 = wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
    queries = int(1)
    found = int(0)
    d = zero
    g = p * zero
    if use_cache != 0 and v > 0 and cache_distance[i] - wp.length(p32 - cache_points[i]) > radius + CACHE_SLACK:
        # The distance cache proves the capped query a miss: the surface is farther than the
        # last query's distance less the move since (the distance is 1-Lipschitz), and the
        # body has not moved since it was written (`HairBodyDistanceCache`).
        queries = 0
    else:
        # With the cache the query looks out to CACHE_REACH, so that a miss proves a bound that
        # lasts; a hit beyond the radius is the capped query's miss, its distance kept.
        reach = radius
        if use_cache != 0:
            reach = wp.max(radius, CACHE_REACH)
        found, d, g = body_signed_distance(
            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
            body * body_vertex_count, body * body_face_count * 3, p, reach, zero_dist
        )
        if use_cache != 0:
            known = reach  # no face strictly within the reach
            if found != 0:
                known = wp.float32(wp.abs(d))
                if known >= radius:
                    found = 0
                    d = zero
                    g = p * zero
            cache_points[i] = p32
            cache_distance[i] = known
    if found == 0 and v == 0:
        # The root anchors the strand's sides: measured at any distance (roots lie on the scalp,
        # so this is rare).
        found, d, g = body_signed_distance(
            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
            body * body_vertex_count, body * body_face_count * 3, p, wp.float32(FAR), zero_dist
        )
        queries = 2
    side = int(0)
    if found != 0:
        side = 1
        if d < zero:
            side = -1
    side_out[i] = side
    hit_distance_out[i] = wp.float32(wp.abs(d))
    query_count_out[i] = queries
    e = zero
    gradient = p * zero
    if found != 0 and v >= 2:
        e = weight * barrier_energy(d, xi, dhat, bp, variant)
        gradient = (weight * barrier_gradient(d, xi, dhat, bp, variant)) * g
    vertex_energy_out[i] = e
    gradient_out[i] = gradient
    winding_out[i] = int(found == 2)


@wp.kernel
def hair_body_deep_flags_kernel(
    # In:
    side: wp.array(dtype=wp.int32),
    num_vertices: int,
    # Out:
    deep_flag_out: wp.array(dtype=wp.int32),
    hit_out: wp.array(dtype=wp.int32),
):
    """Pass 2a, one thread per vertex: a moving vertex that missed its capped query is beyond it
    on the side of the strand's last vertex before it that found the surface
    (`chain_hit_before`). Outside, it is beyond the reach: zero, as pass 1 wrote. Inside, it is
    deep: flag 1 and that hit, for the list that pass 2b runs over (`hair_body_deep_list_kernel`).
    """
    i = wp.tid()
    v = i % num_vertices
    deep_flag_out[i] = 0
    if side[i] != 0 or v < 2:
        return
    hit = chain_hit_before(side, i, v, 1)
    if hit >= 0 and side[hit] > 0:
        return
    deep_flag_out[i] = 1
    hit_out[i] = hit


@wp.kernel
def hair_body_deep_list_kernel(
    # In:
    deep_flag: wp.array(dtype=wp.int32),
    deep_end: wp.array(dtype=wp.int32),
    hit: wp.array(dtype=wp.int32),
    # Out:
    deep_list_out: wp.array(dtype=wp.int32),
    deep_hit_out: wp.array(dtype=wp.int32),
):
    """Pass 2a, continued: each deep vertex at its place in the list (`deep_end`, the inclusive
    prefix sum of the flags), in vertex order. Listed, the deep queries fill whole warps; in
    vertex order a warp's lanes are neighbours along a strand, whose BVH walks go alike (an
    H100, 1024 x 100 hair at batch 32: the deep queries 3.22 ms in the order of an atomic
    append, 2.68 ms in vertex order; docs/contact.md 12).
    """
    i = wp.tid()
    if deep_flag[i] == 0:
        return
    k = deep_end[i] - 1
    deep_list_out[k] = i
    deep_hit_out[k] = hit[i]


@wp.kernel
def hair_body_energy_far_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    zero_dist: Any,
    hit_distance: wp.array(dtype=float),
    deep_count: wp.array(dtype=wp.int32),
    deep_list: wp.array(dtype=wp.int32),
    deep_hit: wp.array(dtype=wp.int32),
    # Out:
    vertex_energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    query_count_out: wp.array(dtype=wp.int32),
):
    """Pass 2b, one thread per listed deep vertex (launched over every vertex, threads past the
    list's count, `deep_count[0]`, return): an exact query capped by its hit's distance plus the way to it
    (`depth_query_radius`) gives its depth.
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    t = wp.tid()
    if t >= deep_count[0]:
        return
    i = deep_list[t]
    hit = deep_hit[t]
    body = (i // (num_strands * num_vertices)) * body_batch_stride
    p = x[i]
    radius = depth_query_radius(x, hit_distance, i, hit)
    found, d, g = body_signed_distance(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, p, radius, zero_dist
    )
    queries = 2
    if found == 0 and radius < wp.float32(FAR):
        # A float32 miss at the bound: retry unbounded.
        found, d, g = body_signed_distance(
            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
            body * body_vertex_count, body * body_face_count * 3, p, wp.float32(FAR), zero_dist
        )
        queries = 3
    query_count_out[i] = queries
    if found == 2 and d > xi * type(xi)(0.0):
        # A piece of a face cut at a self-intersection: the chain of misses proved the vertex
        # inside, whatever the piece's pseudo-normal says.
        d = -d
        g = -g
    if found != 0:
        vertex_energy_out[i] = weight * barrier_energy(d, xi, dhat, bp, variant)
        gradient_out[i] = (weight * barrier_gradient(d, xi, dhat, bp, variant)) * g


@wp.func
def capped_signed_distance(
    mesh: wp.uint64,
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    vertex_offset: int,
    edge_offset: int,
    points: wp.array(dtype=Any),
    i: int,
    v: int,
    line_stride: int,
    max_distance: Any,
    zero_dist: Any,
):
    """Pass 1 of 2 of the capped signed distance of point i, index v along its polyline (its
    predecessor at i - line_stride): a query capped at max(max_distance, the link length)
    (`chain_query_radius`), at any distance for a polyline's first point (it anchors the sides).

    Returns (d, gradient, side, |d| as float32, found): on a hit d clamped to at most
    max_distance (gradient zero where clamped) and side +1 outside / -1 inside; on a miss side 0
    (`capped_signed_distance_of_miss` settles it once every point's side is written); found as
    `body_signed_distance_face`'s (2: the sign is the winding number's).
    """
    zero = zero_dist * type(zero_dist)(0.0)
    p = points[i]
    found, d, g = body_signed_distance(
        mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset, p,
        chain_query_radius(points, i, v, line_stride, max_distance), zero_dist
    )
    if found == 0 and v == 0:
        # The first point anchors its polyline's sides: measured at any distance.
        found, d, g = body_signed_distance(
            mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset,
            p, wp.float32(FAR), zero_dist
        )
    side = int(0)
    if found != 0:
        side = 1
        if d < zero:
            side = -1
    hit_distance = wp.float32(wp.abs(d))
    if found != 0 and d > max_distance:
        d = max_distance
        g = p * zero
    return d, g, side, hit_distance, found


@wp.func
def capped_signed_distance_of_miss(
    mesh: wp.uint64,
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    vertex_offset: int,
    edge_offset: int,
    points: wp.array(dtype=Any),
    side: wp.array(dtype=wp.int32),
    hit_distance: wp.array(dtype=float),
    i: int,
    v: int,
    line_stride: int,
    max_distance: Any,
    zero_dist: Any,
):
    """Pass 2 of 2 for a point i whose pass 1 missed (side[i] == 0; the other points' sides
    written): (d, gradient), outside beyond max_distance (reported as max_distance, gradient
    zero) or inside, where a query capped by the last hit before it (unbounded without one)
    gives its depth.
    """
    zero = zero_dist * type(zero_dist)(0.0)
    p = points[i]
    hit = chain_hit_before(side, i, v, line_stride)
    if hit >= 0 and side[hit] > 0:
        return max_distance, p * zero
    radius = depth_query_radius(points, hit_distance, i, hit)
    found, d, g = body_signed_distance(
        mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset, p,
        radius, zero_dist
    )
    if found == 0 and radius < wp.float32(FAR):
        found, d, g = body_signed_distance(
            mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset,
            p, wp.float32(FAR), zero_dist
        )
    if found == 2 and d > zero:
        # A piece of a face cut at a self-intersection: the chain of misses proved the point
        # inside, whatever the piece's pseudo-normal says.
        d = -d
        g = -g
    if found == 0:
        d = max_distance
        g = p * zero
    if d > max_distance:
        d = max_distance
        g = p * zero
    return d, g


@wp.kernel
def signed_distance_capped_kernel(
    # In:
    points: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    points_per_line: int,
    line_stride: int,
    points_per_batch: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    max_distance: Any,
    zero_dist: Any,
    # Out:
    distance_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    side_out: wp.array(dtype=wp.int32),
    hit_distance_out: wp.array(dtype=float),
    winding_out: wp.array(dtype=wp.int32),
):
    """Signed distance of points on polylines, pass 1 of 2: a query capped at
    max(max_distance, the point's link length) (`chain_query_radius`); a hit writes d clamped
    to at most max_distance (gradient zero where clamped) and its side, a miss side 0;
    `winding_out` 1 where the sign is the winding number's (`signed_distance_winding_kernel`
    settles it before pass 2 reads the sides).
    """
    i = wp.tid()
    v = (i // line_stride) % points_per_line
    body = (i // points_per_batch) * body_batch_stride
    d, g, side, hit_distance, found = capped_signed_distance(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, points, i, v, line_stride, max_distance, zero_dist
    )
    side_out[i] = side
    hit_distance_out[i] = hit_distance
    distance_out[i] = d
    gradient_out[i] = g
    winding_out[i] = int(found == 2)


@wp.kernel
def signed_distance_far_kernel(
    # In:
    points: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    points_per_line: int,
    line_stride: int,
    points_per_batch: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    max_distance: Any,
    zero_dist: Any,
    side: wp.array(dtype=wp.int32),
    hit_distance: wp.array(dtype=float),
    # Out:
    distance_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """Pass 2 of 2: a point that missed is outside beyond max_distance (reported as
    max_distance, gradient zero) or inside, where an unbounded query gives its depth.
    """
    i = wp.tid()
    if side[i] != 0:
        return
    v = (i // line_stride) % points_per_line
    body = (i // points_per_batch) * body_batch_stride
    d, g = capped_signed_distance_of_miss(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, points, side, hit_distance, i, v, line_stride,
        max_distance, zero_dist
    )
    distance_out[i] = d
    gradient_out[i] = g


@wp.func
def winding_settled_distance(
    mesh: wp.uint64,
    vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_mesh: wp.uint64,
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    vertex_offset: int,
    edge_offset: int,
    p: Any,
    zero_dist: Any,
):
    """(d, dd/dp, side +1/-1) of a point flagged by a pass: its unbounded `body_signed_distance`
    signed by the winding number (`winding_signed`); the fix-up passes' shared step.
    """
    found, d, g = body_signed_distance(
        mesh, vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vertex_offset, edge_offset, p,
        wp.float32(FAR), zero_dist
    )
    d, g = winding_signed(winding_mesh, p, found, d, g, zero_dist)
    side = 1
    if d < zero_dist * type(zero_dist)(0.0):
        side = -1
    return d, g, side


@wp.kernel
def signed_distance_winding_kernel(
    # In:
    points: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    points_per_batch: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    max_distance: Any,
    zero_dist: Any,
    winding: wp.array(dtype=wp.int32),
    # Out:
    distance_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    side_out: wp.array(dtype=wp.int32),
):
    """The points flagged in `winding` (closest face a crossing piece whose side of the other
    part is not known, `seam_sides`) again, unbounded, signed by the winding number (`winding_signed`);
    distance clamped to max_distance (gradient zero there) and side written. Other threads
    return at once: the winding query's code stays out of the hot kernels.
    """
    i = wp.tid()
    if winding[i] == 0:
        return
    body = (i // points_per_batch) * body_batch_stride
    p = points[i]
    d, g, side = winding_settled_distance(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, winding_ids[body], first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, p, zero_dist
    )
    side_out[i] = side
    if d > max_distance:
        d = max_distance
        g = p * zero_dist * type(zero_dist)(0.0)
    distance_out[i] = d
    gradient_out[i] = g


@wp.func
def hair_vertex_of_thread(t: int, num_strands: int, num_vertices: int):
    """(index of the point in the hair's (B, M, N) order, its vertex index along its strand) of
    thread t of a launch over B M N threads in (batch, vertex, strand) order: a warp's threads
    query the same vertex of neighbouring strands (near each other, similar BVH walks) rather
    than one strand's, centimetres apart, with no transposed copy of the hair.
    """
    per_batch = num_strands * num_vertices
    b = t // per_batch
    rest = t - b * per_batch
    v = rest // num_strands
    s = rest - v * num_strands
    return b * per_batch + s * num_vertices + v, v


@wp.kernel
def hair_capped_signed_distance_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    max_distance: Any,
    zero_dist: Any,
    active_strands: wp.array(dtype=wp.int32),
    # Out:
    distance_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    side_out: wp.array(dtype=wp.int32),
    hit_distance_out: wp.array(dtype=float),
    winding_out: wp.array(dtype=wp.int32),
):
    """`signed_distance_capped_kernel` (pass 1 of 2) of hair (B, M, N) vec3 in its own layout,
    threads in (batch, vertex, strand) order (`hair_vertex_of_thread`); outputs in the hair's
    order. Pass 2 is `hair_body_keep_out_push_kernel`'s.

    `active_strands`: (B * M,) flags, or an empty array for every strand. The vertices of a
    strand flagged 0 are not queried: they report a hit at `max_distance` with a zero gradient
    (a round of the body pass queries only the strands the last round moved).
    """
    i, v = hair_vertex_of_thread(wp.tid(), num_strands, num_vertices)
    if active_strands.shape[0] > 0:
        if active_strands[i // num_vertices] == 0:
            side_out[i] = 1
            hit_distance_out[i] = wp.float32(max_distance)
            distance_out[i] = max_distance
            gradient_out[i] = x[i] * (zero_dist * type(zero_dist)(0.0))
            winding_out[i] = 0
            return
    body = (i // (num_strands * num_vertices)) * body_batch_stride
    d, g, side, hit_distance, found = capped_signed_distance(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, x, i, v, 1, max_distance, zero_dist
    )
    side_out[i] = side
    hit_distance_out[i] = hit_distance
    distance_out[i] = d
    gradient_out[i] = g
    winding_out[i] = int(found == 2)


@wp.kernel
def hair_body_keep_out_push_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    max_distance: Any,
    zero_dist: Any,
    distance: wp.array(dtype=Any),
    gradient: wp.array(dtype=Any),
    side: wp.array(dtype=wp.int32),
    hit_distance: wp.array(dtype=float),
    margin: Any,
    push_above: Any,
    push_below: Any,
    # Out:
    pushed_out: wp.array(dtype=Any),
    pushed_count_out: wp.array(dtype=wp.int32),
    pushed_strands_out: wp.array(dtype=wp.int32),
):
    """The body pass's push of hair (B, M, N) vec3, threads as `hair_capped_signed_distance_kernel`'s,
    whose outputs (`distance`, `gradient`, `side`, `hit_distance`; the winding pass settled) it
    reads: each moving vertex (index >= FIRST_MOVING_VERTEX) gets its capped signed distance d
    (pass 2, `capped_signed_distance_of_miss`, where pass 1 missed) and, where
    push_above < d < push_below, moves by (margin - d) along the outward direction, counted in
    `pushed_count_out[0]` (added to: zeroed by the caller) and its strand flagged in
    `pushed_strands_out` ((B * M,), set to 1: zeroed by the caller; an empty array: not flagged);
    every other vertex is copied.
    """
    i, v = hair_vertex_of_thread(wp.tid(), num_strands, num_vertices)
    p = x[i]
    if v < FIRST_MOVING_VERTEX:
        pushed_out[i] = p
        return
    d = distance[i]
    g = gradient[i]
    if side[i] == 0:
        body = (i // (num_strands * num_vertices)) * body_batch_stride
        d, g = capped_signed_distance_of_miss(
            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides,
            body * body_vertex_count, body * body_face_count * 3, x, side, hit_distance, i, v, 1, max_distance,
            zero_dist
        )
    if d > push_above and d < push_below:
        pushed_out[i] = p + g * (margin - d)
        wp.atomic_add(pushed_count_out, 0, 1)
        if pushed_strands_out.shape[0] > 0:
            pushed_strands_out[i // num_vertices] = 1
    else:
        pushed_out[i] = p


@wp.kernel
def hair_body_energy_winding_kernel(
    # In:
    x: wp.array(dtype=Any),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=Any),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=Any),
    edge_normals: wp.array(dtype=Any),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    num_strands: int,
    num_vertices: int,
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    zero_dist: Any,
    winding: wp.array(dtype=wp.int32),
    # Out:
    vertex_energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
    side_out: wp.array(dtype=wp.int32),
):
    """The vertices flagged in `winding` by pass 1 (closest face a crossing piece whose side of
    the other part is not known, `seam_sides`) again, unbounded, signed by the winding number (`winding_signed`):
    their side, energy and gradient rewritten. Other threads return at once.
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    i = wp.tid()
    if winding[i] == 0:
        return
    v = i % num_vertices
    body = (i // (num_strands * num_vertices)) * body_batch_stride
    p = x[i]
    d, g, side = winding_settled_distance(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, winding_ids[body], first_piece, seam_sides,
        body * body_vertex_count, body * body_face_count * 3, p, zero_dist
    )
    side_out[i] = side
    if v >= 2:
        vertex_energy_out[i] = weight * barrier_energy(d, xi, dhat, bp, variant)
        gradient_out[i] = (weight * barrier_gradient(d, xi, dhat, bp, variant)) * g


@wp.func
def aabb_distance_sq(c: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """Squared distance from `c` to the box [lower, upper] (zero inside)."""
    e = wp.max(lower - c, wp.vec3(0.0)) + wp.max(c - upper, wp.vec3(0.0))
    return wp.dot(e, e)


@wp.kernel
def crop_mark_faces_kernel(
    # In:
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    num_faces: int,
    body_vertex_count: int,
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    num_balls: int,
    centers_batch_stride: int,
    bound_centers: wp.array(dtype=wp.vec3),
    bound_radii: wp.array(dtype=float),
    # Out:
    keep_out: wp.array(dtype=wp.int32),
):
    """keep[b, f] = 1 if the bounding box of face f of body b meets any ball (conservative:
    a triangle inside its box meets a ball only if the box does). One bounding ball of all the
    balls rejects far faces before the per-ball loop.
    """
    i = wp.tid()
    b = i // num_faces
    f = i % num_faces
    offset = b * body_vertex_count
    pa = vertices[offset + faces[3 * f + 0]]
    pb = vertices[offset + faces[3 * f + 1]]
    pc = vertices[offset + faces[3 * f + 2]]
    lower = wp.min(wp.min(pa, pb), pc)
    upper = wp.max(wp.max(pa, pb), pc)
    keep_out[i] = 0
    r = bound_radii[b]
    if aabb_distance_sq(bound_centers[b], lower, upper) > r * r:
        return
    first = b * centers_batch_stride * num_balls
    for k in range(num_balls):
        r = radii[k]
        if aabb_distance_sq(centers[first + k], lower, upper) <= r * r:
            keep_out[i] = 1
            return


# ---------------------------------------------------------------------------------------------
# Self-intersections. A posed body mesh can pass through itself (an upper arm into the chest at
# the armpit: skinning does not keep the skin's parts apart). The surface that bounds the body
# is then the boundary of the union of its parts; the faces (or parts of faces) inside another
# part are not on it, and the pseudo-normal of such a face signs the points inside that part
# "outside". `hairwarp.ops.hair_body_contact` finds the faces that cross another face
# (`self_intersecting_faces_kernel`) and the faces wholly inside (by the winding number,
# `winding_inside_kernel`), and builds the contact surface without them.
# ---------------------------------------------------------------------------------------------


@wp.func
def segment_crosses_triangle(p: wp.vec3, q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """True if the segment pq passes through the triangle abc (Moller & Trumbore 1997); a
    segment parallel to the triangle's plane counts as not crossing.
    """
    e1 = b - a
    e2 = c - a
    direction = q - p
    h = wp.cross(direction, e2)
    det = wp.dot(e1, h)
    if wp.abs(det) <= 1.0e-7 * wp.length(e1) * wp.length(e2) * wp.length(direction):
        return False
    inv = 1.0 / det
    s = p - a
    u = inv * wp.dot(s, h)
    if u < 0.0 or u > 1.0:
        return False
    r = wp.cross(s, e1)
    v = inv * wp.dot(direction, r)
    if v < 0.0 or u + v > 1.0:
        return False
    t = inv * wp.dot(e2, r)
    return t >= 0.0 and t <= 1.0


@wp.func
def triangles_cross(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3, e: wp.vec3, h: wp.vec3):
    """True if triangles abc and deh cross (an edge of one passes through the other)."""
    return (segment_crosses_triangle(a, b, d, e, h) or segment_crosses_triangle(b, c, d, e, h)
            or segment_crosses_triangle(c, a, d, e, h) or segment_crosses_triangle(d, e, a, b, c)
            or segment_crosses_triangle(e, h, a, b, c) or segment_crosses_triangle(h, d, a, b, c))


@wp.kernel
def self_intersecting_faces_kernel(
    # In:
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    # Out:
    flags_out: wp.array(dtype=wp.int32),
):
    """One thread per face: 1 if an edge of the face crosses another face that shares no vertex
    with it, or an edge of such a face crosses it (two triangles cross exactly when one's edge
    passes through the other); candidates from the mesh's BVH (box overlap).
    """
    f = wp.tid()
    i0 = faces[3 * f + 0]
    i1 = faces[3 * f + 1]
    i2 = faces[3 * f + 2]
    a = points[i0]
    b = points[i1]
    c = points[i2]
    query = wp.mesh_query_aabb(mesh, wp.min(wp.min(a, b), c), wp.max(wp.max(a, b), c))
    g = int(0)
    hit = int(0)
    while wp.mesh_query_next(query, g):
        j0 = faces[3 * g + 0]
        j1 = faces[3 * g + 1]
        j2 = faces[3 * g + 2]
        shares = (j0 == i0 or j0 == i1 or j0 == i2 or j1 == i0 or j1 == i1 or j1 == i2
                  or j2 == i0 or j2 == i1 or j2 == i2)
        if hit == 0 and not shares and triangles_cross(a, b, c, points[j0], points[j1], points[j2]):
            hit = 1
    flags_out[f] = hit


@wp.kernel
def winding_inside_kernel(
    # In:
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    # Out:
    inside_out: wp.array(dtype=wp.int32),
):
    """1 where the mesh's winding number at the point is at least 1 (inside the union of a
    self-intersecting closed mesh's parts), by three rays (`ray_inside`).
    """
    i = wp.tid()
    inside_out[i] = int(ray_inside(mesh, points[i]))


@wp.func
def median_layers(n0: int, n1: int, n2: int):
    """How many layers of a self-intersecting closed mesh hold a point, from three rays' winding
    numbers there (`ray_winding_number`; negative: a miscount): their median, capped at 2 (2 or
    more). Where the first two agree they are the median, and `n2` is not read (the third ray is
    cast only where they disagree: `seam_piece_third_rays_kernel`).
    """
    if n0 == n1:
        return wp.min(n0, 2)
    return wp.min(wp.max(wp.min(n0, n1), wp.min(wp.max(n0, n1), n2)), 2)


@wp.func
def point_triangle_distance_sq(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Squared distance from p to the triangle abc."""
    u, v, w, dist2 = point_triangle_closest_barycentric(p, a, b, c)
    return dist2


# The pieces' sides, where the other part lies across each piece on a self-intersection's crossing
# (`BodyMesh.update` finds them at every pose): four launches (three on the CPU), so that on a GPU
# the winding rays, each a walk of BVH descents, run one to a thread (one thread per piece casting
# up to twelve of them one after another took 2 ms a pose on one H200: docs/physics.md,
# "Twenty-sixth session").
# `seam_piece_crossings_kernel` finds the faces that cross each piece and the points whose winding
# number checks the verdict (`samples`, `need`); `seam_piece_rays_kernel` and
# `seam_piece_third_rays_kernel` cast the rays; `seam_piece_sides_from_rays_kernel` reads them.
# Sample k = 0: the piece's centre, outside; k = 1..3: near corner k - 1.
SEAM_SAMPLES = wp.constant(4)


@wp.kernel
def seam_piece_crossings_kernel(
    # In:
    points: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    face_parent: wp.array(dtype=wp.int32),
    first_piece: int,
    source_mesh: wp.uint64,
    source_points: wp.array(dtype=wp.vec3),
    source_faces: wp.array(dtype=wp.int32),
    offset: wp.array(dtype=float),
    row: int,
    unknown_pieces: wp.array(dtype=wp.int32),
    # Out:
    sides_out: wp.array(dtype=wp.vec4),
    samples_out: wp.array2d(dtype=wp.vec3),
    need_out: wp.array2d(dtype=wp.int32),
):
    """One thread per piece on a self-intersection's crossing (BVH faces from `first_piece` on,
    corners in `points`), one pose: where the other part lies across the piece, for
    `seam_inside_other_part`. The faces of the uncut closed mesh (`source_mesh`, with winding
    numbers) that cross the piece (a face sharing a corner with its parent counts only if it
    keeps clear of the piece's corners: a fold of the skin through itself):
    - none: the piece lies wholly on one side: (-1, -1, -1, 0) inside the other parts,
      (1, 1, 1, 0) outside;
    - one, G: G's plane is the other part's surface across the piece (a second face would cross
      it where the crossing leaves G): (s_a, s_b, s_c, 0), the corners' signed distances to it,
      outward positive;
    - more: (0, 0, 0, 1), the winding number's at query time.
    To be checked against the winding number (`seam_piece_sides_from_rays_kernel`) at the centre
    (none) or near the corners (one; corners within 4 offsets of G's plane skipped), `offset[0]`
    [m] outside along the piece's normal: one layer inside the other part, none outside. Where
    they disagree (the other part grazes an edge or a corner of the piece, or a third part holds
    it) the piece is left to the winding number too, as are those marked in `unknown` (a corner
    on a face left out inside, found on the host). Writes the provisional side ((1, 1, 1, 0) for
    none), the final one for more, and the points to check with their `need_out` flags.
    """
    t = wp.tid()
    f = first_piece + t
    for k in range(SEAM_SAMPLES):
        need_out[t, k] = 0
    a = points[faces[3 * f + 0]]
    b = points[faces[3 * f + 1]]
    c = points[faces[3 * f + 2]]
    parent = face_parent[f]
    i0 = source_faces[3 * parent + 0]
    i1 = source_faces[3 * parent + 1]
    i2 = source_faces[3 * parent + 2]
    touch = 1.0e-3 * wp.max(wp.max(wp.length(b - a), wp.length(c - b)), wp.length(a - c))
    query = wp.mesh_query_aabb(source_mesh, wp.min(wp.min(a, b), c), wp.max(wp.max(a, b), c))
    g = int(0)
    count = int(0)
    other = int(-1)
    while wp.mesh_query_next(query, g):
        j0 = source_faces[3 * g + 0]
        j1 = source_faces[3 * g + 1]
        j2 = source_faces[3 * g + 2]
        if g == parent:
            continue
        d = source_points[j0]
        e = source_points[j1]
        h = source_points[j2]
        shares = (j0 == i0 or j0 == i1 or j0 == i2 or j1 == i0 or j1 == i1 or j1 == i2
                  or j2 == i0 or j2 == i1 or j2 == i2)
        # A face around the parent crosses the piece only away from the corner or edge they
        # share (a fold of the skin passing through itself); one touching the piece is skipped.
        if shares and wp.min(wp.min(point_triangle_distance_sq(a, d, e, h), point_triangle_distance_sq(b, d, e, h)),
                             point_triangle_distance_sq(c, d, e, h)) <= touch * touch:
            continue
        if triangles_cross(a, b, c, d, e, h):
            count += 1
            other = g
    if count > 1 or unknown_pieces[f] != 0:
        sides_out[row + f] = wp.vec4(0.0, 0.0, 0.0, 1.0)
        return
    outward = wp.normalize(wp.cross(b - a, c - a)) * offset[0]
    centre = (a + b + c) / 3.0
    s = wp.vec3(1.0, 1.0, 1.0)
    if count == 0:
        # Which side is the centre's verdict; the corners check it as they check a plane's.
        samples_out[t, 0] = centre + outward
        need_out[t, 0] = 1
    else:
        d = source_points[source_faces[3 * other + 0]]
        n = wp.normalize(wp.cross(source_points[source_faces[3 * other + 1]] - d,
                                  source_points[source_faces[3 * other + 2]] - d))
        s = wp.vec3(wp.dot(a - d, n), wp.dot(b - d, n), wp.dot(c - d, n))
    sides_out[row + f] = wp.vec4(s[0], s[1], s[2], 0.0)
    for k in range(3):
        corner = a
        if k == 1:
            corner = b
        if k == 2:
            corner = c
        if wp.abs(s[k]) > 4.0 * offset[0]:
            # A twentieth of the way in from the corner, a quarter offset out: where the skin
            # folds over the parent's edge into a slit, a point straight out from the corner
            # would cross the slit into the parent's own part.
            samples_out[t, k + 1] = corner + 0.05 * (centre - corner) + 0.25 * outward
            need_out[t, k + 1] = 1


@wp.kernel
def seam_piece_rays_kernel(
    # In:
    source_mesh: wp.uint64,
    samples: wp.array2d(dtype=wp.vec3),
    need: wp.array2d(dtype=wp.int32),
    lanes: int,
    # Out:
    winding_out: wp.array3d(dtype=wp.int32),
):
    """The winding numbers at each needed sample (`seam_piece_crossings_kernel`) along
    `RAY_DIRECTION_0` and `RAY_DIRECTION_1`, launched (pieces, samples, `lanes`): 2, one ray a
    thread (a GPU; `seam_piece_third_rays_kernel` then casts the third where they disagree); 1,
    a thread casting both, and the third where they disagree (the CPU, whose threads run one
    after another: no thread and no launch more than the work).
    """
    t, k, r = wp.tid()
    if need[t, k] == 0:
        return
    p = samples[t, k]
    if lanes == 2:
        direction = RAY_DIRECTION_0
        if r == 1:
            direction = RAY_DIRECTION_1
        winding_out[t, k, r] = ray_winding_number(source_mesh, p, direction)
        return
    n0 = ray_winding_number(source_mesh, p, RAY_DIRECTION_0)
    n1 = ray_winding_number(source_mesh, p, RAY_DIRECTION_1)
    winding_out[t, k, 0] = n0
    winding_out[t, k, 1] = n1
    if n0 != n1:
        winding_out[t, k, 2] = ray_winding_number(source_mesh, p, RAY_DIRECTION_2)


@wp.kernel
def seam_piece_third_rays_kernel(
    # In:
    source_mesh: wp.uint64,
    samples: wp.array2d(dtype=wp.vec3),
    need: wp.array2d(dtype=wp.int32),
    # In and out:
    winding: wp.array3d(dtype=wp.int32),
):
    """One thread per (piece, sample): the third ray (`RAY_DIRECTION_2`) where the first two
    disagree (`median_layers`).
    """
    t, k = wp.tid()
    if need[t, k] != 0 and winding[t, k, 0] != winding[t, k, 1]:
        winding[t, k, 2] = ray_winding_number(source_mesh, samples[t, k], RAY_DIRECTION_2)


@wp.kernel
def seam_piece_sides_from_rays_kernel(
    # In:
    first_piece: int,
    row: int,
    need: wp.array2d(dtype=wp.int32),
    winding: wp.array3d(dtype=wp.int32),
    # In and out:
    sides: wp.array(dtype=wp.vec4),
):
    """One thread per piece: the provisional side of `seam_piece_crossings_kernel` checked
    against the layers at its samples (`median_layers`): with no crossing face, one layer at the
    centre is inside the other parts (-1, -1, -1, 0), none outside (kept), more the winding
    number's (0, 0, 0, 1); then a corner whose layers (1 inside, 0 outside) disagree with its
    side's sign leaves the piece to the winding number.
    """
    t = wp.tid()
    f = first_piece + t
    unknown = wp.vec4(0.0, 0.0, 0.0, 1.0)
    side = sides[row + f]
    if need[t, 0] != 0:
        layers = median_layers(winding[t, 0, 0], winding[t, 0, 1], winding[t, 0, 2])
        if layers == 1:
            side = wp.vec4(-1.0, -1.0, -1.0, 0.0)
        elif layers != 0:
            sides[row + f] = unknown
            return
        sides[row + f] = side
    for k in range(3):
        if need[t, k + 1] != 0:
            layers = median_layers(winding[t, k + 1, 0], winding[t, k + 1, 1], winding[t, k + 1, 2])
            if layers != int(side[k] < 0.0):
                sides[row + f] = unknown
                return
