"""Hair-hair contact: L_hh = lambda_hh * sum over segment pairs of B(d) (HairFormer Eq. 12-14,
d = the distance between two hair segments).

Layout: hair positions are one flat array of B * M * N vertices (batch, strand, vertex), so
vertex (b, m, v) is at (b * M + m) * N + v. Segment i of strand (b, m) joins vertices v = i and
i + 1 and has the flat id (b * M + m) * (N - 1) + i.

Which segments can touch (decided here, documented in `hairwarp.ops.hair_hair_contact`):
    - only segments of *different* strands of the same batch item;
    - only segments whose index along the strand is >= `skip_root_segments` (2 by default:
      the segments that touch the fixed vertices 0 and 1).

Two passes, because the broad phase's loops are data dependent (and we want no generated
adjoint at all):
    1. broad phase, not differentiable. On the device, segment boxes in hashed cells
       (`segment_boxes_kernel` ... `hair_hair_long_pairs_kernel`, below): each pair is tested
       once, in the cell of the low corner of the two boxes' intersection. On the CPU, a dense
       grid of segment midpoints (`segment_keys_kernel`, `dense_counting_sort_kernel`,
       `hair_hair_pairs_cpu_kernel`): each segment walks the cells of its query box (radius set
       by its own length: each pair is found by one query). Both write every pair (i < j) with
       an exact segment distance < xi + dhat into a fixed-capacity buffer, counting with an
       atomic (the count goes on past the capacity, so overflow is detected and the needed size
       known), or add its energy as they find it. The scales live on the device (`grid_params`):
       nothing is read back to launch the device's, so it can be captured in a CUDA graph.
    2. narrow phase (`hair_hair_energy_kernel`): one straight-line thread per pair slot computes
       lambda_hh * B(d) and its gradient w.r.t. the four endpoints in the same pass (envelope
       theorem, `kernels/distances.py`), accumulating energy per batch item and gradient per
       vertex with atomics; slots past the device count return at once. Fixed vertices
       (v = 0, 1) receive no gradient.
"""

from typing import Any

import warp as wp

from hairwarp.kernels.barrier import barrier_energy, barrier_gradient
from hairwarp.kernels.distances import edge_edge_closest_parameters, edge_edge_distance_gradient_at

# Gradients are hand-written beside the energy: no generated adjoints to compile.
wp.set_module_options({"enable_backward": False})

# Vertices 0 and 1 of every strand are fixed (the paper, Section 3.4): no gradient reaches them.
NUM_FIXED_VERTICES = wp.constant(2)


# The broad phase's scales (`grid_params_kernel`) from per-segment statistics gathered in
# this many slots (spread atomics: no single address that every segment's thread queues on),
# the lengths summed in fixed point (integer atomics: the same sum in any order, so the same
# grid run after run).
SEGMENT_STAT_SLOTS = wp.constant(256)
LENGTH_FIXED_POINT = wp.constant(1073741824.0)  # units per metre (2^30)
LENGTH_FIXED_POINT_MAX = wp.constant(1.0e6)  # [m]: a longer segment counts as this in the mean


@wp.kernel
def segment_stats_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    num_vertices: int,
    # Out:
    length_sums: wp.array(dtype=wp.int64),
    longest_out: wp.array(dtype=float),
    largest_out: wp.array(dtype=float),
):
    """Per slot (segment id mod SEGMENT_STAT_SLOTS): the segments' lengths summed in fixed
    point, the longest length and the largest |coordinate| of their vertices [m]. All three
    start at 0.
    """
    seg = wp.tid()
    strand = seg // (num_vertices - 1)
    v0 = strand * num_vertices + seg % (num_vertices - 1)
    a = wp.vec3(x_in[v0])
    b = wp.vec3(x_in[v0 + 1])
    length = float(wp.length(x_in[v0 + 1] - x_in[v0]))
    slot = seg % SEGMENT_STAT_SLOTS
    fixed = wp.min(length, LENGTH_FIXED_POINT_MAX) * LENGTH_FIXED_POINT
    wp.atomic_add(length_sums, slot, wp.int64(fixed))
    wp.atomic_max(longest_out, slot, length)
    largest = wp.max(wp.max(wp.abs(a[0]), wp.abs(a[1])), wp.max(wp.abs(a[2]), wp.abs(b[0])))
    wp.atomic_max(largest_out, slot, wp.max(largest, wp.max(wp.abs(b[1]), wp.abs(b[2]))))


@wp.kernel
def grid_params_kernel(
    # In:
    length_sums: wp.array(dtype=wp.int64),
    longest_in: wp.array(dtype=float),
    largest_in: wp.array(dtype=float),
    num_segments: int,
    cutoff: float,
    long_factor: float,
    cell_factor: float,
    relative_slack: float,
    # Out:
    params_out: wp.array(dtype=float),
):
    """One thread: the broad phase's scales from `segment_stats_kernel`'s slots (see
    `ops.hair_hair_contact._grid_params`): cell width, long half length H, absolute slack,
    longest half length [m].
    """
    total = wp.int64(0)
    longest = float(0.0)
    largest = float(0.0)
    for slot in range(SEGMENT_STAT_SLOTS):
        total = total + length_sums[slot]
        longest = wp.max(longest, longest_in[slot])
        largest = wp.max(largest, largest_in[slot])
    mean = float(0.0)
    if num_segments > 0:
        mean = float(wp.float64(total) / wp.float64(LENGTH_FIXED_POINT) / wp.float64(num_segments))
    max_half = 0.5 * longest
    long_half = wp.min(max_half, 0.5 * long_factor * mean)
    absolute_slack = 4.0 * largest * 1.1920928955078125e-07  # 2^-23
    params_out[0] = (cutoff + 2.0 * long_half) * cell_factor * (1.0 + relative_slack) + absolute_slack
    params_out[1] = long_half
    params_out[2] = absolute_slack
    params_out[3] = max_half


# The lengths past the mean rule's long length, counted on a ladder of LENGTH_LADDER_STEPS rungs
# (each LENGTH_LADDER_RATIO x the last; spread over LENGTH_LADDER_SLOTS addresses per rung), so
# the cells kind can size its cells for all but a small fraction of the segments whatever their
# mix of lengths (`length_ladder_kernel`, `grid_params_from_ladder_kernel`).
LENGTH_LADDER_STEPS = wp.constant(16)
LENGTH_LADDER_SLOTS = wp.constant(32)
LENGTH_LADDER_RATIO = wp.constant(1.25)


@wp.kernel
def length_ladder_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    num_vertices: int,
    grid_params: wp.array(dtype=float),
    # Out:
    counts_out: wp.array(dtype=wp.int32),
):
    """One thread per segment: a segment longer than the mean rule's long length
    base = 2 grid_params[1] is counted on rung k (base r^k < length <= base r^(k + 1), the top
    rung also counting longer ones) of `counts_out` ((LENGTH_LADDER_STEPS x LENGTH_LADDER_SLOTS,),
    zeroed). Hair of even lengths counts nothing (no atomics).
    """
    seg = wp.tid()
    strand = seg // (num_vertices - 1)
    v0 = strand * num_vertices + seg % (num_vertices - 1)
    length = float(wp.length(x_in[v0 + 1] - x_in[v0]))
    base = 2.0 * grid_params[1]
    if base <= 0.0 or length <= base:
        return
    k = int(wp.floor(wp.log(length / base) / wp.log(LENGTH_LADDER_RATIO)))
    k = wp.clamp(k, 0, LENGTH_LADDER_STEPS - 1)
    wp.atomic_add(counts_out, k * LENGTH_LADDER_SLOTS + seg % LENGTH_LADDER_SLOTS, 1)


@wp.kernel
def grid_params_from_ladder_kernel(
    # In:
    counts: wp.array(dtype=wp.int32),
    num_segments: int,
    long_fraction: float,
    cutoff: float,
    cell_factor: float,
    relative_slack: float,
    # In and out:
    params: wp.array(dtype=float),
):
    """One thread: the long length raised up the ladder (`length_ladder_kernel`) to the lowest
    rung base r^j past which at most long_fraction x num_segments segments lie, and the cell
    width (params[0], params[1]) made again from it as `grid_params_kernel` makes them.
    """
    allowed = long_fraction * float(num_segments)
    above = int(0)
    rung = int(0)
    for step in range(LENGTH_LADDER_STEPS):
        k = LENGTH_LADDER_STEPS - 1 - step
        for slot in range(LENGTH_LADDER_SLOTS):
            above += counts[k * LENGTH_LADDER_SLOTS + slot]
        if float(above) > allowed:
            rung = k + 1
            break
    if rung == 0:
        return  # the mean rule stands
    long_half = wp.min(params[3], params[1] * wp.pow(LENGTH_LADDER_RATIO, float(rung)))
    params[1] = long_half
    params[0] = (cutoff + 2.0 * long_half) * cell_factor * (1.0 + relative_slack) + params[2]


@wp.func
def grid_cell(p: wp.vec3, inv_width: float):
    """Integer cell of point p for cells of width 1 / inv_width [m]."""
    return wp.vec3i(int(wp.floor(p[0] * inv_width)), int(wp.floor(p[1] * inv_width)), int(wp.floor(p[2] * inv_width)))


@wp.func
def _add_vertex_gradient(gradient_out: wp.array(dtype=Any), v: int, num_vertices: int, g: Any):
    if v % num_vertices >= NUM_FIXED_VERTICES:
        wp.atomic_add(gradient_out, v, g)


@wp.func
def _add_pair_energy(
    vi: int,
    vj: int,
    p0: Any,
    p1: Any,
    q0: Any,
    q1: Any,
    s: Any,
    t: Any,
    group: int,
    num_vertices: int,
    xi: Any,
    dhat: Any,
    bp: Any,
    weight: Any,
    variant: int,
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """energy_out[group] += weight * B(d), gradient_out[v] += weight * B'(d) dd/dx_v for the pair
    of segments (p0, p1) (first vertex vi) and (q0, q1) (first vertex vj) whose closest points
    are at parameters (s, t) (`edge_edge_closest_parameters`). Fixed vertices get nothing.
    """
    d, g_p0, g_p1, g_q0, g_q1 = edge_edge_distance_gradient_at(p0, p1, q0, q1, s, t)
    energy = barrier_energy(d, xi, dhat, bp, variant)
    if energy == type(energy)(0.0):
        return
    wp.atomic_add(energy_out, group, wp.float64(weight * energy))
    scale = weight * barrier_gradient(d, xi, dhat, bp, variant)
    _add_vertex_gradient(gradient_out, vi, num_vertices, scale * g_p0)
    _add_vertex_gradient(gradient_out, vi + 1, num_vertices, scale * g_p1)
    _add_vertex_gradient(gradient_out, vj, num_vertices, scale * g_q0)
    _add_vertex_gradient(gradient_out, vj + 1, num_vertices, scale * g_q1)


@wp.func
def lines_apart(p0: Any, p1: Any, q0: Any, q1: Any, cutoff2: Any):
    """True if the lines through the segments (p0, p1) and (q0, q1) are surely farther apart
    than sqrt(cutoff2) (so are the segments): a cheap reject before the exact distance.

    Line distance |r . n| / |n| with n = ep x eq, r = p0 - q0. Only when the lines are at least
    0.6 degrees apart (|n|^2 > 1e-4 |ep|^2 |eq|^2: n's direction is then accurate to ~1e-5 of
    the input precision's rounding), and with the cutoff widened by 0.05 %: the exact test
    would find the same, so the pairs are unchanged.
    """
    ep = p1 - p0
    eq = q1 - q0
    n = wp.cross(ep, eq)
    nn = wp.dot(n, n)
    if nn <= type(nn)(1e-4) * wp.dot(ep, ep) * wp.dot(eq, eq):
        return False
    rn = wp.dot(p0 - q0, n)
    return rn * rn > cutoff2 * type(nn)(1.001) * nn


@wp.func
def _write_pair_if_close(
    x_in: wp.array(dtype=Any),
    i: int,
    j: int,
    strand_i: int,
    vi: int,
    p0: Any,
    p1: Any,
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    cutoff2: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    bp: Any,
    weight: Any,
    variant: int,
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """Count and write (min(i, j), max(i, j)) if segment j is of another strand, past the root
    segments, and closer than sqrt(cutoff2) to segment i = (p0, p1) (first vertex vi; the exact
    test, input precision); with `with_energy` 1 also add the pair's energy and gradient
    (`_add_pair_energy`), the broad phase's distance reused (no second pass over the pairs);
    with 2 only for a pair kept in the buffer (n < capacity: the pairs a narrow phase would sum);
    with 3 write no pair: count_out and energy_out are per segment, the pair counted and its
    energy added at min(i, j) (every pair, whatever the capacity).

    The lower id's segment goes first into the distance, as in `hair_hair_energy_kernel`, so
    the test and the energy are the same numbers whichever segment's query finds the pair.
    """
    segs_per_strand = num_vertices - 1
    strand_j = j // segs_per_strand
    if strand_j == strand_i or j % segs_per_strand < skip_root_segments:
        return
    vj = strand_j * num_vertices + j % segs_per_strand
    a0 = p0
    a1 = p1
    b0 = x_in[vj]
    b1 = x_in[vj + 1]
    va = vi
    vb = vj
    if j < i:
        a0 = b0
        a1 = b1
        b0 = p0
        b1 = p1
        va = vj
        vb = vi
    if lines_apart(a0, a1, b0, b1, cutoff2):
        return
    s, t, dist2 = edge_edge_closest_parameters(a0, a1, b0, b1)
    if dist2 < cutoff2:
        if with_energy == 3:
            # Per-segment sums, no list: the pair counted and its energy added at its lower id
            # (spread addresses: no single counter or energy that every thread's atomics queue on).
            low = wp.min(i, j)
            wp.atomic_add(count_out, low, 1)
            _add_pair_energy(va, vb, a0, a1, b0, b1, s, t, low, num_vertices, xi, dhat, bp, weight, variant,
                             energy_out, gradient_out)
            return
        n = wp.atomic_add(count_out, 0, 1)
        if n < capacity:
            pairs_out[2 * n] = wp.min(i, j)
            pairs_out[2 * n + 1] = wp.max(i, j)
        if with_energy == 1 or (with_energy == 2 and n < capacity):
            _add_pair_energy(va, vb, a0, a1, b0, b1, s, t, strand_i // num_strands, num_vertices, xi, dhat, bp,
                             weight, variant, energy_out, gradient_out)


@wp.func
def dense_cell(p: wp.vec3, origin: wp.vec3, inv_width: float, dims: wp.vec3i):
    """Cell of point p in a dense grid of dims cells of width 1 / inv_width [m] from `origin`, clamped to it."""
    return wp.vec3i(wp.clamp(int(wp.floor((p[0] - origin[0]) * inv_width)), 0, dims[0] - 1),
                    wp.clamp(int(wp.floor((p[1] - origin[1]) * inv_width)), 0, dims[1] - 1),
                    wp.clamp(int(wp.floor((p[2] - origin[2]) * inv_width)), 0, dims[2] - 1))


@wp.func
def dense_key(cx: int, cy: int, cz: int, group: int, dims: wp.vec3i):
    """Row-major key of cell (cx, cy, cz) of batch item `group`: a z row of cells is a key range."""
    return ((group * dims[0] + cx) * dims[1] + cy) * dims[2] + cz


@wp.kernel
def segment_keys_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    num_vertices: int,
    num_strands: int,
    origin: wp.vec3,
    inv_width: float,
    dims: wp.vec3i,
    # Out:
    bounds_out: wp.array(dtype=wp.vec4),
    key_out: wp.array(dtype=wp.int32),
):
    """Midpoint and half length (float32, packed: x, y, z, half length) and dense-grid key of each segment."""
    seg = wp.tid()
    strand = seg // (num_vertices - 1)
    v0 = strand * num_vertices + seg % (num_vertices - 1)
    m = wp.vec3((x_in[v0] + x_in[v0 + 1]) * type(x_in[v0][0])(0.5))
    bounds_out[seg] = wp.vec4(m[0], m[1], m[2], wp.float32(wp.length(x_in[v0 + 1] - x_in[v0])) * 0.5)
    c = dense_cell(m, origin, inv_width, dims)
    key_out[seg] = dense_key(c[0], c[1], c[2], strand // num_strands, dims)


@wp.kernel
def dense_counting_sort_kernel(
    # In:
    keys: wp.array(dtype=wp.int32),
    bounds_in: wp.array(dtype=wp.vec4),
    num_cells: int,
    # Out:
    cell_start: wp.array(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    sorted_bounds: wp.array(dtype=wp.vec4),
):
    """The CPU grid's sort, one thread (launch with dim 1): segments ordered by dense-grid key
    (a stable counting sort, ids ascending within a cell) with their packed bounds, and
    cell_start[k] the first sorted index of key k (cell_start[num_cells] = all; the array holds
    num_cells + 2, zeroed). One pass of counts, one of sums, one of scatter: on Warp's CPU
    backend cheaper than torch's sort, gather, bincount and cumsum over the cells.
    """
    for s in range(keys.shape[0]):
        cell_start[keys[s] + 2] = cell_start[keys[s] + 2] + 1
    for c in range(2, num_cells + 2):
        cell_start[c] = cell_start[c] + cell_start[c - 1]
    # cell_start[k + 1] is now key k's first index: used as its cursor, it ends at key k's end,
    # which is key k + 1's first index.
    for s in range(keys.shape[0]):
        k = keys[s] + 1
        p = cell_start[k]
        cell_start[k] = p + 1
        sorted_ids[p] = s
        sorted_bounds[p] = bounds_in[s]


@wp.kernel
def hair_hair_pairs_cpu_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    sorted_bounds: wp.array(dtype=wp.vec4),
    sorted_ids: wp.array(dtype=wp.int32),
    cell_start: wp.array(dtype=wp.int32),
    origin: wp.vec3,
    inv_width: float,
    dims: wp.vec3i,
    query_ranks: wp.array(dtype=wp.int32),
    queried_by_rank: wp.array(dtype=wp.int32),
    all_queried: int,
    grid_params: wp.array(dtype=float),
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    cutoff32: float,
    relative_slack: float,
    cutoff: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """Pairs (i < j) of segments of different strands with distance < cutoff = xi + dhat, by
    queries of a midpoint grid.

    Two segments at distance d have midpoints at most d + l_i / 2 + l_j / 2 apart. A segment is
    "long" when its half length exceeds H = `grid_params[1]`. Each pair is found by one query
    only: between two short segments by the lower rank's, within cutoff + l_i / 2 + H; a pair
    with a long segment by its longer segment's (ties: the lower id), within cutoff + l_i. So
    the query radius follows the segment's own length, and a few stretched segments (an L-BFGS
    line search's trial points reach 8x the rest length) do not widen every query. A candidate
    j is rejected by the pair's midpoint bound cutoff + (l_i + l_j) / 2 before the exact test.
    Bounds are widened by `relative_slack` and `grid_params[2]` [m] for the float32 rounding of
    midpoints and lengths (the ownership tests need none: both queries read the same float32
    half lengths).

    Shaped for Warp's CPU backend, where threads run one after another and the cost is the
    candidates each query walks:
        - a dense grid (not periodic) of cells finer than the query radius, segments sorted by
          cell key (row-major, z fastest), so the cells of one z row of the query box are one
          contiguous range (`cell_start[key]` .. `cell_start[key + 1]`): one lookup per row,
          and fewer candidates outside the query sphere than whole coarse cells bring;
        - a short-short pair is found by the query of the lower *rank* (position in the sorted
          order) rather than the lower id: a query walks only the part of each range past its
          own rank, without a per-candidate branch;
        - a candidate's midpoint and half length are one packed read (`sorted_bounds`).

    Only the segments at `query_ranks` query (thread t queries rank query_ranks[t]). With
    `all_queried` = 1 every segment queries (query_ranks lists all ranks); otherwise
    `queried_by_rank[rank]` says which do, and a query also takes every pair with a segment
    that does not query (the caller guarantees those are short: every long segment queries),
    so each pair with at least one querying segment is found once, and pairs between two
    segments that do not query are not found at all (the caller has them from elsewhere).

    With `with_energy` != 0 each pair found also adds its energy and gradient (the arguments
    of `hair_hair_energy_kernel`; pass capacity 0 to count the pairs without writing them).
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    rank = query_ranks[wp.tid()]
    i = sorted_ids[rank]
    segs_per_strand = num_vertices - 1
    if i % segs_per_strand < skip_root_segments:
        return
    long_half_length = grid_params[1]
    absolute_slack = grid_params[2]
    strand_i = i // segs_per_strand
    group_i = strand_i // num_strands
    vi = strand_i * num_vertices + i % segs_per_strand
    p0 = x_in[vi]
    p1 = x_in[vi + 1]
    bounds_i = sorted_bounds[rank]
    mi = wp.vec3(bounds_i[0], bounds_i[1], bounds_i[2])
    half_i = bounds_i[3]
    long_i = half_i > long_half_length
    reach_i = cutoff32 + half_i
    radius = (reach_i + wp.max(half_i, long_half_length)) * (1.0 + relative_slack) + absolute_slack
    cutoff2 = cutoff * cutoff
    lo = dense_cell(mi - wp.vec3(radius), origin, inv_width, dims)
    hi = dense_cell(mi + wp.vec3(radius), origin, inv_width, dims)
    for cx in range(lo[0], hi[0] + 1):
        for cy in range(lo[1], hi[1] + 1):
            start = cell_start[dense_key(cx, cy, lo[2], group_i, dims)]
            end = cell_start[dense_key(cx, cy, hi[2], group_i, dims) + 1]
            if long_i:
                for k in range(start, end):
                    j = sorted_ids[k]
                    bounds_j = sorted_bounds[k]
                    half_j = bounds_j[3]
                    if all_queried != 0 or queried_by_rank[k] != 0:
                        # Short partners, and long ones that are shorter (ties: the lower id).
                        if half_j > half_i or (half_j == half_i and j <= i):
                            continue
                    bound = (reach_i + half_j) * (1.0 + relative_slack) + absolute_slack
                    e = wp.vec3(bounds_j[0], bounds_j[1], bounds_j[2]) - mi
                    if wp.dot(e, e) > bound * bound:
                        continue
                    _write_pair_if_close(x_in, i, j, strand_i, vi, p0, p1, num_vertices, num_strands,
                                         skip_root_segments, cutoff2, capacity, with_energy, xi, dhat, bp, weight,
                                         variant, count_out, pairs_out, energy_out, gradient_out)
            else:
                if all_queried == 0:
                    # Below our rank: only the segments that do not query (short by the caller's rule).
                    for k in range(start, wp.min(end, rank)):
                        if queried_by_rank[k] != 0:
                            continue
                        bounds_j = sorted_bounds[k]
                        bound = (reach_i + bounds_j[3]) * (1.0 + relative_slack) + absolute_slack
                        e = wp.vec3(bounds_j[0], bounds_j[1], bounds_j[2]) - mi
                        if wp.dot(e, e) > bound * bound:
                            continue
                        _write_pair_if_close(x_in, i, sorted_ids[k], strand_i, vi, p0, p1, num_vertices,
                                             num_strands, skip_root_segments, cutoff2, capacity, with_energy, xi,
                                             dhat, bp, weight, variant, count_out, pairs_out, energy_out,
                                             gradient_out)
                for k in range(wp.max(start, rank + 1), end):
                    bounds_j = sorted_bounds[k]
                    half_j = bounds_j[3]
                    if half_j > long_half_length:
                        continue  # the long segment's query finds this pair
                    bound = (reach_i + half_j) * (1.0 + relative_slack) + absolute_slack
                    e = wp.vec3(bounds_j[0], bounds_j[1], bounds_j[2]) - mi
                    if wp.dot(e, e) > bound * bound:
                        continue
                    _write_pair_if_close(x_in, i, sorted_ids[k], strand_i, vi, p0, p1, num_vertices,
                                         num_strands, skip_root_segments, cutoff2, capacity, with_energy, xi, dhat,
                                         bp, weight, variant, count_out, pairs_out, energy_out, gradient_out)


@wp.kernel
def hair_hair_candidates_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    candidates_in: wp.array(dtype=wp.int32),
    candidate_count: wp.array(dtype=wp.int32),
    queried_in: wp.array(dtype=wp.int32),
    num_vertices: int,
    num_strands: int,
    cutoff: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """Of candidate pairs (i < j, different strands, past the root segments: a reused pair list),
    write those closer than the cutoff, except pairs with a segment that queried this call
    (`queried_in`: `hair_hair_pairs_cpu_kernel` found those); with `with_energy` != 0 also add
    their energy and gradient (as `hair_hair_pairs_cpu_kernel`). Launched over the list's
    buffer: rows k >= min(candidate_count, rows) are empty (a graph's list is filled on the device).
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    k = wp.tid()
    if k >= wp.min(candidate_count[0], candidates_in.shape[0] // 2):
        return
    i = candidates_in[2 * k]
    j = candidates_in[2 * k + 1]
    if queried_in[i] != 0 or queried_in[j] != 0:
        return
    segs_per_strand = num_vertices - 1
    vi = (i // segs_per_strand) * num_vertices + i % segs_per_strand
    _write_pair_if_close(x_in, i, j, i // segs_per_strand, vi, x_in[vi], x_in[vi + 1], num_vertices, num_strands, 0,
                         cutoff * cutoff, capacity, with_energy, xi, dhat, bp, weight, variant, count_out, pairs_out,
                         energy_out, gradient_out)


@wp.kernel
def hair_hair_energy_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    pairs_in: wp.array(dtype=wp.int32),
    count_in: wp.array(dtype=wp.int32),
    capacity: int,
    num_vertices: int,
    num_strands: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """Per pair k < min(count, capacity): energy_out[b] += weight * B(d), gradient_out[v] += weight * B'(d) dd/dx_v.

    The energy sums up to millions of small terms into one number per batch item: it is
    accumulated in float64 whatever the input precision (a float32 running sum of 1.6 M terms
    was measured 0.3 % off). Each vertex gradient sums only tens of terms: input precision.
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    k = wp.tid()
    # Launched over the buffer (or the count read by the host): pairs past the count are empty.
    if k >= wp.min(count_in[0], capacity):
        return
    i = pairs_in[2 * k]
    j = pairs_in[2 * k + 1]
    segs_per_strand = num_vertices - 1
    strand_i = i // segs_per_strand
    strand_j = j // segs_per_strand
    vi = strand_i * num_vertices + i % segs_per_strand
    vj = strand_j * num_vertices + j % segs_per_strand
    p0 = x_in[vi]
    p1 = x_in[vi + 1]
    q0 = x_in[vj]
    q1 = x_in[vj + 1]
    s, t, dist2 = edge_edge_closest_parameters(p0, p1, q0, q1)
    _add_pair_energy(vi, vj, p0, p1, q0, q1, s, t, strand_i // num_strands, num_vertices, xi, dhat, bp, weight,
                     variant, energy_out, gradient_out)


# ------------------------------------------------------------------------------------------
# The device broad phase: segment boxes in hashed cells (one thread per (segment, cell) entry)
#
# Two segments closer than the cutoff c have boxes, each the segment's bounding box grown by
# c / 2 per side, that overlap (the midpoint of the two closest points lies in both). So each
# segment is entered in every cell its box touches, and a pair is tested in exactly one cell:
# the one that holds the low corner of the two boxes' intersection. Cells are as wide as a
# typical box (`grid_params[0]`), so a typical segment sits in at most 2 cells per axis (8
# entries, a fixed bound per segment: no capacity to learn); a longer one ("long", wider than
# 2 cells on some axis: a stretched line-search trial point) is entered once, at its midpoint's
# cell, and finds its own pairs by walking the cells of its box, 32 threads to a long segment
# (`hair_hair_long_pairs_kernel`).
# The cells are hashed into a table of 2^k slots, with the batch item in the hash; slots shared by
# distant cells only add candidates that the exact cell test rejects. Against a midpoint grid
# (every segment within the midpoints' bound: ~600 candidates walked for ~1 pair per segment on a
# drape, docs/contact.md 6), a segment meets only the boxes that share its cells.

# Entries per segment: at most two cells per axis.
MAX_CELLS_PER_SEGMENT = wp.constant(8)


@wp.func
def cell_table_slot(c: wp.vec3i, group: int, table_mask: int):
    """Slot of cell c of batch item `group` in a table of table_mask + 1 (a power of two) slots."""
    h = wp.uint32(c[0]) * wp.uint32(73856093)
    h = h ^ (wp.uint32(c[1]) * wp.uint32(19349663))
    h = h ^ (wp.uint32(c[2]) * wp.uint32(83492791))
    h = h ^ (wp.uint32(group) * wp.uint32(668265263))
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(374761393)
    h = h ^ (h >> wp.uint32(13))
    return int(h & wp.uint32(table_mask))


@wp.func
def box_center_cell(lo: wp.vec3, hi: wp.vec3, inv_width: float):
    """Cell of a box's centre: where a long segment is entered."""
    return grid_cell((lo + hi) * 0.5, inv_width)


@wp.func
def entry_cell(lo_cell: wp.vec3i, k: int):
    """Cell of entry k (0..7) of a short segment whose box starts in cell lo_cell."""
    return wp.vec3i(lo_cell[0] + (k & 1), lo_cell[1] + ((k >> 1) & 1), lo_cell[2] + (k >> 2))


@wp.func
def boxes_meet_in_cell(lo_i: wp.vec3, hi_i: wp.vec3, lo_j: wp.vec3, hi_j: wp.vec3, cell: wp.vec3i, inv_width: float):
    """True if the two boxes overlap and the low corner of their intersection is in `cell`."""
    corner = wp.max(lo_i, lo_j)
    top = wp.min(hi_i, hi_j)
    if corner[0] > top[0] or corner[1] > top[1] or corner[2] > top[2]:
        return False
    c = grid_cell(corner, inv_width)
    return c[0] == cell[0] and c[1] == cell[1] and c[2] == cell[2]


@wp.kernel
def segment_boxes_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    grid_params: wp.array(dtype=float),
    half_cutoff32: float,
    relative_slack: float,
    table_mask: int,
    # Out:
    box_lo_out: wp.array(dtype=wp.vec3),
    box_hi_out: wp.array(dtype=wp.vec3),
    long_out: wp.array(dtype=wp.int32),
    entry_rank_out: wp.array(dtype=wp.int32),
    slot_count_out: wp.array(dtype=wp.int32),
    long_count_out: wp.array(dtype=wp.int32),
    long_list_out: wp.array(dtype=wp.int32),
):
    """Each segment's box (float32, grown by the cutoff / 2 and the rounding slack), whether it is
    long, and its entries: entry k of segment s gets its rank in its slot (`entry_rank_out[8 s + k]`,
    -1 for no entry), counted by an atomic on the slot. Root segments get no entry. Long segments
    are also listed for `hair_hair_long_pairs_kernel` ((2 S,) `long_list_out`, (B + 1,)
    `long_count_out`): all of them from 0 on (`long_count_out[B]` of them), and each batch item
    g's from S + g x its segments on (`long_count_out[g]`).
    """
    s = wp.tid()
    segs_per_strand = num_vertices - 1
    strand = s // segs_per_strand
    index = s % segs_per_strand
    v0 = strand * num_vertices + index
    a = wp.vec3(x_in[v0])
    b = wp.vec3(x_in[v0 + 1])
    pad = half_cutoff32 * (1.0 + relative_slack) + grid_params[2]
    lo = wp.min(a, b) - wp.vec3(pad)
    hi = wp.max(a, b) + wp.vec3(pad)
    box_lo_out[s] = lo
    box_hi_out[s] = hi
    base = s * MAX_CELLS_PER_SEGMENT
    for k in range(MAX_CELLS_PER_SEGMENT):
        entry_rank_out[base + k] = -1
    long_out[s] = 0
    if index < skip_root_segments:
        return
    group = strand // num_strands
    inv_width = 1.0 / grid_params[0]
    lo_cell = grid_cell(lo, inv_width)
    hi_cell = grid_cell(hi, inv_width)
    if hi_cell[0] - lo_cell[0] > 1 or hi_cell[1] - lo_cell[1] > 1 or hi_cell[2] - lo_cell[2] > 1:
        long_out[s] = 1
        # Listed twice: in the batch's list (the long-pairs launch's threads) and in its item's
        # (its long partners; item g's list starts at g x its segments).
        num_groups = long_count_out.shape[0] - 1
        long_list_out[wp.atomic_add(long_count_out, num_groups, 1)] = s
        item_list = long_list_out.shape[0] // 2 + group * num_strands * segs_per_strand
        long_list_out[item_list + wp.atomic_add(long_count_out, group, 1)] = s
        slot = cell_table_slot(box_center_cell(lo, hi, inv_width), group, table_mask)
        entry_rank_out[base] = wp.atomic_add(slot_count_out, slot, 1)
        return
    for k in range(MAX_CELLS_PER_SEGMENT):
        c = entry_cell(lo_cell, k)
        if c[0] <= hi_cell[0] and c[1] <= hi_cell[1] and c[2] <= hi_cell[2]:
            entry_rank_out[base + k] = wp.atomic_add(slot_count_out, cell_table_slot(c, group, table_mask), 1)


@wp.func
def entry_id(s: int, k: int, long_segment: int):
    """Packed entry of the sorted table: 8 s + k for entry k of a short segment s, -(8 s) - 1 for
    a long one (entered once).
    """
    if long_segment != 0:
        return -(s * MAX_CELLS_PER_SEGMENT) - 1
    return s * MAX_CELLS_PER_SEGMENT + k


@wp.kernel
def scatter_entries_kernel(
    # In:
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    long_in: wp.array(dtype=wp.int32),
    entry_rank: wp.array(dtype=wp.int32),
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    grid_params: wp.array(dtype=float),
    num_vertices: int,
    num_strands: int,
    table_mask: int,
    # Out:
    sorted_entries_out: wp.array(dtype=wp.int32),
    sorted_lo_out: wp.array(dtype=wp.vec3),
    sorted_hi_out: wp.array(dtype=wp.vec3),
):
    """Counting sort: entry k of segment s goes to position start(slot) + its rank in the slot,
    with its box, so a slot's candidates are read contiguously.
    """
    e = wp.tid()
    rank = entry_rank[e]
    if rank < 0:
        return
    s = e // MAX_CELLS_PER_SEGMENT
    k = e % MAX_CELLS_PER_SEGMENT
    group = s // ((num_vertices - 1) * num_strands)
    inv_width = 1.0 / grid_params[0]
    lo = box_lo[s]
    hi = box_hi[s]
    is_long = long_in[s]
    cell = entry_cell(grid_cell(lo, inv_width), k)
    if is_long != 0:
        cell = box_center_cell(lo, hi, inv_width)
    slot = cell_table_slot(cell, group, table_mask)
    pos = slot_end[slot] - slot_count[slot] + rank
    sorted_entries_out[pos] = entry_id(s, k, is_long)
    sorted_lo_out[pos] = lo
    sorted_hi_out[pos] = hi


@wp.func
def _cell_walk_length(n: int, r: int):
    """Partners entry r of a slot of n entries meets (a round robin: each pair of the slot's
    entries met once, the work dealt evenly): r + 1 ... r + (n - 1) / 2 (mod n), and for even n
    also the one n / 2 on if r < n / 2. (Meeting every later entry halves the reads but not a
    warp's longest loop.)
    """
    meets = (n - 1) // 2
    if n % 2 == 0 and r < n // 2:
        meets = n // 2
    return meets


@wp.func
def _entry_cell_and_slot(
    packed: int,
    lo: wp.vec3,
    group: int,
    inv_width: float,
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    table_mask: int,
):
    """The cell of sorted entry `packed` (its segment's box starting at `lo`, of batch item
    `group`) and its slot's first position and entry count: (cell, start, n). One function for
    the hits kernel and the pairs kernel, whose walks must be the same step for step (the
    pairs kernel resumes the other's).
    """
    cell = entry_cell(grid_cell(lo, inv_width), packed % MAX_CELLS_PER_SEGMENT)
    slot = cell_table_slot(cell, group, table_mask)
    n = slot_count[slot]
    return cell, slot_end[slot] - n, n


@wp.func
def _cell_partner(
    sorted_entries: wp.array(dtype=wp.int32),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    q: int,
    i: int,
    strand_i: int,
    group: int,
    lo_i: wp.vec3,
    hi_i: wp.vec3,
    cell: wp.vec3i,
    inv_width: float,
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
):
    """Segment j of sorted entry q if the pair (i, j) is met at i's entry in `cell`: j short, of
    another strand of i's batch item, past the root segments, j's box meets i's with the
    intersection's low corner in `cell`, and q is j's entry of `cell` (not of another cell
    sharing the slot); else -1.
    """
    other = sorted_entries[q]
    if other < 0:
        return -1
    j = other // MAX_CELLS_PER_SEGMENT
    segs_per_strand = num_vertices - 1
    strand_j = j // segs_per_strand
    if strand_j == strand_i or j % segs_per_strand < skip_root_segments:
        return -1
    lo_j = sorted_lo[q]
    if not boxes_meet_in_cell(lo_i, hi_i, lo_j, sorted_hi[q], cell, inv_width):
        return -1
    c = entry_cell(grid_cell(lo_j, inv_width), other % MAX_CELLS_PER_SEGMENT)
    if c[0] != cell[0] or c[1] != cell[1] or c[2] != cell[2]:
        return -1  # j's entry of another cell sharing this slot: the pair is met in c only
    if strand_j // num_strands != group:
        return -1  # another batch item's cell sharing this slot
    return j


@wp.kernel
def hair_hair_cell_hits_kernel(
    # In:
    sorted_entries: wp.array(dtype=wp.int32),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    grid_params: wp.array(dtype=float),
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    table_mask: int,
    hit_rows: int,
    hit_slots: int,
    max_steps: int,
    # Out:
    hits_out: wp.array(dtype=wp.int32),
    hit_state_out: wp.array(dtype=wp.int32),
):
    """The walk of the short-short pairs without their exact test, one thread per sorted entry
    (segment i, cell c; threads of a slot side by side, reading the same candidates): the first
    `hit_slots` partners j that `_cell_partner` keeps go to row `pos` of `hits_out`
    ((hit_slots x hit_rows,) segment ids, slot-major) for `hair_hair_hit_pairs_kernel`. Row state
    (`hit_state_out`, (hit_rows,)): the hits written (0 ... hit_slots), or hit_slots + t if the
    walk met one more at step t, or if it walked `max_steps` steps with more to go (t =
    max_steps + 1; the row's unwritten slots then hold -1): `hair_hair_cell_pairs_kernel` goes
    on from step t, in lanes (a walk capped here is shared by them). Entries past the rows get no
    row: that kernel walks them whole.

    Why apart from the exact test: a thread that carries the test's registers runs the walk,
    a few hundred reads per entry, at a fraction of the occupancy (docs/contact.md 11).
    """
    pos = wp.tid()
    if pos >= hit_rows:
        return
    hit_state_out[pos] = 0
    if pos >= slot_end[table_mask]:
        return  # past the entries (launched over the bound of 8 per segment)
    packed = sorted_entries[pos]
    if packed < 0:
        return  # a long segment: `hair_hair_long_pairs_kernel`
    i = packed // MAX_CELLS_PER_SEGMENT
    strand_i = i // (num_vertices - 1)
    group = strand_i // num_strands
    inv_width = 1.0 / grid_params[0]
    lo_i = sorted_lo[pos]
    hi_i = sorted_hi[pos]
    cell, start, n = _entry_cell_and_slot(packed, lo_i, group, inv_width, slot_end, slot_count, table_mask)
    r = pos - start
    hits = int(0)
    length = _cell_walk_length(n, r)
    for t in range(1, wp.min(length, max_steps) + 1):
        j = _cell_partner(sorted_entries, sorted_lo, sorted_hi, start + (r + t) % n, i, strand_i, group, lo_i, hi_i,
                          cell, inv_width, num_vertices, num_strands, skip_root_segments)
        if j < 0:
            continue
        if hits == hit_slots:
            hit_state_out[pos] = hit_slots + t
            return
        hits_out[hits * hit_rows + pos] = j  # slot-major: see `hair_hair_hit_pairs_kernel`
        hits += 1
    if length > max_steps:
        for k in range(hits, hit_slots):
            hits_out[k * hit_rows + pos] = -1
        hit_state_out[pos] = hit_slots + max_steps + 1
        return
    hit_state_out[pos] = hits


@wp.kernel
def hair_hair_hit_pairs_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    sorted_entries: wp.array(dtype=wp.int32),
    hits: wp.array(dtype=wp.int32),
    hit_state: wp.array(dtype=wp.int32),
    hit_slots: int,
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    cutoff: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """The exact test of the hits `hair_hair_cell_hits_kernel` wrote, one thread per hit slot
    (hit_slots x hit_rows, slot-major): the pair (segment of sorted entry `row`, hits[t]) through
    `_write_pair_if_close`. Slot-major, a warp holds one slot of 32 rows: the first slots' warps
    are mostly full, the last ones' mostly empty and done at once (row-major measured the same
    on an H100: the tests, not the idle lanes, take the time).
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    t = wp.tid()
    hit_rows = hit_state.shape[0]
    row = t % hit_rows
    if t // hit_rows >= wp.min(hit_state[row], hit_slots):
        return
    j = hits[t]
    if j < 0:
        return  # a slot left empty by a walk capped at max_steps
    i = sorted_entries[row] // MAX_CELLS_PER_SEGMENT
    segs_per_strand = num_vertices - 1
    strand_i = i // segs_per_strand
    vi = strand_i * num_vertices + i % segs_per_strand
    _write_pair_if_close(x_in, i, j, strand_i, vi, x_in[vi], x_in[vi + 1], num_vertices, num_strands,
                         skip_root_segments, cutoff * cutoff, capacity, with_energy, xi, dhat, bp, weight, variant,
                         count_out, pairs_out, energy_out, gradient_out)


@wp.kernel
def hair_hair_cell_pairs_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    sorted_entries: wp.array(dtype=wp.int32),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    hit_state: wp.array(dtype=wp.int32),
    hit_rows: int,
    hit_slots: int,
    walk_lanes: int,
    num_entries: int,
    grid_params: wp.array(dtype=float),
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    table_mask: int,
    cutoff: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """The walks `hair_hair_cell_hits_kernel` left, `walk_lanes` threads per sorted entry (of
    `num_entries`, the launch's bound; lane-major): from the step its row stopped at
    (hit_state - hit_slots), or the whole walk for an entry past the rows, lane k taking every
    `walk_lanes`-th step from the k-th on; each partner `_cell_partner` keeps tested exactly
    (`_write_pair_if_close`, which orders the two by id). With the hits kernel, each pair is
    tested once: in one cell, by one of its two entries there (the round robin of
    `_cell_walk_length`), by one lane. Lanes share a crowded cell's long walks where the launch
    leaves the GPU room (a small batch; docs/contact.md 12).
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    tid = wp.tid()
    pos = tid % num_entries
    lane = tid // num_entries
    if pos >= slot_end[table_mask]:
        return  # past the entries (launched over the bound of 8 per segment)
    first = int(1)
    if pos < hit_rows:
        first = hit_state[pos] - hit_slots
        if first <= 0:
            return  # walked whole by the hits kernel
    packed = sorted_entries[pos]
    if packed < 0:
        return  # a long segment: `hair_hair_long_pairs_kernel`
    i = packed // MAX_CELLS_PER_SEGMENT
    segs_per_strand = num_vertices - 1
    strand_i = i // segs_per_strand
    group = strand_i // num_strands
    inv_width = 1.0 / grid_params[0]
    lo_i = sorted_lo[pos]
    hi_i = sorted_hi[pos]
    cell, start, n = _entry_cell_and_slot(packed, lo_i, group, inv_width, slot_end, slot_count, table_mask)
    vi = strand_i * num_vertices + i % segs_per_strand
    p0 = x_in[vi]
    p1 = x_in[vi + 1]
    cutoff2 = cutoff * cutoff
    r = pos - start
    for t in range(first + lane, _cell_walk_length(n, r) + 1, walk_lanes):
        j = _cell_partner(sorted_entries, sorted_lo, sorted_hi, start + (r + t) % n, i, strand_i, group, lo_i, hi_i,
                          cell, inv_width, num_vertices, num_strands, skip_root_segments)
        if j < 0:
            continue
        _write_pair_if_close(x_in, i, j, strand_i, vi, p0, p1, num_vertices, num_strands, skip_root_segments,
                             cutoff2, capacity, with_energy, xi, dhat, bp, weight, variant, count_out, pairs_out,
                             energy_out, gradient_out)


# Threads that share one long segment's walk (its cells dealt out in turn): a few long segments
# with wide boxes would otherwise each be one thread walking a hundred cells, the whole launch
# waiting on them.
LONG_LANES = wp.constant(32)


@wp.func
def box_cell(lo_cell: wp.vec3i, hi_cell: wp.vec3i, c: int):
    """Cell c (row-major, x fastest) of the cell box [lo_cell, hi_cell]."""
    ex = hi_cell[0] - lo_cell[0] + 1
    ey = hi_cell[1] - lo_cell[1] + 1
    return wp.vec3i(lo_cell[0] + c % ex, lo_cell[1] + (c // ex) % ey, lo_cell[2] + c // (ex * ey))


@wp.func
def box_cell_count(lo_cell: wp.vec3i, hi_cell: wp.vec3i):
    """Cells in the cell box [lo_cell, hi_cell]."""
    return (hi_cell[0] - lo_cell[0] + 1) * (hi_cell[1] - lo_cell[1] + 1) * (hi_cell[2] - lo_cell[2] + 1)


@wp.func
def _long_short_partners_in_cell(
    cell: wp.vec3i,
    x_in: wp.array(dtype=Any),
    i: int,
    group: int,
    strand_i: int,
    vi: int,
    p0: Any,
    p1: Any,
    lo_i: wp.vec3,
    hi_i: wp.vec3,
    inv_width: float,
    sorted_entries: wp.array(dtype=wp.int32),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    table_mask: int,
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    cutoff2: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    bp: Any,
    weight: Any,
    variant: int,
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """The short partners of long segment i whose pair is met in `cell` (the cell of the low
    corner of the two boxes' intersection), each tested exactly (`_write_pair_if_close`).
    """
    segs_per_strand = num_vertices - 1
    slot = cell_table_slot(cell, group, table_mask)
    end = slot_end[slot]
    for q in range(end - slot_count[slot], end):
        other = sorted_entries[q]
        if other < 0:
            continue
        j = other // MAX_CELLS_PER_SEGMENT
        if (j // segs_per_strand) // num_strands != group:
            continue
        lo_j = sorted_lo[q]
        if not boxes_meet_in_cell(lo_i, hi_i, lo_j, sorted_hi[q], cell, inv_width):
            continue
        cj = entry_cell(grid_cell(lo_j, inv_width), other % MAX_CELLS_PER_SEGMENT)
        if cj[0] != cell[0] or cj[1] != cell[1] or cj[2] != cell[2]:
            continue  # j's entry of another cell sharing this slot
        _write_pair_if_close(x_in, i, j, strand_i, vi, p0, p1, num_vertices, num_strands, skip_root_segments,
                             cutoff2, capacity, with_energy, xi, dhat, bp, weight, variant, count_out, pairs_out,
                             energy_out, gradient_out)


@wp.kernel
def hair_hair_long_pairs_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    long_count: wp.array(dtype=wp.int32),
    long_list: wp.array(dtype=wp.int32),
    sorted_entries: wp.array(dtype=wp.int32),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    slot_end: wp.array(dtype=wp.int32),
    slot_count: wp.array(dtype=wp.int32),
    grid_params: wp.array(dtype=float),
    num_vertices: int,
    num_strands: int,
    skip_root_segments: int,
    table_mask: int,
    list_stride: int,
    cutoff: Any,
    capacity: int,
    with_energy: int,
    xi: Any,
    dhat: Any,
    join_fraction: wp.array(dtype=Any),
    weight: Any,
    variant: int,
    # Out:
    count_out: wp.array(dtype=wp.int32),
    pairs_out: wp.array(dtype=wp.int32),
    energy_out: wp.array(dtype=wp.float64),
    gradient_out: wp.array(dtype=Any),
):
    """The long segments' pairs: LONG_LANES threads per long segment i of the batch's list
    (`segment_boxes_kernel`; launched as list_stride x LONG_LANES threads, striding over it).
    Lane l walks the cells l, l + LONG_LANES, ... of i's box for short partners (each met in the
    cell of the boxes' low corner, as between short ones), then the long segments l,
    l + LONG_LANES, ... of i's batch item's list for long partners, keeping those shorter than i
    (ties: the lower id tests the pair).
    """
    bp = join_fraction[0]  # a device scalar: a captured graph follows its value
    t = wp.tid()
    lane = t % LONG_LANES
    segs_per_strand = num_vertices - 1
    segs_per_group = num_strands * segs_per_strand
    num_groups = long_count.shape[0] - 1
    inv_width = 1.0 / grid_params[0]
    cutoff2 = cutoff * cutoff
    for listed in range(t // LONG_LANES, long_count[num_groups], list_stride):
        i = long_list[listed]
        strand_i = i // segs_per_strand
        group = strand_i // num_strands
        lo_i = box_lo[i]
        hi_i = box_hi[i]
        vi = strand_i * num_vertices + i % segs_per_strand
        p0 = x_in[vi]
        p1 = x_in[vi + 1]
        half_i = wp.length(wp.vec3(p1) - wp.vec3(p0)) * 0.5
        lo_cell = grid_cell(lo_i, inv_width)
        hi_cell = grid_cell(hi_i, inv_width)
        # A short partner's pair is met in the cell of the boxes' low corner, which lies in j's
        # box (< 2 cells a side) within the cutoff of segment i's closest point to i: within
        # reach = 2 sqrt(3) cells + the cutoff of segment i. A segment stretched to metres has a
        # box of millions of cells but only a tube of them within that reach: walked slab by slab
        # along its longest axis when that is fewer cells than the box.
        width = grid_params[0]
        reach = (3.4642 * width + wp.float32(cutoff)) * 1.001 + 1.0e-6
        a0 = wp.vec3(p0)
        d = wp.vec3(p1) - a0
        axis = int(0)
        if wp.abs(d[1]) > wp.abs(d[axis]):
            axis = 1
        if wp.abs(d[2]) > wp.abs(d[axis]):
            axis = 2
        k_lo = wp.max(lo_cell[axis], int(wp.floor((wp.min(a0[axis], a0[axis] + d[axis]) - reach) * inv_width)))
        k_hi = wp.min(hi_cell[axis], int(wp.floor((wp.max(a0[axis], a0[axis] + d[axis]) + reach) * inv_width)))
        across = (4.0 * reach + width) * inv_width + 2.0
        if float(k_hi - k_lo + 1) * across * across >= float(box_cell_count(lo_cell, hi_cell)):
            for c in range(lane, box_cell_count(lo_cell, hi_cell), LONG_LANES):
                _long_short_partners_in_cell(box_cell(lo_cell, hi_cell, c), x_in, i, group, strand_i, vi, p0, p1,
                                             lo_i, hi_i, inv_width, sorted_entries, sorted_lo, sorted_hi, slot_end,
                                             slot_count, table_mask, num_vertices, num_strands, skip_root_segments,
                                             cutoff2, capacity, with_energy, xi, dhat, bp, weight, variant,
                                             count_out, pairs_out, energy_out, gradient_out)
        else:
            for k in range(k_lo + lane, k_hi + 1, LONG_LANES):
                # The part of segment i within reach of slab k (along `axis`), grown by the reach.
                u0 = (float(k) * width - reach - a0[axis]) / d[axis]
                u1 = (float(k + 1) * width + reach - a0[axis]) / d[axis]
                lo_u = wp.clamp(wp.min(u0, u1), 0.0, 1.0)
                hi_u = wp.clamp(wp.max(u0, u1), 0.0, 1.0)
                q0 = a0 + d * lo_u
                q1 = a0 + d * hi_u
                cl = grid_cell(wp.min(q0, q1) - wp.vec3(reach), inv_width)
                ch = grid_cell(wp.max(q0, q1) + wp.vec3(reach), inv_width)
                cl = wp.max(cl, lo_cell)
                ch = wp.min(ch, hi_cell)
                if axis == 0:
                    cl = wp.vec3i(k, cl[1], cl[2])
                    ch = wp.vec3i(k, ch[1], ch[2])
                elif axis == 1:
                    cl = wp.vec3i(cl[0], k, cl[2])
                    ch = wp.vec3i(ch[0], k, ch[2])
                else:
                    cl = wp.vec3i(cl[0], cl[1], k)
                    ch = wp.vec3i(ch[0], ch[1], k)
                if ch[0] < cl[0] or ch[1] < cl[1] or ch[2] < cl[2]:
                    continue
                for c in range(box_cell_count(cl, ch)):
                    _long_short_partners_in_cell(box_cell(cl, ch, c), x_in, i, group, strand_i, vi, p0, p1, lo_i,
                                                 hi_i, inv_width, sorted_entries, sorted_lo, sorted_hi, slot_end,
                                                 slot_count, table_mask, num_vertices, num_strands,
                                                 skip_root_segments, cutoff2, capacity, with_energy, xi, dhat, bp,
                                                 weight, variant, count_out, pairs_out, energy_out, gradient_out)
        # Long partners: every other long segment of i's batch item, the longer of the two
        # testing the pair (ties: the lower id). A walk of i's box grown by the longest half
        # length cost every long segment a metre-wide box once one line-search trial stretched a
        # segment to metres (0.7-1.6 s per evaluation, docs/contact.md 8); the list is a few
        # hundred per item in a drape (one list for the whole batch made this loop grow with the
        # square of the batch: docs/contact.md 11).
        first = long_list.shape[0] // 2 + group * segs_per_group
        for k in range(lane, long_count[group], LONG_LANES):
            j = long_list[first + k]
            if j == i:
                continue
            vj = (j // segs_per_strand) * num_vertices + j % segs_per_strand
            half_j = wp.length(wp.vec3(x_in[vj + 1]) - wp.vec3(x_in[vj])) * 0.5
            if half_j > half_i or (half_j == half_i and j < i):
                continue  # the longer one's thread (ties: the lower id's) tests the pair
            _write_pair_if_close(x_in, i, j, strand_i, vi, p0, p1, num_vertices, num_strands,
                                 skip_root_segments, cutoff2, capacity, with_energy, xi, dhat, bp, weight,
                                 variant, count_out, pairs_out, energy_out, gradient_out)


@wp.kernel
def pair_list_stale_kernel(
    # In:
    x_in: wp.array(dtype=Any),
    reference_in: wp.array(dtype=Any),
    threshold: Any,
    # Out:
    stale_out: wp.array(dtype=wp.int32),
):
    """stale_out[0] = 1 if vertex v is more than `threshold` from where the pair list was built
    (a Verlet list built at cutoff + skin holds every pair within the cutoff while no vertex has
    moved more than skin / 2: two segments' distance changes by at most their vertices' moves).
    """
    v = wp.tid()
    if wp.length_sq(x_in[v] - reference_in[v]) > threshold * threshold:
        stale_out[0] = 1
