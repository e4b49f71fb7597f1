"""A hashed grid of the body's faces for short closest-face queries.

A BVH query (`wp.mesh_query_point_no_sign`) descends the tree from its root: a dozen levels of
dependent loads however small its ball. Where one thread makes a long chain of short queries (the
guides' walk: a strand lying on the shoulders queries vertex after vertex, each within a few
millimetres of the surface) that descent is the chain's cost. Here each cell of a uniform grid
(edge `cell` [m]) lists, in a bucket of a hash table, every face that comes within `reach` [m] of
it; a query of radius <= `reach` reads its cell's bucket and tests those faces only. A bucket may
hold faces of several cells (a hash collision adds faces, never drops one), so the closest face
within the radius is the BVH's (up to ties). The buckets are laid out one after another (counts,
their exclusive prefix sums, then the faces), in a list of fixed capacity so that a CUDA graph
can hold it; a bucket that does not fit answers "unknown" and the caller queries the BVH.

Which faces a cell lists: those whose distance to the cell's centre is at most reach + half the
cell's diagonal (any point of the cell is within half the diagonal of the centre), over the
cells that the face's box grown by that distance overlaps.
"""

import warp as wp

from hairwarp.kernels.distances import point_triangle_closest_barycentric

# Large primes of the classic spatial hash (Teschner et al. 2003).
HASH_X = wp.constant(73856093)
HASH_Y = wp.constant(19349663)
HASH_Z = wp.constant(83492791)


@wp.func
def body_grid_bucket(ix: int, iy: int, iz: int, buckets: int):
    """The bucket of cell (ix, iy, iz) among `buckets` (a power of two)."""
    h = (ix * HASH_X) ^ (iy * HASH_Y) ^ (iz * HASH_Z)
    return h & (buckets - 1)


@wp.kernel
def body_grid_fill_kernel(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    vertex_offset: int,
    inv_cell: float,
    cell: float,
    reach: float,
    buckets: int,
    capacity: int,
    write: int,
    bucket_start: wp.array(dtype=wp.int32),
    bucket_count: wp.array(dtype=wp.int32),
    bucket_faces: wp.array(dtype=wp.int32),
):
    """Face f (thread) into the bucket of every cell within `reach` of it.

    write 0: counts only (`bucket_count`, zeroed by the caller). write 1: the faces, at
    `bucket_start` (the counts' exclusive prefix sums) + a slot taken from `bucket_count` (zeroed
    again by the caller), those past `capacity` dropped (their bucket then answers "unknown").
    """
    f = wp.tid()
    a = vertices[vertex_offset + faces[3 * f + 0]]
    b = vertices[vertex_offset + faces[3 * f + 1]]
    c = vertices[vertex_offset + faces[3 * f + 2]]
    half_diagonal = 0.8660254 * cell
    grow = reach + half_diagonal + 0.01 * cell  # slack for float32 rounding
    lo = wp.min(wp.min(a, b), c) - wp.vec3(grow, grow, grow)
    hi = wp.max(wp.max(a, b), c) + wp.vec3(grow, grow, grow)
    i0 = int(wp.floor(lo[0] * inv_cell))
    j0 = int(wp.floor(lo[1] * inv_cell))
    k0 = int(wp.floor(lo[2] * inv_cell))
    i1 = int(wp.floor(hi[0] * inv_cell))
    j1 = int(wp.floor(hi[1] * inv_cell))
    k1 = int(wp.floor(hi[2] * inv_cell))
    for k in range(k0, k1 + 1):
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                centre = wp.vec3((float(i) + 0.5) * cell, (float(j) + 0.5) * cell, (float(k) + 0.5) * cell)
                u, v, w, d2 = point_triangle_closest_barycentric(centre, a, b, c)
                if d2 <= grow * grow:
                    bucket = body_grid_bucket(i, j, k, buckets)
                    slot = wp.atomic_add(bucket_count, bucket, 1)
                    if write != 0:
                        at = bucket_start[bucket] + slot
                        if at < capacity:
                            bucket_faces[at] = f


@wp.func
def body_grid_closest_face(
    p: wp.vec3,
    max_dist: float,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    vertex_offset: int,
    inv_cell: float,
    reach: float,
    buckets: int,
    capacity: int,
    bucket_start: wp.array(dtype=wp.int32),
    bucket_count: wp.array(dtype=wp.int32),
    bucket_faces: wp.array(dtype=wp.int32),
):
    """The closest face strictly within `max_dist` [m] of p, from p's cell's bucket.

    Returns (state, face): state 1 and the face; 0 when no face lies within `max_dist`; 2 when the
    grid cannot tell (`max_dist` > `reach`, no grid, or the bucket past the list's capacity): ask
    the BVH.
    """
    if buckets == 0 or max_dist > reach:
        return 2, -1
    i = int(wp.floor(p[0] * inv_cell))
    j = int(wp.floor(p[1] * inv_cell))
    k = int(wp.floor(p[2] * inv_cell))
    bucket = body_grid_bucket(i, j, k, buckets)
    start = bucket_start[bucket]
    count = bucket_count[bucket]
    if start + count > capacity:
        return 2, -1
    best = max_dist * max_dist
    face = int(-1)
    for s in range(count):
        f = bucket_faces[start + s]
        u, v, w, d2 = point_triangle_closest_barycentric(
            p, vertices[vertex_offset + faces[3 * f + 0]], vertices[vertex_offset + faces[3 * f + 1]],
            vertices[vertex_offset + faces[3 * f + 2]])
        if d2 < best:
            best = d2
            face = f
    if face < 0:
        return 0, -1
    return 1, face
