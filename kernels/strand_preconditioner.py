"""A per-strand banded Hessian and its Cholesky factor: the physics solver's preconditioner.

The implicit-Euler step (Eq. 6 without L_func_reg) is badly conditioned in one way above all:
the stretch term (Eq. 7, k_s = 1e8) makes each strand a nearly inextensible chain whose
along-segment stiffness exceeds the inertia term's mass / dt^2 by six orders of magnitude, so a
quasi-Newton method from a scaled identity needs hundreds of iterations per frame. The terms
that live on one strand couple a vertex only to its neighbours up to two apart, so their
Hessian is banded; factored once per solve, it turns L-BFGS into a preconditioned one whose
first direction is already a Newton step of the strand model.

The matrix, per strand, over the 3 (N - 2) coordinates of the moving vertices 2..N-1
(coordinate q = 3 (v - 2) + axis), with the term scales of `hairwarp.ops.strand_energies`:
- stretch (Eq. 7), segment (v, v+1) with unit direction u and length l against rest l0:
  2 s_stretch [u u^T + max(0, 1 - l0 / l) (I - u u^T)] on the segment's two vertices (signs of a
  difference); the transverse part only when stretched (the tension's stiffness), so the
  matrix stays positive semi-definite;
- smoothness (Eq. 10), joint v with a = (1, -2, 1) on (v-1, v, v+1): 2 s_smooth a a^T per axis;
- root alignment (Eq. 15), the first k' moving edges: s_root / l^2 (I - u u^T), the term's
  transverse stiffness where the edge points along the scalp normal (its Hessian is not
  positive definite elsewhere; this is its magnitude), so that the stiff pull of a unit
  direction over millimetre edges does not read as a soft transverse mode;
- a diagonal c I: inertia (Eq. 16, 2 s_inertia m) and the auxiliary term (Eq. 9, 2 s_aux).
Fixed vertices 0 and 1 drop out (their rows and columns). Bending (Eq. 8, k_b = 1e-6), root
alignment and the contacts are left to the L-BFGS memory.

Storage: the lower band, L[strand, i, j] = L_{i, i-j} for j = 0..BAND (float64), BAND = 8 (vertex
v and v+2 coupled by smoothness: 3 * 2 + 2 scalars apart).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Scalars between the farthest coupled coordinates (vertices two apart, axes 0 and 2).
BAND = wp.constant(8)
FIRST_MOVING = wp.constant(2)


@wp.func
def band_add(band: wp.array3d(dtype=wp.float64), s: int, i: int, j: int, value: wp.float64):
    """Add `value` to the symmetric matrix's entry (i, j), i >= j, in the lower band."""
    band[s, i, i - j] = band[s, i, i - j] + value


@wp.func
def add_vertex_block(band: wp.array3d(dtype=wp.float64), s: int, vi: int, vj: int, block: wp.mat33d):
    """Add the 3 x 3 `block` at moving vertices (vi, vj), vi >= vj (block (vj, vi) is its transpose)."""
    for a in range(3):
        for b in range(3):
            i = 3 * vi + a
            j = 3 * vj + b
            if i >= j:
                band_add(band, s, i, j, block[a, b])


@wp.kernel
def strand_band_cholesky_kernel(
    # In:
    x: wp.array(dtype=wp.vec3),
    rest_lengths: wp.array2d(dtype=wp.float32),
    num_strands: int,
    num_vertices: int,
    stretch_stiffness: wp.float64,
    smooth_stiffness: wp.float64,
    root_stiffness: wp.float64,
    root_segments: int,
    diagonal: wp.float64,
    # Out (factor in place):
    band: wp.array3d(dtype=wp.float64),
):
    """One thread per (batch, strand): assemble the strand's banded Hessian (see the module),
    then factor it in place, P = L L^T (banded Cholesky, float64).

    `x` is the flat (B M N) vertex array, `rest_lengths` (M, N-1); `stretch_stiffness` =
    2 s_stretch, `smooth_stiffness` = 2 s_smooth, `root_stiffness` = s_root on edges
    1..`root_segments`, `diagonal` = c. A pivot that is not positive
    (cannot happen with c > 0) is replaced by c so the factor stays finite.
    """
    s = wp.tid()
    strand = s % num_strands
    n = 3 * (num_vertices - FIRST_MOVING)
    base = s * num_vertices
    for i in range(n):
        for j in range(BAND + 1):
            band[s, i, j] = wp.float64(0.0)
        band[s, i, 0] = diagonal
    eye = wp.identity(n=3, dtype=wp.float64)
    # Stretch: segments (v, v+1), v = 1..N-2 (segment 1 touches the fixed vertex 1).
    for v in range(1, num_vertices - 1):
        p0 = x[base + v]
        p1 = x[base + v + 1]
        e = wp.vec3d(wp.float64(p1[0] - p0[0]), wp.float64(p1[1] - p0[1]), wp.float64(p1[2] - p0[2]))
        length = wp.length(e)
        if length > wp.float64(1.0e-12):
            u = e / length
            tension = wp.max(wp.float64(0.0), wp.float64(1.0) - wp.float64(rest_lengths[strand, v]) / length)
            block = stretch_stiffness * (wp.outer(u, u) + tension * (eye - wp.outer(u, u)))
            if v <= root_segments:
                block += root_stiffness / (length * length) * (eye - wp.outer(u, u))
            a = v - FIRST_MOVING
            b = v + 1 - FIRST_MOVING
            add_vertex_block(band, s, b, b, block)
            if a >= 0:
                add_vertex_block(band, s, a, a, block)
                add_vertex_block(band, s, b, a, -block)
    # Smoothness: joints at v = 1..N-2 with weights (1, -2, 1) on (v-1, v, v+1).
    for v in range(1, num_vertices - 1):
        for r in range(3):
            vr = v - 1 + r
            wr = wp.float64(1.0)
            if r == 1:
                wr = wp.float64(-2.0)
            for c in range(r + 1):
                vc = v - 1 + c
                wc = wp.float64(1.0)
                if c == 1:
                    wc = wp.float64(-2.0)
                if vr >= FIRST_MOVING and vc >= FIRST_MOVING:
                    value = smooth_stiffness * wr * wc
                    for axis in range(3):
                        band_add(band, s, 3 * (vr - FIRST_MOVING) + axis, 3 * (vc - FIRST_MOVING) + axis, value)
    # Banded Cholesky, row by row: L_ij = (P_ij - sum_k L_ik L_jk) / L_jj, L_ii = sqrt(P_ii - sum_k L_ik^2).
    for i in range(n):
        first = wp.max(0, i - BAND)
        for j in range(first, i + 1):
            acc = band[s, i, i - j]
            for k in range(wp.max(first, j - BAND), j):
                acc -= band[s, i, i - k] * band[s, j, j - k]
            if j == i:
                if acc <= wp.float64(0.0):
                    acc = diagonal
                band[s, i, 0] = wp.sqrt(acc)
            else:
                band[s, i, i - j] = acc / band[s, j, 0]


@wp.kernel
def strand_band_solve_kernel(
    # In:
    band: wp.array3d(dtype=wp.float64),
    rhs: wp.array2d(dtype=wp.float32),
    # Out:
    out: wp.array2d(dtype=wp.float32),
    work: wp.array2d(dtype=wp.float64),
):
    """One thread per (batch, strand): out = P^-1 rhs with P = L L^T factored by
    `strand_band_cholesky_kernel` (forward then backward substitution in float64).

    `rhs`, `out`: (B M, 3 (N - 2)) moving coordinates of each strand; `work` the same shape.
    """
    s = wp.tid()
    n = rhs.shape[1]
    for i in range(n):
        acc = wp.float64(rhs[s, i])
        for k in range(wp.max(0, i - BAND), i):
            acc -= band[s, i, i - k] * work[s, k]
        work[s, i] = acc / band[s, i, 0]
    for step in range(n):
        i = n - 1 - step
        acc = work[s, i]
        for k in range(i + 1, wp.min(n, i + BAND + 1)):
            acc -= band[s, k, k - i] * work[s, k]
        work[s, i] = acc / band[s, i, 0]
        out[s, i] = wp.float32(work[s, i])
