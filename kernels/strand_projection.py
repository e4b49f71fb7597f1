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

from typing import Any

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES

wp.set_module_options({"enable_backward": False})

FIRST_PROJECTED_VERTEX = wp.constant(NUM_FIXED_VERTICES)


@wp.kernel
def follow_the_leader_kernel(
    rigid: wp.array(dtype=Any),
    target: wp.array(dtype=Any),
    num_vertices: int,
    eps: Any,
    out: wp.array(dtype=Any),
):
    """Projected positions of one strand (thread = batch * M + strand); arrays are (B*M*N,) vec3."""
    base = wp.tid() * num_vertices
    for k in range(FIRST_PROJECTED_VERTEX):
        out[base + k] = target[base + k]
    leader = out[base + FIRST_PROJECTED_VERTEX - 1]
    for i in range(FIRST_PROJECTED_VERTEX, num_vertices):
        rest_edge = rigid[base + i] - rigid[base + i - 1]
        rest = wp.length(rest_edge)
        d = target[base + i] - leader
        n = wp.length(d)
        if n > eps:
            leader = leader + d * (rest / n)
        else:
            leader = leader + rest_edge
        out[base + i] = leader


@wp.kernel
def follow_the_leader_adjoint_kernel(
    rigid: wp.array(dtype=Any),
    target: wp.array(dtype=Any),
    projected: wp.array(dtype=Any),
    grad_out: wp.array(dtype=Any),
    num_vertices: int,
    eps: Any,
    grad_target: wp.array(dtype=Any),
):
    """dL/dq of one strand from dL/dx (`grad_out`) and the forward's output `projected`."""
    base = wp.tid() * num_vertices
    carry = grad_out[base] * type(eps)(0.0)  # a zero of the vector type
    i = num_vertices - 1
    while i >= FIRST_PROJECTED_VERTEX:
        g = grad_out[base + i] + carry
        rest = wp.length(rigid[base + i] - rigid[base + i - 1])
        d = target[base + i] - projected[base + i - 1]
        n = wp.length(d)
        gd = g * type(eps)(0.0)
        if n > eps:
            u = d / n
            du = g * rest
            gd = (du - u * wp.dot(u, du)) / n
        grad_target[base + i] = gd
        carry = g - gd
        i = i - 1
    for k in range(FIRST_PROJECTED_VERTEX):
        grad_target[base + k] = grad_out[base + k]
    grad_target[base + FIRST_PROJECTED_VERTEX - 1] = grad_out[base + FIRST_PROJECTED_VERTEX - 1] + carry
