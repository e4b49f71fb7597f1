"""Strand energy terms of HairFormer Section 3.4 (Eq. 7-11, 15, 16) with analytic gradients.

Each term is a pair of `@wp.func`s with the same arguments, evaluated on one element of a strand:
    edge e_i = p_{i+1} - p_i, |e_i|       stretch (Eq. 7), root alignment (Eq. 15)
    joint (e_i, e_{i+1}) at vertex i+1    bending (Eq. 8), smoothness (Eq. 10)
    vertex p                              auxiliary (Eq. 9), gravity (Eq. 11), inertia (Eq. 16)
`<term>_energy` returns the element's energy, `<term>_gradient` its gradient with respect to
the element's edges or vertex (`bending_energy_gradient` gives both, sharing the work). A
vertex's gradient follows from its edges' as dE/dp_j = G_{j-1} - G_j with G_i = dE/de_i, so
edge lengths are computed once per edge. Every function takes a `scale` that already holds the
term's weight and the equation's normalisation (1 / (M (N-1)) and so on), so an element's
energy sums directly into the total.

Two launch layouts share those funcs and compute all seven terms in one pass:
    `strand_energies_per_strand_kernel`  one thread per (batch, strand) walking its vertices;
        every element is evaluated once and its gradient is scattered into a three-vertex
        register window (best on the CPU, where Warp runs one thread).
    `strand_energies_per_vertex_kernel`  one thread per (batch, strand, vertex) gathering the
        gradient of the elements that touch its vertex, no atomics (best on the GPU).
Both write per-term energies per thread (term-major, in the order of
`hairwarp.config.STRAND_TERMS`) and the gradient of the weighted total into a `(B*M*N)` vec3
buffer. The gradient at vertices 0
and 1 of each strand is zero: the paper fixes them and excludes them from gradient computation
(their positions still enter the energies of Eq. 7-10 and 15).

All functions are generic over float32/float64 (`Any`); literals are cast with `type(x)`.
"""

from typing import Any

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES

# Gradients are hand-written beside each energy: no generated adjoints to compile.
wp.set_module_options({"enable_backward": False})

# Column of each term in the per-thread energy output (the order of config.STRAND_TERMS).
TERM_STRETCH = wp.constant(0)
TERM_BENDING = wp.constant(1)
TERM_AUXILIARY = wp.constant(2)
TERM_SMOOTHNESS = wp.constant(3)
TERM_GRAVITY = wp.constant(4)
TERM_ROOT_ALIGNMENT = wp.constant(5)
TERM_INERTIA = wp.constant(6)
NUM_TERMS = wp.constant(7)

# Vertices 0 (root) and 1 are fixed (Section 3.4): the first moving vertex.
FIRST_MOVING_VERTEX = wp.constant(NUM_FIXED_VERTICES)


# ---------------------------------------------------------------- stretch (Eq. 7), edge
@wp.func
def stretch_energy(e: Any, length: Any, rest: Any, scale: Any):
    """Scale * (|e| - l0)^2 for edge e = p_{i+1} - p_i of length |e|; scale = k_s / (M (N-1))."""
    r = length - rest
    return scale * r * r


@wp.func
def stretch_gradient(e: Any, length: Any, rest: Any, scale: Any):
    """d/de of `stretch_energy`.

    |e| has no derivative at e = 0 (coincident vertices): the zero subgradient is used there,
    so the result stays finite.
    """
    if length > type(length)(0.0):
        return e * (type(length)(2.0) * scale * (length - rest) / length)
    return e * type(length)(0.0)


# ---------------------------------------------------------------- bending (Eq. 8), joint
@wp.func
def _asin_small(r: wp.float32):
    """asin(r) for |r| <= 0.5: the Cephes asinf minimax polynomial (relative error ~1e-7)."""
    z = r * r
    p = wp.float32(4.2163199048e-2) * z + wp.float32(2.4181311049e-2)
    p = p * z + wp.float32(4.5470025998e-2)
    p = p * z + wp.float32(7.4953002686e-2)
    p = p * z + wp.float32(1.6666752422e-1)
    return r + r * (p * z)


@wp.func
def bending_acos(x: wp.float32):
    """Arccos for float32 on [-1, 1], inline (absolute error < 4e-7 rad).

    A call into the C library's acosf in the middle of the fused loop spills every live vector
    register (all are caller-saved) and made the bending term cost twice the others on the CPU.
    Cephes range reduction: acos(x) = 2 asin(sqrt((1 - x) / 2)) for x > 1/2, which also keeps
    the full relative precision of small angles near x = 1.
    """
    half = wp.float32(0.5)
    one = wp.float32(1.0)
    two = wp.float32(2.0)
    if x > half:
        return two * _asin_small(wp.sqrt(half * (one - x)))
    if x < -half:
        return wp.float32(3.14159265358979) - two * _asin_small(wp.sqrt(half * (one + x)))
    return wp.float32(1.57079632679490) - _asin_small(x)


@wp.func
def bending_acos(x: wp.float64):  # noqa: F811 (a Warp overload, chosen by argument type)
    """Arccos for float64: the C library's (the float64 path is for checks, not speed)."""
    return wp.acos(x)


@wp.func
def bending_edge_frame(e: Any, length: Any, eps: Any):
    """Per-edge factors of Eq. 8, shared by the two joints an edge belongs to.

    Returns (u, inv, ratio): u = e / (|e| + eps), inv = 1 / (|e| + eps), ratio = (|e| + eps) / |e|;
    all zero when |e| <= eps (C_valid fails), so `ratio > 0` marks a valid edge.
    """
    zero = type(eps)(0.0)
    if length > eps:
        inv = type(eps)(1.0) / (length + eps)
        return e * inv, inv, (length + eps) / length
    return e * zero, zero, zero


@wp.func
def bending_joint(
    u0: Any, inv0: Any, ratio0: Any, u1: Any, inv1: Any, ratio1: Any, eps: Any, scale: Any, with_energy: int
):
    """(energy, d/de0, d/de1) of a joint from its edges' `bending_edge_frame`s.

    The arccos is evaluated only when `with_energy` != 0 (the energy is zero otherwise). The
    gradient is zero where C_valid fails or where the clamp of Eq. 8 is active (arccos of a
    clamped constant), so a straight or folded joint never produces 1 / sqrt(1 - theta^2) = inf.
    """
    zero = type(eps)(0.0)
    one = type(eps)(1.0)
    gz = u0 * zero
    if ratio0 > zero and ratio1 > zero:
        theta = wp.dot(u0, u1)
        energy = zero
        if with_energy != 0:
            energy = scale * bending_acos(wp.clamp(theta, -one + eps, one - eps))
        if theta > -one + eps and theta < one - eps:
            dalpha = -scale / wp.sqrt((one - theta) * (one + theta))
            # d theta / d e0 = (u1 - e0_hat (e0_hat . u1) |e0| / (|e0| + eps)) / (|e0| + eps)
            #                = (u1 - u0 theta (|e0| + eps) / |e0|) / (|e0| + eps),
            # and the same with the edges swapped for e1.
            g0 = (u1 - u0 * (theta * ratio0)) * (dalpha * inv0)
            g1 = (u0 - u1 * (theta * ratio1)) * (dalpha * inv1)
            return energy, g0, g1
        return energy, gz, gz
    return zero, gz, gz


@wp.func
def bending_energy(e0: Any, l0: Any, e1: Any, l1: Any, eps: Any, scale: Any):
    """Scale * alpha, the turning angle between edges e0 = e_i and e1 = e_{i+1} (scale = k_b).

    theta = e0 / (|e0| + eps) . e1 / (|e1| + eps), alpha = arccos(clamp(theta, -1 + eps,
    1 - eps)), and alpha = 0 unless both edges are longer than eps (C_valid of Eq. 8).
    """
    u0, inv0, ratio0 = bending_edge_frame(e0, l0, eps)
    u1, inv1, ratio1 = bending_edge_frame(e1, l1, eps)
    energy, g0, g1 = bending_joint(u0, inv0, ratio0, u1, inv1, ratio1, eps, scale, 1)
    return energy


@wp.func
def bending_energy_gradient(e0: Any, l0: Any, e1: Any, l1: Any, eps: Any, scale: Any):
    """(energy, d/de0, d/de1) of `bending_energy` in one evaluation."""
    u0, inv0, ratio0 = bending_edge_frame(e0, l0, eps)
    u1, inv1, ratio1 = bending_edge_frame(e1, l1, eps)
    return bending_joint(u0, inv0, ratio0, u1, inv1, ratio1, eps, scale, 1)


# ---------------------------------------------------------------- smoothness (Eq. 10), joint
@wp.func
def smoothness_energy(e0: Any, e1: Any, scale: Any):
    """Scale * |p_{v+1} - 2 p_v + p_{v-1}|^2 = scale * |e1 - e0|^2; scale = lambda_smooth / (M (N-2))."""
    r = e1 - e0
    return scale * wp.dot(r, r)


@wp.func
def smoothness_gradient(e0: Any, e1: Any, scale: Any):
    """(d/de0, d/de1) of `smoothness_energy`."""
    g = (e1 - e0) * (type(scale)(2.0) * scale)
    return -g, g


# ---------------------------------------------------------------- root alignment (Eq. 15), edge
@wp.func
def root_alignment_energy(e: Any, length: Any, normal: Any, eps: Any, scale: Any):
    """-scale * d_hat . n for one of the first k' moving edges; scale = lambda_root / (M k').

    d_hat = e / (|e| + eps_norm). The constant lambda_root / M per strand of Eq. 15 is added
    by the caller. With eps = 0 and e = 0, d_hat is taken as 0.
    """
    denom = length + eps
    if denom > type(eps)(0.0):
        return -scale * wp.dot(e, normal) / denom
    return type(eps)(0.0)


@wp.func
def root_alignment_gradient(e: Any, length: Any, normal: Any, eps: Any, scale: Any):
    """d/de of `root_alignment_energy`.

    d(e . n / (|e| + eps))/de = n / (|e| + eps) - e_hat (e_hat . n) |e| / (|e| + eps)^2; the
    second part tends to zero with |e|, so it is dropped at e = 0 and the gradient stays
    continuous there (n / eps).
    """
    zero = type(eps)(0.0)
    denom = length + eps
    if denom > zero:
        g = normal / denom
        if length > zero:
            g = g - e * (wp.dot(e, normal) / (length * denom * denom))
        return g * (-scale)
    return e * zero


# ---------------------------------------------------------------- auxiliary (Eq. 9), vertex
@wp.func
def auxiliary_energy(p: Any, rigid: Any, scale: Any):
    """Scale * |p - p_rigid|^2; scale = lambda_aux / (3 M N)."""
    d = p - rigid
    return scale * wp.dot(d, d)


@wp.func
def auxiliary_gradient(p: Any, rigid: Any, scale: Any):
    """d/dp of `auxiliary_energy`."""
    return (p - rigid) * (type(scale)(2.0) * scale)


# ---------------------------------------------------------------- gravity (Eq. 11), vertex
@wp.func
def gravity_energy(p: Any, weight_g: Any, mass: Any):
    """-mass (weight g) . p of a moving vertex [J]; `weight_g` = gravity_weight * g."""
    return -mass * wp.dot(weight_g, p)


@wp.func
def gravity_gradient(p: Any, weight_g: Any, mass: Any):
    """d/dp of `gravity_energy`: the weighted weight force, negated."""
    return weight_g * (-mass)


# ---------------------------------------------------------------- inertia (Eq. 16), vertex
@wp.func
def inertia_energy(p: Any, projected: Any, mass: Any, scale: Any):
    """Scale * mass * |p - p_proj|^2; scale = lambda_inertia / (M N_mov 2 dt^2).

    p_proj = 2 p(t-1) - p(t-2) is a constant input (stop-gradient, Section 3.4.5).
    """
    d = p - projected
    return scale * mass * wp.dot(d, d)


@wp.func
def inertia_gradient(p: Any, projected: Any, mass: Any, scale: Any):
    """d/dp of `inertia_energy`; nothing flows to p(t-1), p(t-2)."""
    return (p - projected) * (type(scale)(2.0) * scale * mass)


# ---------------------------------------------------------------- shared by both layouts
@wp.func
def vertex_mass(mass: wp.array(dtype=Any), use_mass_array: int, mass_value: Any, index: int):
    """Mass of a vertex [kg]: per vertex (an M*N array shared by the batch) or one scalar."""
    if use_mass_array != 0:
        return mass[index]
    return mass_value


@wp.func
def edge_gradient(
    e: Any,
    length: Any,
    edge: int,
    rest: Any,
    stretch_scale: Any,
    normal: Any,
    root_scale: Any,
    root_eps: Any,
    root_segments: int,
):
    """d/de of the edge terms (stretch, root alignment) of edge `edge` (0-based)."""
    zero = stretch_scale * type(stretch_scale)(0.0)
    g = e * zero
    if stretch_scale != zero:
        g += stretch_gradient(e, length, rest, stretch_scale)
    # Eq. 15 sums edges i = 1..k' (p_i -> p_{i+1}).
    if root_scale != zero and edge >= 1 and edge <= root_segments:
        g += root_alignment_gradient(e, length, normal, root_eps, root_scale)
    return g


@wp.func
def vertex_terms_gradient(
    p: Any,
    rigid: Any,
    auxiliary_scale: Any,
    weight_g: Any,
    gravity_on: int,
    projected: Any,
    inertia_scale: Any,
    mass: Any,
):
    """d/dp of the vertex terms (auxiliary, gravity, inertia) of a moving vertex."""
    zero = auxiliary_scale * type(auxiliary_scale)(0.0)
    g = p * zero
    if auxiliary_scale != zero:
        g += auxiliary_gradient(p, rigid, auxiliary_scale)
    if gravity_on != 0:
        g += gravity_gradient(p, weight_g, mass)
    if inertia_scale != zero:
        g += inertia_gradient(p, projected, mass, inertia_scale)
    return g


@wp.func
def write_energies(
    energy_out: wp.array(dtype=Any),
    thread: int,
    stretch: Any,
    bending: Any,
    auxiliary: Any,
    smoothness: Any,
    gravity: Any,
    root_alignment: Any,
    inertia: Any,
):
    """Store a thread's per-term energies term-major, energy_out[term * threads + thread].

    Term-major keeps neighbouring threads' stores contiguous (coalesced on the GPU).
    """
    threads = energy_out.shape[0] / NUM_TERMS
    energy_out[TERM_STRETCH * threads + thread] = stretch
    energy_out[TERM_BENDING * threads + thread] = bending
    energy_out[TERM_AUXILIARY * threads + thread] = auxiliary
    energy_out[TERM_SMOOTHNESS * threads + thread] = smoothness
    energy_out[TERM_GRAVITY * threads + thread] = gravity
    energy_out[TERM_ROOT_ALIGNMENT * threads + thread] = root_alignment
    energy_out[TERM_INERTIA * threads + thread] = inertia


# ---------------------------------------------------------------- fused kernels
@wp.kernel
def strand_energies_per_strand_kernel(
    # In:
    x: wp.array(dtype=Any),
    rest: wp.array(dtype=Any),
    rest_batch_stride: int,
    rigid: wp.array(dtype=Any),
    rigid_batch_stride: int,
    normals: wp.array(dtype=Any),
    normals_batch_stride: int,
    prev: wp.array(dtype=Any),
    prev_batch_stride: int,
    prev2: wp.array(dtype=Any),
    prev2_batch_stride: int,
    mass: wp.array(dtype=Any),
    use_mass_array: int,
    mass_value: Any,
    weight_g: Any,
    stretch_scale: Any,
    bending_scale: Any,
    bending_eps: Any,
    auxiliary_scale: Any,
    smoothness_scale: Any,
    gravity_on: int,
    root_scale: Any,
    root_constant: Any,
    root_eps: Any,
    root_segments: int,
    inertia_scale: Any,
    num_strands: int,
    num_vertices: int,
    compute_gradient: int,
    # Out:
    energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """One thread per (batch b, strand s): thread b M + s writes its strand's energies.

    Positions and gradients are flat (B*M*N) vec3 arrays; an input whose batch stride is 0 is
    shared by the batch. A zero scale (or `gravity_on` = 0) skips a term's work. Every edge
    and joint is evaluated once: edge gradients G_i = dE/de_i accumulate in registers, and
    dE/dp_j = (vertex terms) + G_{j-1} - G_j is written once edge j is complete.
    """
    row = wp.tid()
    b = row / num_strands
    s = row - b * num_strands
    n = num_vertices
    base = row * n
    zero = stretch_scale * type(stretch_scale)(0.0)
    two = type(zero)(2.0)
    gz = type(x[base])()
    nrm = gz
    if root_scale != zero:
        nrm = normals[b * normals_batch_stride + s]
    rest_base = b * rest_batch_stride + s * (n - 1)
    e_stretch = zero
    e_bending = zero
    e_auxiliary = zero
    e_smoothness = zero
    e_gravity = zero
    e_root = zero
    e_inertia = zero
    # Sliding window at step k: vertex terms' gradients of vertices k-2 (gv_a) and k-1 (gv_b);
    # edge gradients of edges k-3 (grad_a, complete) and k-2 (grad_b, waiting for the joint
    # of edges k-2 and k-1); edge k-2 itself (e_b) and its bending frame (u_b, inv_b, ratio_b).
    gv_a = gz
    gv_b = gz
    grad_a = gz
    grad_b = gz
    e_b = gz
    u_b = gz
    inv_b = zero
    ratio_b = zero
    p_prev = x[base]
    for k in range(n):
        pk = x[base + k]
        v_index = s * n + k
        gv_k = gz
        q = gz
        if auxiliary_scale != zero:
            q = rigid[b * rigid_batch_stride + v_index]
            e_auxiliary += auxiliary_energy(pk, q, auxiliary_scale)
        proj = gz
        m = zero
        if k >= FIRST_MOVING_VERTEX:
            m = vertex_mass(mass, use_mass_array, mass_value, v_index)
            if gravity_on != 0:
                e_gravity += gravity_energy(pk, weight_g, m)
            if inertia_scale != zero:
                proj = two * prev[b * prev_batch_stride + v_index] - prev2[b * prev2_batch_stride + v_index]
                e_inertia += inertia_energy(pk, proj, m, inertia_scale)
            if compute_gradient != 0:
                gv_k = vertex_terms_gradient(
                    pk, q, auxiliary_scale, weight_g, gravity_on, proj, inertia_scale, m
                )
        if k >= 1:
            # Edge k-1: p_{k-1} -> p_k.
            e_c = pk - p_prev
            l_c = wp.length(e_c)
            l0 = zero
            if stretch_scale != zero:
                l0 = rest[rest_base + k - 1]
                e_stretch += stretch_energy(e_c, l_c, l0, stretch_scale)
            if root_scale != zero and k - 1 >= 1 and k - 1 <= root_segments:
                e_root += root_alignment_energy(e_c, l_c, nrm, root_eps, root_scale)
            grad_c = gz
            if compute_gradient != 0:
                grad_c = edge_gradient(
                    e_c, l_c, k - 1, l0, stretch_scale, nrm, root_scale, root_eps, root_segments
                )
            u_c = gz
            inv_c = zero
            ratio_c = zero
            if bending_scale != zero:
                u_c, inv_c, ratio_c = bending_edge_frame(e_c, l_c, bending_eps)
            if k >= 2:
                # Joint between edges k-2 and k-1 (centred at vertex k-1).
                if bending_scale != zero:
                    eb, g0, g1 = bending_joint(
                        u_b, inv_b, ratio_b, u_c, inv_c, ratio_c, bending_eps, bending_scale, 1
                    )
                    e_bending += eb
                    grad_b += g0
                    grad_c += g1
                if smoothness_scale != zero:
                    e_smoothness += smoothness_energy(e_b, e_c, smoothness_scale)
                    if compute_gradient != 0:
                        g0, g1 = smoothness_gradient(e_b, e_c, smoothness_scale)
                        grad_b += g0
                        grad_c += g1
                # Edge k-2 is complete: vertex k-2 is final.
                if compute_gradient != 0:
                    if k - 2 >= FIRST_MOVING_VERTEX:
                        gradient_out[base + k - 2] = gv_a + grad_a - grad_b
                    else:
                        gradient_out[base + k - 2] = gz
            grad_a = grad_b
            grad_b = grad_c
            e_b = e_c
            u_b = u_c
            inv_b = inv_c
            ratio_b = ratio_c
        gv_a = gv_b
        gv_b = gv_k
        p_prev = pk
    if compute_gradient != 0:
        # n >= 3; vertex n-2 is fixed only when n = 3.
        if n - 2 >= FIRST_MOVING_VERTEX:
            gradient_out[base + n - 2] = gv_a + grad_a - grad_b
        else:
            gradient_out[base + n - 2] = gz
        gradient_out[base + n - 1] = gv_b + grad_b
    if root_scale != zero:
        e_root += root_constant
    write_energies(
        energy_out, row, e_stretch, e_bending, e_auxiliary, e_smoothness, e_gravity, e_root, e_inertia
    )


@wp.kernel
def strand_energies_per_vertex_kernel(
    # In:
    x: wp.array(dtype=Any),
    rest: wp.array(dtype=Any),
    rest_batch_stride: int,
    rigid: wp.array(dtype=Any),
    rigid_batch_stride: int,
    normals: wp.array(dtype=Any),
    normals_batch_stride: int,
    prev: wp.array(dtype=Any),
    prev_batch_stride: int,
    prev2: wp.array(dtype=Any),
    prev2_batch_stride: int,
    mass: wp.array(dtype=Any),
    use_mass_array: int,
    mass_value: Any,
    weight_g: Any,
    stretch_scale: Any,
    bending_scale: Any,
    bending_eps: Any,
    auxiliary_scale: Any,
    smoothness_scale: Any,
    gravity_on: int,
    root_scale: Any,
    root_constant: Any,
    root_eps: Any,
    root_segments: int,
    inertia_scale: Any,
    num_strands: int,
    num_vertices: int,
    compute_gradient: int,
    # Out:
    energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """One thread per (batch b, strand s, vertex v): thread (b M + s) N + v writes its energies.

    Vertex v owns (writes the energy of) its vertex terms, edge v (p_v -> p_{v+1}) and the
    joint centred at v, so each element is counted once. Its gradient gathers everything that
    touches it, dE/dp_v = (vertex terms) + G_{v-1} - G_v with G_i = dE/de_i from edge i and the
    joints on either side of it, so no two threads write the same address (no atomics).
    """
    tid = wp.tid()
    n = num_vertices
    row = tid / n
    v = tid - row * n
    b = row / num_strands
    s = row - b * num_strands
    v_index = s * n + v
    zero = stretch_scale * type(stretch_scale)(0.0)
    two = type(zero)(2.0)
    p = x[tid]
    gz = type(p)()
    moving = v >= FIRST_MOVING_VERTEX and compute_gradient != 0
    rest_base = b * rest_batch_stride + s * (n - 1)
    nrm = gz
    if root_scale != zero:
        nrm = normals[b * normals_batch_stride + s]
    e_stretch = zero
    e_bending = zero
    e_auxiliary = zero
    e_smoothness = zero
    e_gravity = zero
    e_root = zero
    e_inertia = zero

    # Vertex terms (Eq. 9, 11, 16).
    q = gz
    if auxiliary_scale != zero:
        q = rigid[b * rigid_batch_stride + v_index]
        e_auxiliary = auxiliary_energy(p, q, auxiliary_scale)
    g = gz
    if v >= FIRST_MOVING_VERTEX:
        m = vertex_mass(mass, use_mass_array, mass_value, v_index)
        proj = gz
        if gravity_on != 0:
            e_gravity = gravity_energy(p, weight_g, m)
        if inertia_scale != zero:
            proj = two * prev[b * prev_batch_stride + v_index] - prev2[b * prev2_batch_stride + v_index]
            e_inertia = inertia_energy(p, proj, m, inertia_scale)
        if moving:
            g = vertex_terms_gradient(p, q, auxiliary_scale, weight_g, gravity_on, proj, inertia_scale, m)
    if v == 0 and root_scale != zero:
        e_root = root_constant

    # Edges v-2, v-1, v, v+1 around the vertex (those that exist).
    e_v = gz
    l_v = zero
    rest_v = zero
    if v + 1 < n:
        e_v = x[tid + 1] - p
        l_v = wp.length(e_v)
        if stretch_scale != zero:
            rest_v = rest[rest_base + v]
            e_stretch = stretch_energy(e_v, l_v, rest_v, stretch_scale)
        if root_scale != zero and v >= 1 and v <= root_segments:
            e_root = root_alignment_energy(e_v, l_v, nrm, root_eps, root_scale)
    e_m = gz
    l_m = zero
    if v >= 1:
        e_m = p - x[tid - 1]
        l_m = wp.length(e_m)
        if v + 1 < n:
            # The joint centred at v, between edges v-1 and v.
            if smoothness_scale != zero:
                e_smoothness = smoothness_energy(e_m, e_v, smoothness_scale)
            if bending_scale != zero and not moving:
                e_bending = bending_energy(e_m, l_m, e_v, l_v, bending_eps, bending_scale)

    if moving:
        # G_{v-1} (edge v-1, joints (v-2, v-1) and (v-1, v)) and G_v (edge v, joints (v-1, v)
        # and (v, v+1)). Inputs of a term that is off are never read: they may be a one-element
        # placeholder.
        rest_m = zero
        if stretch_scale != zero:
            rest_m = rest[rest_base + v - 1]
        grad_m = edge_gradient(
            e_m, l_m, v - 1, rest_m, stretch_scale, nrm, root_scale, root_eps, root_segments
        )
        grad_v = gz
        has_v = v + 1 < n
        has_p = v + 2 < n
        if has_v:
            grad_v = edge_gradient(
                e_v, l_v, v, rest_v, stretch_scale, nrm, root_scale, root_eps, root_segments
            )
        e_mm = x[tid - 1] - x[tid - 2]
        e_p = gz
        if has_p:
            e_p = x[tid + 2] - x[tid + 1]
        if smoothness_scale != zero:
            g0, g1 = smoothness_gradient(e_mm, e_m, smoothness_scale)
            grad_m += g1
            if has_v:
                g0, g1 = smoothness_gradient(e_m, e_v, smoothness_scale)
                grad_m += g0
                grad_v += g1
            if has_p:
                g0, g1 = smoothness_gradient(e_v, e_p, smoothness_scale)
                grad_v += g0
        if bending_scale != zero:
            # Each edge's frame once; the owned joint (v-1, v) also gives its energy.
            u_mm, inv_mm, ratio_mm = bending_edge_frame(e_mm, wp.length(e_mm), bending_eps)
            u_m, inv_m, ratio_m = bending_edge_frame(e_m, l_m, bending_eps)
            eb, g0, g1 = bending_joint(
                u_mm, inv_mm, ratio_mm, u_m, inv_m, ratio_m, bending_eps, bending_scale, 0
            )
            grad_m += g1
            if has_v:
                u_v, inv_v, ratio_v = bending_edge_frame(e_v, l_v, bending_eps)
                eb, g0, g1 = bending_joint(
                    u_m, inv_m, ratio_m, u_v, inv_v, ratio_v, bending_eps, bending_scale, 1
                )
                e_bending = eb
                grad_m += g0
                grad_v += g1
                if has_p:
                    u_p, inv_p, ratio_p = bending_edge_frame(e_p, wp.length(e_p), bending_eps)
                    eb, g0, g1 = bending_joint(
                        u_v, inv_v, ratio_v, u_p, inv_p, ratio_p, bending_eps, bending_scale, 0
                    )
                    grad_v += g0
        g += grad_m - grad_v

    if compute_gradient != 0:
        gradient_out[tid] = g
    write_energies(
        energy_out, tid, e_stretch, e_bending, e_auxiliary, e_smoothness, e_gravity, e_root, e_inertia
    )
