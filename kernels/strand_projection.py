"""Follow-the-leader length projection of strands (Mueller et al. 2012, "Fast Simulation of
Inextensible Hair and Fur"), forward and hand-written adjoint, one thread per strand.

Given the rigid placement r (whose segment lengths are the rest lengths l_i = |r_i - r_{i-1}|)
and target positions q (the rigid placement plus a network's tapered deformation, Eq. 2), the
projection walks each strand from the root:

    x_k = q_k                                   for the fixed vertices k < NUM_FIXED_VERTICES
    x_i = x_{i-1} + l_i * (q_i - x_{i-1}) / |q_i - x_{i-1}|      for i >= NUM_FIXED_VERTICES

so every segment keeps its rest length exactly and the deformation only bends the strand. A
target on top of its leader (|q_i - x_{i-1}| below `eps`) keeps the rigid segment direction.

Adjoint (reverse walk; J = (I - u u^T) / |d| the Jacobian of u = d / |d|): with G_i the total
gradient reaching x_i (its own plus what x_{i+1} passed back),
    dL/dq_i = l_i J G_i,   G_{i-1} = g_{i-1} + G_i - dL/dq_i.
"""

import functools
from typing import Any

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES

wp.set_module_options({"enable_backward": False})

FIRST_PROJECTED_VERTEX = wp.constant(NUM_FIXED_VERTICES)


@wp.func
def follow_the_leader_step(leader: Any, target: Any, rest_edge: Any, eps: Any):
    """x_i from its leader x_{i-1}, its target q_i and its rigid edge r_i - r_{i-1}."""
    d = target - leader
    n = wp.length(d)
    if n > eps:
        return leader + d * (wp.length(rest_edge) / n)
    return leader + rest_edge


@wp.kernel
def follow_the_leader_kernel(
    rigid: wp.array(dtype=Any),
    target: wp.array(dtype=Any),
    num_vertices: int,
    eps: Any,
    out: wp.array(dtype=Any),
):
    """Projected positions of one strand (thread = batch * M + strand); arrays are (B*M*N,) vec3.

    The walk is sequential, so its speed is the latency of its loads: they are issued four
    vertices at a time, ahead of the stores (a store before a load of another array could
    alias it, which keeps the compiler from hoisting the load: one memory round trip per vertex,
    125 us for 1024 x 100 hair on an H100, against ~4x less in chunks).
    """
    base = wp.tid() * num_vertices
    for k in range(FIRST_PROJECTED_VERTEX):
        out[base + k] = target[base + k]
    leader = target[base + FIRST_PROJECTED_VERTEX - 1]
    i = int(FIRST_PROJECTED_VERTEX)
    while i + 4 <= num_vertices:
        r0 = rigid[base + i - 1]
        r1 = rigid[base + i]
        r2 = rigid[base + i + 1]
        r3 = rigid[base + i + 2]
        r4 = rigid[base + i + 3]
        q1 = target[base + i]
        q2 = target[base + i + 1]
        q3 = target[base + i + 2]
        q4 = target[base + i + 3]
        x1 = follow_the_leader_step(leader, q1, r1 - r0, eps)
        x2 = follow_the_leader_step(x1, q2, r2 - r1, eps)
        x3 = follow_the_leader_step(x2, q3, r3 - r2, eps)
        leader = follow_the_leader_step(x3, q4, r4 - r3, eps)
        out[base + i] = x1
        out[base + i + 1] = x2
        out[base + i + 2] = x3
        out[base + i + 3] = leader
        i += 4
    while i < num_vertices:
        leader = follow_the_leader_step(leader, target[base + i], rigid[base + i] - rigid[base + i - 1], eps)
        out[base + i] = leader
        i += 1


@wp.func
def follow_the_leader_adjoint_step(g: Any, rest_edge: Any, target: Any, leader: Any, eps: Any, max_gain: Any):
    """dL/dq_i from G_i (`g`), the rigid edge r_i - r_{i-1}, q_i and the projected leader x_{i-1}.

    d x_i / d q_i = gain (I - u u^T) with gain = l_i / |q_i - x_{i-1}|, capped at `max_gain`:
    the exact gain grows without bound as a target nears its leader (training's option; the
    exact adjoint passes a cap no gain reaches).
    """
    d = target - leader
    n = wp.length(d)
    if n > eps:
        u = d / n
        gain = wp.min(wp.length(rest_edge) / n, max_gain)
        return (g - u * wp.dot(u, g)) * gain
    return g * type(eps)(0.0)


@wp.kernel
def follow_the_leader_adjoint_kernel(
    rigid: wp.array(dtype=Any),
    target: wp.array(dtype=Any),
    projected: wp.array(dtype=Any),
    grad_out: wp.array(dtype=Any),
    num_vertices: int,
    eps: Any,
    max_gain: Any,
    grad_target: wp.array(dtype=Any),
):
    """dL/dq of one strand from dL/dx (`grad_out`) and the forward's output `projected`.

    Walked from the tip, four vertices at a time with their loads issued ahead of the stores
    (as the forward: one memory round trip per vertex otherwise).
    """
    base = wp.tid() * num_vertices
    carry = grad_out[base] * type(eps)(0.0)  # a zero of the vector type
    i = num_vertices - 1
    while i - 3 >= FIRST_PROJECTED_VERTEX:
        g0 = grad_out[base + i]
        g1 = grad_out[base + i - 1]
        g2 = grad_out[base + i - 2]
        g3 = grad_out[base + i - 3]
        r0 = rigid[base + i]
        r1 = rigid[base + i - 1]
        r2 = rigid[base + i - 2]
        r3 = rigid[base + i - 3]
        r4 = rigid[base + i - 4]
        q0 = target[base + i]
        q1 = target[base + i - 1]
        q2 = target[base + i - 2]
        q3 = target[base + i - 3]
        p1 = projected[base + i - 1]
        p2 = projected[base + i - 2]
        p3 = projected[base + i - 3]
        p4 = projected[base + i - 4]
        G0 = g0 + carry
        d0 = follow_the_leader_adjoint_step(G0, r0 - r1, q0, p1, eps, max_gain)
        G1 = g1 + G0 - d0
        d1 = follow_the_leader_adjoint_step(G1, r1 - r2, q1, p2, eps, max_gain)
        G2 = g2 + G1 - d1
        d2 = follow_the_leader_adjoint_step(G2, r2 - r3, q2, p3, eps, max_gain)
        G3 = g3 + G2 - d2
        d3 = follow_the_leader_adjoint_step(G3, r3 - r4, q3, p4, eps, max_gain)
        carry = G3 - d3
        grad_target[base + i] = d0
        grad_target[base + i - 1] = d1
        grad_target[base + i - 2] = d2
        grad_target[base + i - 3] = d3
        i = i - 4
    while i >= FIRST_PROJECTED_VERTEX:
        g = grad_out[base + i] + carry
        gd = follow_the_leader_adjoint_step(g, rigid[base + i] - rigid[base + i - 1], target[base + i],
                                            projected[base + i - 1], eps, max_gain)
        grad_target[base + i] = gd
        carry = g - gd
        i = i - 1
    for k in range(FIRST_PROJECTED_VERTEX):
        grad_target[base + k] = grad_out[base + k]
    grad_target[base + FIRST_PROJECTED_VERTEX - 1] = grad_out[base + FIRST_PROJECTED_VERTEX - 1] + carry


# A tile kernel holds its strand in shared memory: 5 arrays of N vectors (the adjoint's four inputs
# and its output). Strands longer than this many bytes of it run the one-thread kernels above.
TILED_MAX_SHARED_BYTES = 40 * 1024
# Threads a block of the tile kernels: they load and store the strand together; the walk itself is
# one chain that every thread of the block runs in step (shared-memory reads, no divergence).
TILED_BLOCK_DIM = 32


@functools.lru_cache(maxsize=None)
def follow_the_leader_tiled_kernels(num_vertices: int, vec_type):
    """(forward, adjoint) tile kernels of the projection for strands of `num_vertices` vertices
    of `vec_type` (wp.vec3f or wp.vec3d): a block per strand, launched with
    `block_dim=TILED_BLOCK_DIM`, arrays (B*M*N,) vec3 as in the kernels above.

    The one-thread kernels walk a strand with a memory round trip every few vertices (latency
    bound: 1 024 threads on a GPU of 132 SMs): on one H100, 1 024 x 100 hair, 116 us forward and
    160 us adjoint. Here the block loads the strand into shared memory in one coalesced pass, the
    walk reads it there and the block stores the result: 18 us and 34 us
    (docs/physics.md, section 1). Compiled once per vertex count and type.
    """
    n = int(num_vertices)
    scalar = vec_type._wp_scalar_type_

    def forward(rigid: wp.array(dtype=vec_type), target: wp.array(dtype=vec_type), eps: scalar,
                out: wp.array(dtype=vec_type)):
        strand, _lane = wp.tid()
        base = strand * n
        r = wp.tile_load(rigid, shape=n, offset=base, storage="shared")
        q = wp.tile_load(target, shape=n, offset=base, storage="shared")
        x = wp.tile_zeros(shape=n, dtype=vec_type, storage="shared")
        for k in range(FIRST_PROJECTED_VERTEX):
            x[k] = q[k]
        leader = q[FIRST_PROJECTED_VERTEX - 1]
        for i in range(FIRST_PROJECTED_VERTEX, n):
            leader = follow_the_leader_step(leader, q[i], r[i] - r[i - 1], eps)
            x[i] = leader
        wp.tile_store(out, x, offset=base)

    def adjoint(rigid: wp.array(dtype=vec_type), target: wp.array(dtype=vec_type),
                projected: wp.array(dtype=vec_type), grad_out: wp.array(dtype=vec_type), eps: scalar,
                max_gain: scalar, grad_target: wp.array(dtype=vec_type)):
        strand, _lane = wp.tid()
        base = strand * n
        r = wp.tile_load(rigid, shape=n, offset=base, storage="shared")
        q = wp.tile_load(target, shape=n, offset=base, storage="shared")
        p = wp.tile_load(projected, shape=n, offset=base, storage="shared")
        g = wp.tile_load(grad_out, shape=n, offset=base, storage="shared")
        dq = wp.tile_zeros(shape=n, dtype=vec_type, storage="shared")
        carry = vec_type()
        for j in range(n - FIRST_PROJECTED_VERTEX):
            i = n - 1 - j
            total = g[i] + carry
            d = follow_the_leader_adjoint_step(total, r[i] - r[i - 1], q[i], p[i - 1], eps, max_gain)
            dq[i] = d
            carry = total - d
        for k in range(FIRST_PROJECTED_VERTEX):
            dq[k] = g[k]
        dq[FIRST_PROJECTED_VERTEX - 1] = g[FIRST_PROJECTED_VERTEX - 1] + carry
        wp.tile_store(grad_target, dq, offset=base)

    kernel = functools.partial(wp.kernel, enable_backward=False, module="unique")
    return kernel()(forward), kernel()(adjoint)
