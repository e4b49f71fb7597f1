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

The walk. `follower_targets_kernel` computes every vertex's target above (a thread per vertex);
`follow_guides_kernel` walks each strand from its root: the rest length (follow-the-leader) and
the body (its docstring), one thread per strand. The rounds at the end of this module are the
same walk with the queries taken out of it.

Bound. The signed distance is 1-Lipschitz: for any guide vertex g with signed distance d_g,
d(x) >= d_g - |x - g|. `follower_distance_bound_kernel` takes the largest such bound over the
follower's guides (at their anchor vertices); a vertex whose bound clears the margin is outside
the body without a query.
"""

import functools

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.kernels.distances import point_triangle_closest_barycentric
from hairwarp.kernels.hair_body_contact import body_signed_distance_face, winding_signed

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


# Threads a block of `guide_frame_rotations_tiled_kernel`, and the shared memory its strands may take
# (two strands of vec3 and the rotations; longer guides run the one-thread kernel).
FRAMES_BLOCK_DIM = 32
FRAMES_MAX_SHARED_BYTES = 40 * 1024


@functools.lru_cache(maxsize=None)
def guide_frame_rotations_tiled_kernel(num_vertices: int, window: int):
    """`guide_frame_rotations_kernel` with a block per guide and frame (`block_dim =
    FRAMES_BLOCK_DIM`): the block loads the guide's rest and current strands into shared memory
    in one coalesced pass, every thread walks the frames in step from there, and the block
    stores the rotations. The one-thread kernel waits on a memory round trip at every segment
    (~200 us for 1 024 guides of 100 vertices on an H200). Compiled once per vertex count and
    window.
    """
    n = int(num_vertices)
    segments = n - 1
    reach = int(window)

    def frames(guides_rest: wp.array(dtype=wp.vec3), guides_now: wp.array(dtype=wp.vec3),
               head_rotation: wp.array(dtype=wp.quat), num_guides: int, rotations: wp.array(dtype=wp.quat)):
        tid, _lane = wp.tid()
        b = tid // num_guides
        g = tid - b * num_guides
        r = wp.tile_load(guides_rest, shape=n, offset=g * n, storage="shared")
        c = wp.tile_load(guides_now, shape=n, offset=tid * n, storage="shared")
        out = wp.tile_zeros(shape=segments, dtype=wp.quat, storage="shared")
        q_head = head_rotation[b]
        up = wp.vec3(0.0, 1.0, 0.0)
        t0 = segment_direction(r[0], r[1], up)
        t = segment_direction(c[0], c[1], wp.quat_rotate(q_head, t0))
        q = rotation_between(wp.quat_rotate(q_head, t0), t) * q_head
        out[0] = q
        for i in range(1, segments):
            lo = wp.max(i - reach, 0)
            hi = wp.min(i + 1 + reach, n - 1)
            t0_next = segment_direction(r[lo], r[hi], t0)
            t_next = segment_direction(c[lo], c[hi], t)
            q = wp.normalize(rotation_between(t, t_next) * q * wp.quat_inverse(rotation_between(t0, t0_next)))
            out[i] = q
            t0 = t0_next
            t = t_next
        wp.tile_store(rotations, out, offset=tid * segments)

    return wp.kernel(enable_backward=False, module="unique")(frames)


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


# A hinted query's radius: the hint face's distance x HINT_SLACK + HINT_PAD [m], so that float32
# rounding of the two distance computations never leaves the hint face outside the ball.
HINT_SLACK = wp.constant(1.0001)
HINT_PAD = wp.constant(1.0e-6)


@wp.kernel
def follow_guides_kernel(
    targets: wp.array(dtype=wp.vec3),
    target_bound: wp.array(dtype=float),
    guide_slot: wp.array(dtype=wp.int32),
    rest_lengths: wp.array(dtype=float),
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
    num_followers: int,
    num_vertices: int,
    body_pass: int,
    margin: float,
    passes: int,
    reach_segments: float,
    zero_dist: float,
    settle: float,
    face_hint: int,
    first_thread: int,
    out: wp.array(dtype=wp.vec3),
    pushed: wp.array(dtype=wp.int32),
):
    """One strand of the groom in one frame (thread = frame * M + strand, from `first_thread`).

    A guide's row (`guide_slot` >= 0) is the guide's. A follower is walked from its root: each
    vertex is placed on the ray from its (placed) predecessor to its target (`follower_target`,
    precomputed by `follower_targets_kernel`: the walk then holds fewer registers) at its rest
    length (follow-the-leader, Mueller et al. 2012); with `body_pass`, where the vertex's bound
    (its target's `distance_bound`, `target_bound`, less how far the projection moved it) is
    below `margin` its signed distance is queried and, inside or within the margin, it is pushed
    out along the gradient to the margin and back onto its rest length, up to `passes` times. Each query is capped at
    `reach_segments` (>= 1) rest lengths plus the margin: a vertex whose ball of that radius holds
    no face is on its predecessor's side of the surface, outside (clear by its bound or placed at
    the margin), so a miss costs a shallow descent of the tree. A vertex's clearance (its bound,
    its queried distance, or the empty ball's radius) less the next segment's length bounds the
    next vertex too: an empty ball clears the next vertices without a query (on a
    100 000-strand groom draped on the default body, 2.45 million queries became 2.00 million
    at a reach of one segment).
    With `settle` > 0 a pushed vertex is not queried again when the projection moved it less than
    `settle` from where the push put it (at the margin): its signed distance is then at least
    margin - settle (1-Lipschitz). On a flat patch a vertex pushed out by a fraction of its
    segment is projected back by less (a 1 mm push on a 5 mm segment: 0.1 mm), and the query
    that confirmed it was a second or third link in the strand's chain of queries.
    With `face_hint` each query is capped at the distance to the closest face of the strand's
    last query (that face lies within it; the closest one can only be nearer), so that the
    tree's descent prunes more; the same faces are found (up to ties).
    The strand slides over the body; every segment keeps its rest length. out (B*M*N,), pushed
    (B*M,): vertices the body pass moved.
    """
    tid = wp.tid() + first_thread
    b = tid // num_followers
    m = tid - b * num_followers
    base = tid * num_vertices
    if guide_slot[m] >= 0:
        for i in range(num_vertices):
            out[base + i] = targets[base + i]
        pushed[tid] = 0
        return
    body = b * body_batch_stride
    leader = wp.vec3(0.0, 0.0, 0.0)
    count = int(0)
    clear = float(-1.0e30)  # a lower bound on the leader's signed distance [m]
    hint = int(-1)  # with `face_hint`, the closest face of the strand's last query
    for i in range(num_vertices):
        x = targets[base + i]
        if i >= FIXED_VERTICES:
            rest = rest_lengths[m * (num_vertices - 1) + i - 1]
            step = x - leader
            n = wp.length(step)
            if n > TANGENT_EPS:
                x = leader + step * (rest / n)
            if body_pass != 0:
                # The target's bound less how far the vertex is from its target; the vertex lies
                # within `rest` of its leader, so the leader's clearance bounds it too.
                bound = wp.max(target_bound[base + i] - wp.length(x - targets[base + i]), clear - rest)
                clear = bound
                if bound < margin:
                    clear = float(-1.0e30)
                    for k in range(passes):
                        reach = reach_segments * rest + margin
                        if hint >= 0:
                            # The last query's closest face bounds this one's distance from
                            # above: a ball of that radius holds the closest face, and a
                            # smaller ball prunes more of the tree.
                            vo = body * body_vertex_count
                            u, v, w, hint_d2 = point_triangle_closest_barycentric(
                                x, body_vertices[vo + faces[3 * hint + 0]], body_vertices[vo + faces[3 * hint + 1]],
                                body_vertices[vo + faces[3 * hint + 2]])
                            reach = wp.min(reach, wp.sqrt(hint_d2) * HINT_SLACK + HINT_PAD)
                        found, d, g, face = body_signed_distance_face(
                            mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece,
                            seam_sides, body * body_vertex_count, body * body_face_count * 3, x, reach,
                            zero_dist,
                        )
                        d, g = winding_signed(winding_ids[body], x, found, d, g, zero_dist)
                        if found == 0:
                            clear = reach
                            break
                        if face_hint != 0:
                            hint = face
                        if d >= margin:
                            clear = d
                            break
                        x = x + (margin - d) * g
                        pushed_to = x
                        step = x - leader
                        n = wp.length(step)
                        if n > TANGENT_EPS:
                            x = leader + step * (rest / n)
                        count += 1
                        # pushed_to lies at the margin (the push is along the closest point's
                        # normal); the signed distance is 1-Lipschitz.
                        if settle > 0.0 and wp.length(x - pushed_to) <= settle:
                            break
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


@wp.kernel
def follower_targets_kernel(
    guides_rest: wp.array(dtype=wp.vec3),
    guides_now: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    followers_rest: wp.array(dtype=wp.vec3),
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    guide_slot: wp.array(dtype=wp.int32),
    guide_signed_distance: wp.array(dtype=float),
    num_guides: int,
    num_followers: int,
    num_vertices: int,
    neighbours: int,
    with_bound: int,
    first_thread: int,
    out: wp.array(dtype=wp.vec3),
    placed: wp.array(dtype=wp.vec3),
    bound: wp.array(dtype=float),
):
    """`follower_target` of one vertex (thread = (frame * M + strand) * N + i, from
    `first_thread`); a guide's row is the guide's, in `placed` too (the rounds' walk leaves a
    guide's row alone); with `with_bound`, a follower's `distance_bound` there (the walk's first
    bound). out, placed (B*M*N,) vec3; bound (B*M*N,) or empty.
    """
    tid = wp.tid() + first_thread
    i = tid % num_vertices
    fm = tid // num_vertices
    b = fm // num_followers
    m = fm - b * num_followers
    slot = guide_slot[m]
    if slot >= 0:
        x = guides_now[(b * num_guides + slot) * num_vertices + i]
        out[tid] = x
        placed[tid] = x
    else:
        x = follower_target(guides_rest, guides_now, rotations, followers_rest[m * num_vertices + i],
                            follower_guides, follower_weights, follower_ratios, m * neighbours, b, i, num_guides,
                            num_vertices, neighbours)
        out[tid] = x
        if with_bound != 0:
            bound[tid] = distance_bound(guides_now, guide_signed_distance, x, follower_guides, follower_weights,
                                        follower_ratios, m * neighbours, b, i, num_guides, num_vertices, neighbours)


# The same groom in rounds (`follow_guides(schedule="rounds")`, `GuideConfig.body_schedule`). The
# walk above queries the body vertex after vertex, so a strand lying on the shoulders is one chain
# of ~250 queries, and a GPU waits for its longest chain. In rounds the queries of a round run at
# once and a walk with no query in it reads their answers: after the targets, follow-the-leader
# from them (a block per strand, the strand in shared memory); then `passes` times [every vertex
# whose bound is below the margin queried where it is (a thread per vertex); the walk again from
# the last positions, each vertex placed at its rest length from its predecessor and moved out of
# the tangent plane its last query found (`onto_plane_side`)]. A plane is wrong where the body is
# concave and stale where a vertex's predecessors moved: the rounds leave more vertices inside
# than the walk (docs/guides.md). After the first round only the strands a round found within the
# margin are walked and queried again (`strand_state`).


@wp.func
def onto_plane_side(leader: wp.vec3, x: wp.vec3, rest: float, normal: wp.vec3, surface: wp.vec3, margin: float):
    """The point at `rest` from `leader` nearest `x` (itself at `rest` from it) whose height over the
    plane through `surface` with unit `normal` is at least `margin`: the segment's direction u
    keeps its tangential part and gets normal . u = c, c = (margin - leader's height) / rest
    (u = normal where c >= 1: the leader is too deep for any direction). Pushing along the normal
    and projecting back onto the rest length undoes itself on a segment that points into the
    plane; this does not.
    """
    u = (x - leader) / rest
    c = wp.min((margin - wp.dot(normal, leader - surface)) / rest, 1.0)
    tangent = u - wp.dot(normal, u) * normal
    t = wp.length(tangent)
    if t > TANGENT_EPS:
        tangent = tangent / t
    else:
        tangent = wp.vec3(0.0, 0.0, 0.0)
        c = 1.0
    return leader + rest * (c * normal + wp.sqrt(wp.max(1.0 - c * c, 0.0)) * tangent)


# Threads a block of `follower_walk_tiled_kernel`: they load and store the strand together; the
# walk is one chain that every thread runs in step from shared memory.
WALK_BLOCK_DIM = 32
# A strand's state between the rounds (`strand_state`): left where it was by the last walk, walked
# by it, or given a vertex within the margin by the round's queries since (to be walked again).
STRAND_SETTLED = wp.constant(0)
STRAND_WALKED = wp.constant(1)
STRAND_CHANGED = wp.constant(2)
# `clearance` of a vertex not queried in this call (its `cleared_at` and plane are not set).
NEVER_QUERIED = wp.constant(-1.0e30)


@functools.lru_cache(maxsize=None)
def follower_walk_tiled_kernel(num_vertices: int):
    """The rounds' walk of every follower (a block per strand, `block_dim = WALK_BLOCK_DIM`),
    compiled once per vertex count.

    From the root, vertex i >= FIXED_VERTICES is placed on the ray from its placed predecessor
    to its target at its rest length (follow-the-leader, as `follow_guides_kernel`); where a
    query has found the body near it (the tangent plane through `surface` with the unit outward
    `normal`) and the plane puts it below the margin, it is moved onto the plane's side of the
    margin (`onto_plane_side`). A guide's row is left alone. `targets` may be `x` itself (the
    block loads the strand before it stores it). On one H200 a block per strand walked 10 000
    strands in 104 us and 100 000 in 855 us, a thread per strand in 131 / 1 036 us.

    Unless `every_strand`, a strand is walked again only where the last round's queries found a
    vertex of it within the margin (`strand_state` STRAND_CHANGED): elsewhere its planes leave
    every vertex where it is (each new plane passes at the vertex's queried distance, >= the
    margin, below it), so the walk would return its positions up to rounding. It is marked
    STRAND_SETTLED and keeps its positions and its last walk's `pushed`; the next round's queries
    skip it (its bounds are those that cleared it). On the 10 000-strand groom about one strand
    in six touches the body.

    targets, x (B*M*N,) vec3 [m]; rest_lengths (M*(N-1),) [m]; guide_slot (M,); surface, normal
    (B*M*N,) vec3 from `follower_body_query_kernel` (normal zero: no plane); strand_state (B*M,)
    int32, in and out (STRAND_WALKED after a walk); pushed (B*M,): the vertices the planes moved
    in the strand's last walk.
    """
    n = int(num_vertices)
    segments = n - 1

    def walk(guide_slot: wp.array(dtype=wp.int32), rest_lengths: wp.array(dtype=float),
             targets: wp.array(dtype=wp.vec3), surface: wp.array(dtype=wp.vec3), normal: wp.array(dtype=wp.vec3),
             num_followers: int, margin: float, every_strand: int, x: wp.array(dtype=wp.vec3),
             pushed: wp.array(dtype=wp.int32), strand_state: wp.array(dtype=wp.int32)):
        strand, lane = wp.tid()
        m = strand % num_followers
        # Read by every lane before lane 0 writes it: a lane that reads lane 0's STRAND_SETTLED
        # takes the same branch, and lane 0 writes STRAND_WALKED only past the loads' barrier.
        walked = every_strand != 0 or strand_state[strand] == STRAND_CHANGED
        if guide_slot[m] < 0 and not walked:
            if lane == 0:
                strand_state[strand] = STRAND_SETTLED
        if guide_slot[m] < 0 and walked:
            base = strand * n
            q = wp.tile_load(targets, shape=n, offset=base, storage="shared")
            rest = wp.tile_load(rest_lengths, shape=segments, offset=m * segments, storage="shared")
            on = wp.tile_load(surface, shape=n, offset=base, storage="shared")
            up = wp.tile_load(normal, shape=n, offset=base, storage="shared")
            out = wp.tile_zeros(shape=n, dtype=wp.vec3, storage="shared")
            for k in range(FIXED_VERTICES):
                out[k] = q[k]
            leader = q[FIXED_VERTICES - 1]
            count = int(0)
            for i in range(FIXED_VERTICES, n):
                p = q[i]
                length_i = rest[i - 1]
                step = p - leader
                length = wp.length(step)
                if length > TANGENT_EPS:
                    p = leader + step * (length_i / length)
                g = up[i]
                if wp.dot(g, g) > 0.0 and wp.dot(g, p - on[i]) < margin:
                    p = onto_plane_side(leader, p, length_i, g, on[i], margin)
                    count += 1
                out[i] = p
                leader = p
            wp.tile_store(x, out, offset=base)
            if lane == 0:
                pushed[strand] = count
                strand_state[strand] = STRAND_WALKED

    return wp.kernel(enable_backward=False, module="unique")(walk)


@wp.kernel
def follower_body_query_kernel(
    guides_now: wp.array(dtype=wp.vec3),
    guide_signed_distance: wp.array(dtype=float),
    follower_guides: wp.array(dtype=wp.int32),
    follower_weights: wp.array(dtype=float),
    follower_ratios: wp.array(dtype=float),
    guide_slot: wp.array(dtype=wp.int32),
    rest_lengths: wp.array(dtype=float),
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
    margin: float,
    reach_segments: float,
    zero_dist: float,
    face_hint: int,
    x: wp.array(dtype=wp.vec3),
    cleared_at: wp.array(dtype=wp.vec3),
    clearance: wp.array(dtype=float),
    surface: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    closest_face: wp.array(dtype=wp.int32),
    strand_state: wp.array(dtype=wp.int32),
):
    """One round's body query of one follower vertex (thread = (frame * M + strand) * N + i).

    Its lower bound is the larger of its guides' (`distance_bound`) and its last query's (the
    clearance found at `cleared_at`, less how far it has moved since: the signed distance is
    1-Lipschitz). Below the margin it is queried where it is: the bound's cache keeps the place
    and the signed distance (on a miss, the query's reach); a face found replaces the tangent
    plane the walk pushes out of (its closest point and outward gradient) and, within the margin,
    marks the strand STRAND_CHANGED (`follower_walk_tiled_kernel` walks it again). A miss keeps
    the last plane: a vertex the plane pushed clear would otherwise fall back in at the next
    walk. A strand the last walk left STRAND_SETTLED is skipped: none of its vertices moved, and
    each was cleared by its bound or its last query. With `face_hint` a vertex that found a face
    in an earlier round caps its query at the distance to that face (`closest_face`), as the
    walk's hint does: the same faces are found, a vertex moved by a push of a millimetre or
    less queries a ball of about that size instead of a segment's. x (B*M*N,); cleared_at,
    surface, normal (B*M*N,) vec3, clearance (B*M*N,) (NEVER_QUERIED: cleared_at, the plane and
    closest_face not set; normal zero: no plane, closest_face not set); closest_face (B*M*N,)
    int32; strand_state (B*M,) int32.
    """
    tid = wp.tid()
    i = tid % num_vertices
    fm = tid // num_vertices
    b = fm // num_followers
    m = fm - b * num_followers
    if i < FIXED_VERTICES or guide_slot[m] >= 0 or strand_state[fm] == STRAND_SETTLED:
        return
    p = x[tid]
    bound = distance_bound(guides_now, guide_signed_distance, p, follower_guides, follower_weights, follower_ratios,
                           m * neighbours, b, i, num_guides, num_vertices, neighbours)
    carried = clearance[tid]
    if carried > NEVER_QUERIED:
        bound = wp.max(bound, carried - wp.length(p - cleared_at[tid]))
    if bound >= margin:
        return
    body = b * body_batch_stride
    vo = body * body_vertex_count
    # Unlike the walk's, this vertex's predecessor may be inside too, so a miss proves it outside
    # only where the query reaches past its bound's depth: d >= bound, and a miss means |d| >= reach.
    reach = wp.max(reach_segments * rest_lengths[m * (num_vertices - 1) + i - 1], -bound) + margin
    up = normal[tid]
    if face_hint != 0 and wp.dot(up, up) > 0.0:
        # The last closest face lies within this ball (no miss, so no clearance claimed from it);
        # the closest one can only be nearer.
        hint = closest_face[tid]
        u, v, w, hint_d2 = point_triangle_closest_barycentric(
            p, body_vertices[vo + faces[3 * hint + 0]], body_vertices[vo + faces[3 * hint + 1]],
            body_vertices[vo + faces[3 * hint + 2]])
        reach = wp.min(reach, wp.sqrt(hint_d2) * HINT_SLACK + HINT_PAD)
    found, d, g, face = body_signed_distance_face(
        mesh_ids[body], body_vertices, faces, vertex_normals, edge_normals, first_piece, seam_sides, vo,
        body * body_face_count * 3, p, reach, zero_dist,
    )
    d, g = winding_signed(winding_ids[body], p, found, d, g, zero_dist)
    cleared_at[tid] = p
    if found == 0:
        clearance[tid] = reach
    else:
        clearance[tid] = d
        surface[tid] = p - d * g
        normal[tid] = g
        closest_face[tid] = face
        if d < margin:
            strand_state[fm] = STRAND_CHANGED
