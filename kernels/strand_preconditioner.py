"""A per-strand preconditioner of the physics steps: a block-banded factor of each strand's stiffness.

The implicit-Euler step's Hessian is block-banded along a strand: a moving vertex couples with the
two vertices before and after it (stretch, bending and smoothness, Eq. 7, 8, 10), and on the rest
lengths each segment's tension adds lambda / l (I - u u^T) across it (the multiplier of its length:
a hanging strand is a pendulum whose restoring force is its weight). Stretch's own share, k u u^T
along each segment, is added here too: its k_s is ~10^5 times a vertex's inertia, and a float32
difference of its gradient (lengths of ~1 m coordinates) would drown the soft terms. Arrays here are (M*V,) 3x3
blocks of the M strands' V moving vertices, strand-major: P_ii (`diag`), P_{i,i+1} (`off1`) and
P_{i,i+2} (`off2`), zero past the tip.

P = U U^T with U upper block-triangular of bandwidth two (a Cholesky factorisation from the tip):
    U_{i,i+2} = P_{i,i+2} U_{i+2,i+2}^-1
    U_{i,i+1} = (P_{i,i+1} - U_{i,i+2} U_{i+1,i+2}^T) U_{i+1,i+1}^-1
    U_ii      = (P_ii - U_{i,i+1} U_{i,i+1}^T - U_{i,i+2} U_{i,i+2}^T)^(1/2)   (symmetric square root)
P need not be positive definite (bending and root alignment are not convex, differences are
noisy): a strand whose pivots fall below the floor is factored again with a growing shift of its
diagonal (`strand_band_factor_kernel`), and the square roots' eigenvalues are held at `floor`.
With the solver's variables z = U^T t (t the free targets), L-BFGS on z starts from H0 = P^-1: the
forward map t = U^-T z is a walk from the root (`strand_band_solve_transposed`), its adjoint
w = U^-1 a a walk from the tip (`strand_band_solve`); both one thread per strand.
"""

from typing import Any

import warp as wp

from hairwarp.config import NUM_FIXED_VERTICES

wp.set_module_options({"enable_backward": False})

FIXED_VERTICES = wp.constant(NUM_FIXED_VERTICES)


@wp.func
def clamped_square_root(s: Any, floor: Any):
    """(S^(1/2), S^(-1/2), smallest eigenvalue) of a symmetric 3x3 block, its eigenvalues held at
    `floor` at least in the roots.
    """
    q, d = wp.eig3(s)
    r0 = wp.sqrt(wp.max(d[0], floor))
    r1 = wp.sqrt(wp.max(d[1], floor))
    r2 = wp.sqrt(wp.max(d[2], floor))
    root = q * wp.diag(type(d)(r0, r1, r2)) * wp.transpose(q)
    one = type(floor)(1.0)
    inverse = q * wp.diag(type(d)(one / r0, one / r1, one / r2)) * wp.transpose(q)
    return root, inverse, wp.min(wp.min(d[0], d[1]), d[2])


# Factorisations of a strand tried with a growing shift before the last one is kept.
FACTOR_ATTEMPTS = wp.constant(14)


@wp.kernel
def strand_band_factor_kernel(
    diag: wp.array(dtype=Any),
    off1: wp.array(dtype=Any),
    off2: wp.array(dtype=Any),
    num_vertices: int,
    floor: Any,
    root: wp.array(dtype=Any),
    inverse: wp.array(dtype=Any),
    coupling1: wp.array(dtype=Any),
    coupling2: wp.array(dtype=Any),
):
    """U of one strand (thread = strand), walking from the tip: `root` U_ii, `inverse` U_ii^-1,
    `coupling1` U_{i,i+1}, `coupling2` U_{i,i+2}; arrays (M*V,) mat33, V = `num_vertices` moving
    vertices a strand.

    A pivot whose smallest eigenvalue falls below floor / 2 means P is not positive definite there;
    holding it at the floor would leave U U^T far from P and U^-1 growing like U_{i,i+1} / U_ii
    per vertex (a float32 walk overflowed). The strand is then factored again as P + mu I, mu
    growing eightfold from `floor` (a Levenberg shift; 8^13 ~ 5e11 times the inertia covers a
    contact's differenced stiffness), up to `FACTOR_ATTEMPTS` times.
    """
    base = wp.tid() * num_vertices
    zero = diag[base] - diag[base]
    eye = wp.identity(n=3, dtype=type(floor))
    shift = floor * type(floor)(0.0)
    for attempt in range(FACTOR_ATTEMPTS):
        inv1 = zero  # U_{i+1,i+1}^-1
        inv2 = zero  # U_{i+2,i+2}^-1
        c1_next = zero  # U_{i+1,i+2}
        indefinite = int(0)
        for j in range(num_vertices):
            i = num_vertices - 1 - j
            c2 = off2[base + i] * inv2
            c1 = (off1[base + i] - c2 * wp.transpose(c1_next)) * inv1
            s = diag[base + i] + eye * shift - c1 * wp.transpose(c1) - c2 * wp.transpose(c2)
            s = (s + wp.transpose(s)) * type(floor)(0.5)
            u, u_inv, smallest = clamped_square_root(s, floor)
            if not (smallest >= floor * type(floor)(0.5)):
                indefinite = 1
            root[base + i] = u
            inverse[base + i] = u_inv
            coupling1[base + i] = c1
            coupling2[base + i] = c2
            inv2 = inv1
            inv1 = u_inv
            c1_next = c1
        if indefinite == 0:
            break
        shift = wp.max(shift * type(floor)(8.0), floor)


@wp.kernel
def strand_band_solve_transposed_kernel(
    inverse: wp.array(dtype=Any),
    coupling1: wp.array(dtype=Any),
    coupling2: wp.array(dtype=Any),
    z: wp.array(dtype=Any),
    num_vertices: int,
    t: wp.array(dtype=Any),
):
    """T = U^-T z, one strand a thread, from the root: U_ii t_i = z_i - U_{i-1,i}^T t_{i-1} -
    U_{i-2,i}^T t_{i-2} (U_ii symmetric); arrays (M*V,) (vec3 for z and t).
    """
    base = wp.tid() * num_vertices
    t1 = z[base] - z[base]  # t_{i-1}
    t2 = t1  # t_{i-2}
    for i in range(num_vertices):
        r = z[base + i]
        if i >= 1:
            r = r - wp.transpose(coupling1[base + i - 1]) * t1
        if i >= 2:
            r = r - wp.transpose(coupling2[base + i - 2]) * t2
        ti = inverse[base + i] * r
        t[base + i] = ti
        t2 = t1
        t1 = ti


@wp.kernel
def strand_band_solve_kernel(
    inverse: wp.array(dtype=Any),
    coupling1: wp.array(dtype=Any),
    coupling2: wp.array(dtype=Any),
    a: wp.array(dtype=Any),
    num_vertices: int,
    w: wp.array(dtype=Any),
):
    """W = U^-1 a, one strand a thread, from the tip: U_ii w_i = a_i - U_{i,i+1} w_{i+1} -
    U_{i,i+2} w_{i+2} (the adjoint of `strand_band_solve_transposed_kernel`).
    """
    base = wp.tid() * num_vertices
    w1 = a[base] - a[base]  # w_{i+1}
    w2 = w1  # w_{i+2}
    for j in range(num_vertices):
        i = num_vertices - 1 - j
        r = a[base + i] - coupling1[base + i] * w1 - coupling2[base + i] * w2
        wi = inverse[base + i] * r
        w[base + i] = wi
        w2 = w1
        w1 = wi


@wp.kernel
def strand_band_multiply_transposed_kernel(
    root: wp.array(dtype=Any),
    coupling1: wp.array(dtype=Any),
    coupling2: wp.array(dtype=Any),
    t: wp.array(dtype=Any),
    num_vertices: int,
    z: wp.array(dtype=Any),
):
    """Z = U^T t (thread = strand * V + i): z_i = U_ii t_i + U_{i-1,i}^T t_{i-1} + U_{i-2,i}^T t_{i-2}."""
    k = wp.tid()
    i = k % num_vertices
    r = root[k] * t[k]
    if i >= 1:
        r = r + wp.transpose(coupling1[k - 1]) * t[k - 1]
    if i >= 2:
        r = r + wp.transpose(coupling2[k - 2]) * t[k - 2]
    z[k] = r


@wp.kernel
def segment_tension_stiffness_kernel(
    x: wp.array(dtype=Any),
    gradient: wp.array(dtype=Any),
    num_vertices: int,
    scale: Any,
    stretch: Any,
    diag: wp.array(dtype=Any),
    off1: wp.array(dtype=Any),
):
    """Adds each segment's tension stiffness max(lambda, 0) / l (I - u u^T) (times `scale`) and its
    stretch stiffness `stretch` u u^T (Eq. 7's Hessian on the rest length, 2 k_s / (M (N-1)),
    already scaled) to the bands of one strand (thread = strand). x and gradient are (M*N,) vec3 over all N vertices (the
    positions on the rest lengths and the energy's gradient there); the bands are (M*V,) mat33 over
    the V = N - 2 moving vertices. The tensions balance the gradient along the strand from the tip,
    lambda_{i-1} = -(g_i - lambda_i u_i) . u_{i-1} (least squares of g + sum lambda grad c = 0);
    a compressed segment (lambda < 0) adds nothing.
    """
    strand = wp.tid()
    base = strand * num_vertices
    moving = num_vertices - FIXED_VERTICES
    band = strand * moving
    carry = gradient[base] - gradient[base]  # lambda_i u_i of the segment past vertex i
    eye = wp.identity(n=3, dtype=type(scale))
    for j in range(moving):
        i = num_vertices - 1 - j  # the moving vertex at the far end of segment i-1
        e = x[base + i] - x[base + i - 1]
        length = wp.length(e)
        u = e / length
        lam = -wp.dot(gradient[base + i] - carry, u)
        carry = u * lam
        along = wp.outer(u, u)
        block = (eye - along) * (wp.max(lam, type(scale)(0.0)) / length * scale) + along * stretch
        b = band + i - FIXED_VERTICES
        diag[b] = diag[b] + block
        if i - 1 >= FIXED_VERTICES:
            diag[b - 1] = diag[b - 1] + block
            off1[b - 1] = off1[b - 1] - block
