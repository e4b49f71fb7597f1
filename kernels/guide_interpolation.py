"""Guide strands drive the full groom: the guides' segment frames, the followers' positions, and
a bound on how close a follower vertex can be to the body. float32, no autograd (a post-process).

Frames. A guide's frame at segment i is carried along the strand by parallel transport (the
minimal rotation taking one segment's direction to the next, Bishop frames), in the rest pose
and now, with each segment's direction read over a window of segments (the centreline's: a
follower sits centimetres from its guide, so the guide's vertex-to-vertex jitter, turned into
a rotation of that offset, would bend the follower's curl); `guide_frame_rotations_kernel`
writes the rotation R_i = F_i F0_i^T that takes the rest frame to the current one, as a unit
quaternion. The walk starts from the head's rotation (so a twist about the root segment follows
the head) corrected by the minimal rotation from the rigidly turned rest root segment to the
current one. Parallel transport commutes with a rigid
motion, so a guide that moved rigidly by (R, c) with R the head's rotation gets R_i = R at every
segment: a follower then moves by exactly the same rigid motion.

Followers. A follower vertex at rest arc length s reads guide j at the parameter u = s / l_j
(l_j the guide's rest segment length; `follower_ratios` holds L_follower / L_guide, so u = i *
ratio), on the guide's segment i0 = floor(u) (extrapolated past the tip; the two fixed vertices
read segment 0, which is rigid with the head, so a follower's root and first segment stay with
the scalp), and keeps its rest offset from that anchor in the segment's frame:

    x_i = sum_j w_j ( p_j(u) + R_j,i0 (x0_i - p0_j(u)) ),  p(u) = g_i0 + (u - i0)(g_i0+1 - g_i0)

A follower sitting on its guide (offset zero, ratio 1, one guide) reproduces it exactly; a curl
of the follower is carried in its offsets, so it keeps its shape as the frames turn.

One pass. `follow_guides_kernel` walks each strand from its root: the target above, the rest
length (follow-the-leader) and the body (its docstring), one thread per strand.

Bound. The signed distance is 1-Lipschitz: for any guide vertex g with signed distance d_g,
d(x) >= d_g - |x - g|. `follower_distance_bound_kernel` takes the largest such bound over the
follower's guides (at their anchor vertices); a vertex whose bound clears the margin is outside
the body without a query.
"""

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.kernels.hair_body_contact import body_signed_distance, winding_signed

wp.set_module_options({"enable_backward": False})

FIXED_VERTICES = wp.constant(NUM_FIXED_VERTICES)
# Below this length [m] a segment has no direction: the previous one is kept.
TANGENT_EPS = wp.constant(1.0e-12)


@wp.func
def rotation_between(a: wp.vec3, b: wp.vec3):
    """The unit quaternion of the minimal rotation taking unit vector a to unit vector b."""
    c = wp.dot(a, b)
    if c < -0.999999:
        # Opposite directions: half a turn about any axis perpendicular to a.
        axis = wp.cross(a, wp.vec3(1.0, 0.0, 0.0))
        if wp.length(axis) < 1.0e-3:
            axis = wp.cross(a, wp.vec3(0.0, 1.0, 0.0))
        axis = wp.normalize(axis)
        return wp.quat(axis[0], axis[1], axis[2], 0.0)
    v = wp.cross(a, b)
    return wp.normalize(wp.quat(v[0], v[1], v[2], 1.0 + c))


@wp.func
def segment_direction(p0: wp.vec3, p1: wp.vec3, previous: wp.vec3):
    """The unit direction of segment p0 -> p1, or `previous` for a segment of no length."""
    d = p1 - p0
    n = wp.length(d)
    if n > TANGENT_EPS:
        return d / n
    return previous


@wp.func
def smoothed_direction(strand: wp.array(dtype=wp.vec3), base: int, i: int, window: int, num_vertices: int,
                       previous: wp.vec3):
    """The direction of segment i seen over `window` segments on each side (the chord from vertex
    i - window to vertex i + 1 + window, clamped to the strand): the centreline's direction.
    """
    return segment_direction(strand[base + wp.max(i - window, 0)],
                             strand[base + wp.min(i + 1 + window, num_vertices - 1)], previous)


@wp.kernel
def guide_frame_rotations_kernel(
    guides_rest: wp.array(dtype=wp.vec3),
    guides_now: wp.array(dtype=wp.vec3),
    head_rotation: wp.array(dtype=wp.quat),
    num_guides: int,
    num_vertices: int,
    window: int,
    rotations: wp.array(dtype=wp.quat),
):
    """R_i of one guide in one frame (thread = frame * K + guide), i = 0 .. N-2.

    guides_rest (K*N,), guides_now (B*K*N,), head_rotation (B,), rotations (B*K*(N-1),).
    Segment 0 (fixed with the scalp) is transported from the head's rotation exactly; segments
    i >= 1 by their `smoothed_direction`, so a follower rides on its guide's centreline and a
    guide's vertex-to-vertex jitter does not turn its offset back and forth.
    """
    tid = wp.tid()
    b = tid // num_guides
    g = tid - b * num_guides
    rest = g * num_vertices
    now = tid * num_vertices
    out = tid * (num_vertices - 1)
    q_head = head_rotation[b]
    up = wp.vec3(0.0, 1.0, 0.0)
    t0 = segment_direction(guides_rest[rest], guides_rest[rest + 1], up)
    t = segment_direction(guides_now[now], guides_now[now + 1], wp.quat_rotate(q_head, t0))
    q = rotation_between(wp.quat_rotate(q_head, t0), t) * q_head
    rotations[out] = q
    for i in range(1, num_vertices - 1):
        t0_next = smoothed_direction(guides_rest, rest, i, window, num_vertices, t0)
        t_next = smoothed_direction(guides_now, now, i, window, num_vertices, t)
        q = wp.normalize(rotation_between(t, t_next) * q * wp.quat_inverse(rotation_between(t0, t0_next)))
        rotations[out + i] = q
        t0 = t0_next
        t = t_next


@wp.func
def guide_anchor(guides: wp.array(dtype=wp.vec3), base: int, i0: int, a: float):
    """p(u) = g_i0 + a (g_i0+1 - g_i0) on the strand starting at `base` (a > 1: past the tip)."""
    return guides[base + i0] + a * (guides[base + i0 + 1] - guides[base + i0])


@wp.func
def anchor_segment(i: int, ratio: float, num_vertices: int):
    """(segment i0, fraction a) of follower vertex i on a guide; a > 1 past the guide's tip."""
    u = float(i) * ratio
    i0 = wp.clamp(int(wp.floor(u)), 0, num_vertices - 2)
    if i < FIXED_VERTICES:
        i0 = 0
    return i0, u - float(i0)


@wp.func
def follower_target(
    guides_rest: wp.array(dtype=wp.vec3),
    guides_now: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    x0: wp.vec3,
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    row: int,
    b: int,
    i: int,
    num_guides: int,
    num_vertices: int,
    neighbours: int,
):
    """x_i of a follower (its rest vertex x0, its guides from `row` = m * k): the blend above."""
    x = wp.vec3(0.0, 0.0, 0.0)
    for j in range(neighbours):
        w = follower_weights[row + j]
        if w != 0.0:
            g = follower_guides[row + j]
            i0, a = anchor_segment(i, follower_ratios[row + j], num_vertices)
            p0 = guide_anchor(guides_rest, g * num_vertices, i0, a)
            p = guide_anchor(guides_now, (b * num_guides + g) * num_vertices, i0, a)
            q = rotations[(b * num_guides + g) * (num_vertices - 1) + i0]
            x += w * (p + wp.quat_rotate(q, x0 - p0))
    return x


@wp.func
def distance_bound(
    guides_now: wp.array(dtype=wp.vec3),
    guide_signed_distance: wp.array(dtype=float),
    x: wp.vec3,
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    row: int,
    b: int,
    i: int,
    num_guides: int,
    num_vertices: int,
    neighbours: int,
):
    """The largest d_g - |x - g| over a follower vertex's guides (at their anchor vertices)."""
    best = float(-1.0e30)
    for j in range(neighbours):
        if follower_weights[row + j] != 0.0:
            g = follower_guides[row + j]
            i0, a = anchor_segment(i, follower_ratios[row + j], num_vertices)
            near = i0
            if a > 0.5:
                near = i0 + 1
            k = (b * num_guides + g) * num_vertices + near
            best = wp.max(best, guide_signed_distance[k] - wp.length(x - guides_now[k]))
    return best


@wp.kernel
def follow_guides_kernel(
    guides_rest: wp.array(dtype=wp.vec3),
    guides_now: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    followers_rest: wp.array(dtype=wp.vec3),
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    guide_slot: wp.array(dtype=wp.int32),
    rest_lengths: wp.array(dtype=float),
    guide_signed_distance: wp.array(dtype=float),
    mesh_ids: wp.array(dtype=wp.uint64),
    body_vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    vertex_normals: wp.array(dtype=wp.vec3),
    edge_normals: wp.array(dtype=wp.vec3),
    winding_ids: wp.array(dtype=wp.uint64),
    first_piece: int,
    seam_sides: wp.array(dtype=wp.vec4),
    body_vertex_count: int,
    body_face_count: int,
    body_batch_stride: int,
    num_guides: int,
    num_followers: int,
    num_vertices: int,
    neighbours: int,
    project: int,
    body_pass: int,
    margin: float,
    passes: int,
    reach_segments: float,
    zero_dist: float,
    first_thread: int,
    out: wp.array(dtype=wp.vec3),
    pushed: wp.array(dtype=wp.int32),
):
    """One strand of the groom in one frame (thread = frame * M + strand, from `first_thread`).

    A guide's row (`guide_slot` >= 0) is the guide's. A follower is walked from its root: each
    vertex's target is `follower_target`; with `project` the vertex is placed on the ray from
    its (placed) predecessor to the target at its rest length (follow-the-leader, Mueller et al.
    2012); with `body_pass`, where the vertex's `distance_bound` is below `margin` its signed
    distance is queried and, inside or within the margin, it is pushed out along the gradient to
    the margin and back onto its rest length, up to `passes` times. Each query is capped at
    `reach_segments` (>= 1) rest lengths plus the margin: a vertex whose ball of that radius holds
    no face is on its predecessor's side of the surface, outside (clear by its bound or placed at
    the margin), so a miss costs a shallow descent of the tree. A vertex's clearance (its bound,
    its queried distance, or the empty ball's radius) less the next segment's length bounds the
    next vertex too: an empty ball clears the next vertices without a query (on a
    100 000-strand groom draped on the default body, 2.45 million queries became 2.00 million
    at a reach of one segment).
    The strand slides over the body; every segment keeps its rest length. out (B*M*N,), pushed
    (B*M,): vertices the body pass moved.
    """
    tid = wp.tid() + first_thread
    b = tid // num_followers
    m = tid - b * num_followers
    base = tid * num_vertices
    slot = guide_slot[m]
    if slot >= 0:
        for i in range(num_vertices):
            out[base + i] = guides_now[(b * num_guides + slot) * num_vertices + i]
        pushed[tid] = 0
        return
    row = m * neighbours
    body = b * body_batch_stride
    leader = wp.vec3(0.0, 0.0, 0.0)
    count = int(0)
    clear = float(-1.0e30)  # a lower bound on the leader's signed distance [m]
    for i in range(num_vertices):
        x = follower_target(guides_rest, guides_now, rotations, followers_rest[m * num_vertices + i],
                            follower_guides, follower_weights, follower_ratios, row, b, i, num_guides,
                            num_vertices, neighbours)
        if i >= FIXED_VERTICES and project != 0:
            rest = rest_lengths[m * (num_vertices - 1) + i - 1]
            step = x - leader
            n = wp.length(step)
            if n > TANGENT_EPS:
                x = leader + step * (rest / n)
            if body_pass != 0:
                # The vertex lies within `rest` of its leader: the leader's clearance bounds it too.
                bound = wp.max(distance_bound(guides_now, guide_signed_distance, x, follower_guides,
                                              follower_weights, follower_ratios, row, b, i, num_guides,
                                              num_vertices, neighbours), clear - rest)
                clear = bound
                if bound < margin:
                    clear = float(-1.0e30)
                    reach = reach_segments * rest + margin
                    for k in range(passes):
                        found, d, g = body_signed_distance(
                            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece,
                            seam_sides, body * body_vertex_count, body * body_face_count * 3, x, reach,
                            zero_dist,
                        )
                        d, g = winding_signed(winding_ids[body], x, found, d, g, zero_dist)
                        if found == 0:
                            clear = reach
                            break
                        if d >= margin:
                            clear = d
                            break
                        x = x + (margin - d) * g
                        step = x - leader
                        n = wp.length(step)
                        if n > TANGENT_EPS:
                            x = leader + step * (rest / n)
                        count += 1
        out[base + i] = x
        leader = x
    pushed[tid] = count


@wp.kernel
def follower_distance_bound_kernel(
    guides_now: wp.array(dtype=wp.vec3),
    guide_signed_distance: wp.array(dtype=float),
    followers: wp.array(dtype=wp.vec3),
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    num_guides: int,
    num_followers: int,
    num_vertices: int,
    neighbours: int,
    first_thread: int,
    bound: wp.array(dtype=float),
):
    """A lower bound [m] on the signed distance of one follower vertex (thread = (frame * M +
    follower) * N + i, from `first_thread`): `distance_bound`.
    """
    tid = wp.tid() + first_thread
    i = tid % num_vertices
    fm = tid // num_vertices
    b = fm // num_followers
    m = fm - b * num_followers
    bound[tid] = distance_bound(guides_now, guide_signed_distance, followers[tid], follower_guides, follower_weights,
                                follower_ratios, m * neighbours, b, i, num_guides, num_vertices, neighbours)
