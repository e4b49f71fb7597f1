"""Unsigned distances between primitives, with their gradients (used by the contact terms).

`d` in HairFormer Eq. 12 is, for hair-hair contact, the distance between two hair segments;
these functions compute it (and the point-triangle distance used for the body).

Method (ipc-toolkit style, made branch-robust):
    A distance between two convex primitives is the minimum of a convex quadratic over a box
    or a triangle of parameters. The minimum is either interior (the stationary point) or on
    the boundary, where it reduces to point-segment distances with clamped projections. We
    evaluate every boundary candidate plus, when the primitives are not degenerate, the
    interior one, and keep the smallest. Every candidate is a valid pair of points on the
    primitives, so even an inaccurate interior solve (near-parallel segments) can only lose to
    a better candidate, never return a distance that is too small; parallel, crossing and
    zero-length segments need no special branch beyond skipping a division by zero.

Gradient (envelope theorem):
    with the closest parameters held fixed, d = |x_p - x_q| where x_p, x_q are the closest
    points, barycentric combinations of the endpoints. At the minimum, moving a parameter
    changes d only to second order (interior) or not at all (clamped), so
    dd/dendpoint = +-(barycentric weight) * n with n = (x_p - x_q) / d. Exact wherever the
    closest pair is unique and d > 0. When the closest points are interior to both primitives
    (segments: 0 < s, t < 1; triangle: face region), x_p - x_q lies exactly along the unit
    normal of the two directions (or of the triangle), so n is taken as that normal, signed:
    the same value, but exact even when d is at rounding level.
    At d = 0 (touching or crossing) d is not differentiable; we return the subgradient with
    n = that unit normal, the direction in which a small separation grows d linearly; n = 0
    when the normal is degenerate too (parallel segments touching, zero-area triangles).

Positions are taken relative to a local origin (the first point) before any product, so the
float32 distances of millimetre gaps stay accurate for hair far from the world origin.

All functions are generic over float32/float64 (`Any`, vec3 or vec3d).
"""

from typing import Any

import warp as wp

# Gradients are hand-written (envelope theorem): no generated adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.func
def _clamp01(x: Any):
    return wp.min(wp.max(x, type(x)(0.0)), type(x)(1.0))


@wp.func
def point_segment_parameter(r: Any, e: Any):
    """Clamped parameter t in [0, 1] of the point of segment (0, e) closest to r.

    Zero-length segments (e = 0) give t = 0.
    """
    ee = wp.dot(e, e)
    t = type(ee)(0.0)
    if ee > type(ee)(0.0):
        t = _clamp01(wp.dot(r, e) / ee)
    return t


@wp.func
def _unit_or_zero(v: Any):
    """V / |v|, or the zero vector when |v| = 0 (the subgradient choice at contact)."""
    n2 = wp.dot(v, v)
    if n2 > type(n2)(0.0):
        return v / wp.sqrt(n2)
    return v * type(n2)(0.0)


@wp.func
def edge_edge_closest_parameters(p0: Any, p1: Any, q0: Any, q1: Any):
    """Parameters (s, t) in [0, 1]^2 of the closest points p0 + s (p1 - p0), q0 + t (q1 - q0).

    Returns:
        s, t, and the squared distance between the two closest points [m^2].
    """
    zero = type(p0[0])(0.0)
    one = type(p0[0])(1.0)
    ep = p1 - p0
    eq = q1 - q0
    r = p0 - q0  # local origin: only differences enter
    aa = wp.dot(ep, ep)
    ee = wp.dot(eq, eq)
    bb = wp.dot(ep, eq)
    cc = wp.dot(ep, r)
    ff = wp.dot(eq, r)

    # Boundary candidates: an endpoint of one segment against the other segment.
    # s = 0: p0 against Q.
    best_s = zero
    best_t = point_segment_parameter(r, eq)
    v = r - best_t * eq
    best = wp.dot(v, v)
    # s = 1: p1 against Q.
    t = point_segment_parameter(r + ep, eq)
    v = r + ep - t * eq
    dist2 = wp.dot(v, v)
    if dist2 < best:
        best = dist2
        best_s = one
        best_t = t
    # t = 0: q0 against P.
    s = point_segment_parameter(-r, ep)
    v = r + s * ep
    dist2 = wp.dot(v, v)
    if dist2 < best:
        best = dist2
        best_s = s
        best_t = zero
    # t = 1: q1 against P.
    s = point_segment_parameter(eq - r, ep)
    v = r + s * ep - eq
    dist2 = wp.dot(v, v)
    if dist2 < best:
        best = dist2
        best_s = s
        best_t = one

    # Interior candidate: the closest points of the two infinite lines, clamped, then one exact
    # coordinate minimisation in t and in s (so it stays a local improvement when clamping
    # moved it). The lines' solution is written with the cross product n = ep x eq rather than
    # the normal equations: |n|^2 loses relative accuracy like eps / sin(angle), where
    # aa ee - bb^2 would lose it like eps / sin(angle)^2 -- the difference between an
    # exact and a visibly wrong crossing point for near-parallel hair segments.
    n = wp.cross(ep, eq)
    nn = wp.dot(n, n)
    if aa > zero and ee > zero and nn > zero:
        w = -r  # q0 - p0
        s = _clamp01(wp.dot(wp.cross(w, eq), n) / nn)
        t = _clamp01((bb * s + ff) / ee)
        s = _clamp01((bb * t - cc) / aa)
        v = r + s * ep - t * eq
        dist2 = wp.dot(v, v)
        if dist2 < best:
            best = dist2
            best_s = s
            best_t = t
    return best_s, best_t, best


@wp.func
def edge_edge_distance(p0: Any, p1: Any, q0: Any, q1: Any):
    """Distance between segments p0-p1 and q0-q1, and the closest parameters.

    Args:
        p0, p1: endpoints of the first segment [m] (vec3 or vec3d).
        q0, q1: endpoints of the second segment [m].

    Returns:
        d [m] (>= 0), s, t in [0, 1]: closest points p0 + s (p1 - p0) and q0 + t (q1 - q0).
    """
    s, t, dist2 = edge_edge_closest_parameters(p0, p1, q0, q1)
    return wp.sqrt(dist2), s, t


@wp.func
def edge_edge_distance_gradient_at(p0: Any, p1: Any, q0: Any, q1: Any, s: Any, t: Any):
    """D and dd/d(p0, p1, q0, q1) with the closest parameters (s, t) already known.

    Returns:
        d [m], then the gradients w.r.t. p0, p1, q0, q1 (dimensionless vec3 each).
    """
    zero = type(s)(0.0)
    one = type(s)(1.0)
    ep = p1 - p0
    eq = q1 - q0
    v = (p0 - q0) + s * ep - t * eq  # x_p - x_q
    dist2 = wp.dot(v, v)
    d = wp.sqrt(dist2)
    n = v * zero
    normal = _unit_or_zero(wp.cross(ep, eq))
    if s > zero and s < one and t > zero and t < one and wp.dot(normal, normal) > zero:
        # Interior closest points: x_p - x_q is exactly along the common normal; using the
        # normal (not v / d) keeps the direction exact when d is at rounding level, and is the
        # subgradient at d = 0 (crossing segments).
        n = normal
        if wp.dot(v, normal) < zero:
            n = -normal
    elif dist2 > zero:
        n = v / d
    else:
        # Touching at an endpoint: the subgradient along the common normal (zero if parallel).
        n = normal
    return d, (one - s) * n, s * n, -(one - t) * n, -t * n


@wp.func
def point_triangle_closest_barycentric(p: Any, a: Any, b: Any, c: Any):
    """Barycentric (u, v, w) of the point of triangle abc closest to p (u + v + w = 1).

    Returns:
        u, v, w and the squared distance [m^2].
    """
    zero = type(p[0])(0.0)
    one = type(p[0])(1.0)
    # Local origin at p.
    ra = a - p
    rb = b - p
    rc = c - p
    eab = b - a
    ebc = c - b
    eca = a - c

    # Boundary candidates: the three edges.
    t = point_segment_parameter(-ra, eab)
    x = ra + t * eab
    best = wp.dot(x, x)
    bu = one - t
    bv = t
    bw = zero
    t = point_segment_parameter(-rb, ebc)
    x = rb + t * ebc
    dist2 = wp.dot(x, x)
    if dist2 < best:
        best = dist2
        bu = zero
        bv = one - t
        bw = t
    t = point_segment_parameter(-rc, eca)
    x = rc + t * eca
    dist2 = wp.dot(x, x)
    if dist2 < best:
        best = dist2
        bu = t
        bv = zero
        bw = one - t

    # Interior candidate: the projection onto the plane, if it falls inside the triangle.
    e0 = b - a
    e1 = c - a
    d00 = wp.dot(e0, e0)
    d01 = wp.dot(e0, e1)
    d11 = wp.dot(e1, e1)
    d20 = wp.dot(-ra, e0)
    d21 = wp.dot(-ra, e1)
    denom = d00 * d11 - d01 * d01
    if denom > zero:
        v = (d11 * d20 - d01 * d21) / denom
        w = (d00 * d21 - d01 * d20) / denom
        u = one - v - w
        if u >= zero and v >= zero and w >= zero:
            x = ra + v * e0 + w * e1
            dist2 = wp.dot(x, x)
            if dist2 < best:
                best = dist2
                bu = u
                bv = v
                bw = w
    return bu, bv, bw, best


@wp.func
def point_triangle_distance(p: Any, a: Any, b: Any, c: Any):
    """Distance from point p to triangle abc (unsigned), and the closest point's barycentrics.

    Args:
        p: the point [m] (vec3 or vec3d).
        a, b, c: triangle vertices [m]; degenerate (zero-area) triangles are handled as
            their edges.

    Returns:
        d [m] (>= 0), u, v, w: closest point u a + v b + w c.
    """
    u, v, w, dist2 = point_triangle_closest_barycentric(p, a, b, c)
    return wp.sqrt(dist2), u, v, w


@wp.func
def point_triangle_distance_gradient_at(p: Any, a: Any, b: Any, c: Any, u: Any, v: Any, w: Any):
    """D and dd/d(p, a, b, c) with the closest barycentrics (u, v, w) already known."""
    zero = type(u)(0.0)
    x = -(u * (a - p) + v * (b - p) + w * (c - p))  # p - closest point, as u + v + w = 1
    dist2 = wp.dot(x, x)
    d = wp.sqrt(dist2)
    n = x * zero
    normal = _unit_or_zero(wp.cross(b - a, c - a))
    if u > zero and v > zero and w > zero and wp.dot(normal, normal) > zero:
        # Face region: p - closest point is exactly along the normal (exact direction even at
        # rounding-level d; the subgradient at d = 0).
        n = normal
        if wp.dot(x, normal) < zero:
            n = -normal
    elif dist2 > zero:
        n = x / d
    else:
        # On an edge or vertex: the subgradient along the triangle's normal.
        n = normal
    return d, n, -u * n, -v * n, -w * n


@wp.kernel
def edge_edge_distance_kernel(
    # In:
    p0_in: wp.array(dtype=Any),
    p1_in: wp.array(dtype=Any),
    q0_in: wp.array(dtype=Any),
    q1_in: wp.array(dtype=Any),
    # Out:
    distance_out: wp.array(dtype=Any),
    parameters_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """Per pair: d, (s, t) into parameters_out[2k:2k+2], dd/d(p0,p1,q0,q1) into gradient_out[4k:4k+4]."""
    k = wp.tid()
    p0 = p0_in[k]
    p1 = p1_in[k]
    q0 = q0_in[k]
    q1 = q1_in[k]
    s, t, dist2 = edge_edge_closest_parameters(p0, p1, q0, q1)
    d, g_p0, g_p1, g_q0, g_q1 = edge_edge_distance_gradient_at(p0, p1, q0, q1, s, t)
    distance_out[k] = d
    parameters_out[2 * k] = s
    parameters_out[2 * k + 1] = t
    gradient_out[4 * k] = g_p0
    gradient_out[4 * k + 1] = g_p1
    gradient_out[4 * k + 2] = g_q0
    gradient_out[4 * k + 3] = g_q1


@wp.kernel
def point_triangle_distance_kernel(
    # In:
    p_in: wp.array(dtype=Any),
    a_in: wp.array(dtype=Any),
    b_in: wp.array(dtype=Any),
    c_in: wp.array(dtype=Any),
    # Out:
    distance_out: wp.array(dtype=Any),
    barycentric_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """Per query: d, (u, v, w) into barycentric_out[3k:3k+3], dd/d(p,a,b,c) into gradient_out[4k:4k+4]."""
    k = wp.tid()
    p = p_in[k]
    a = a_in[k]
    b = b_in[k]
    c = c_in[k]
    u, v, w, dist2 = point_triangle_closest_barycentric(p, a, b, c)
    d, g_p, g_a, g_b, g_c = point_triangle_distance_gradient_at(p, a, b, c, u, v, w)
    distance_out[k] = d
    barycentric_out[3 * k] = u
    barycentric_out[3 * k + 1] = v
    barycentric_out[3 * k + 2] = w
    gradient_out[4 * k] = g_p
    gradient_out[4 * k + 1] = g_a
    gradient_out[4 * k + 2] = g_b
    gradient_out[4 * k + 3] = g_c
