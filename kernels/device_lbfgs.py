"""One L-BFGS iteration on the device (`hairwarp.solvers.device_lbfgs`) in seven kernels.

An iteration is a trial step, the energy there (the caller's), and the update. Its n-sized work
is four passes over the vectors, each reducing what the next decision needs in the same pass
(block sums in shared memory, one atomic per block and value, float64), and its decisions and
the memory's m x m triangular solves are single-thread kernels:

1. `lbfgs_trial_kernel` (n threads): the direction d (the memory's candidate if it descends,
   else -min(1, 1/|g|_1) g), the step length t shrunk so that no point moves farther than
   `max_step`, the trial x + t d;
2. (the energy at the trial: f_t, g_t)
3. `lbfgs_products_kernel` (blocks per memory row): every product the decision and the first
   loop need, before anything moves: y_j . d, s_j . y, s_j . g_t, s_j . g per row j, and g . d,
   y . d, y . y, d . d, g_t . d, |g_t|_1, |g_t|_inf (y = g_t - g);
4. `lbfgs_accept_kernel` (one thread): Armijo's test, the pair's entry into the memory and
   s_i . y_j, t's shrinking on a rejection, then the two-loop recursion's first loop in closed
   form (Byrd, Nocedal & Schnabel 1994) from the products of step 3, the new row's own read
   from the scalars (it is written only in step 5);
5. `lbfgs_update_kernel` (n threads): the stored row, the accepted x and g, and
   r = gamma (g - Y^T a);
6. `lbfgs_rows_dot_kernel` (blocks per row): y_j . r;
7. `lbfgs_second_loop_kernel` (one thread): the second loop's coefficients c;
8. `lbfgs_candidate_kernel` (blocks over points): the candidate -(r + S^T c), its product with
   g and the largest point norms of it and of g, for step 1 of the next iteration.

Before: ~25 kernels, the n-sized products by cuBLAS; a 3 x n by n x 3 Gram product alone took
71 us of a 0.97 ms iteration on one H100 (a 64 x 64 tile kernel over a 307 200-long inner
dimension), the L-BFGS's vector work ~285 us in all (docs/physics.md, section 2).

Memory layout (see the solver): S, Y (m, n) ring buffers, flat; rho (m,) with 0 marking an
unused row; SY (m, m) float64 with SY[i, j] = s_i . y_j; head the newest row; the k-th newest
row is (head - k) mod m. Decisions of the accept kernel, read by the later kernels:
flags[0] = accepted, flags[1] = pair stored (then in row head).

Reductions: a tile kernel of `block_dim` threads (one on the CPU); block b of a row kernel serves
row b // chunks and chunk b % chunks, each thread striding over the vector by chunks *
block_dim. Sums are float64 whatever the state's precision, in no fixed order (atomics).
"""

from typing import Any

import warp as wp

from hairwarp.kernels.reductions import row_chunk_start

wp.set_module_options({"enable_backward": False})

FLAG_ACCEPT = wp.constant(0)
FLAG_STORE = wp.constant(1)

# `products` rows past the memory's m: (g . d, y . d, y . y, d . d), then (g_t . d, |g_t|_1, |g_t|_inf, 0).
TRIAL_ROW = wp.constant(0)
GRADIENT_ROW = wp.constant(1)
# `candidate_sums`: g . candidate, the candidate's largest squared point norm, g's.
CANDIDATE_DOT = wp.constant(0)
CANDIDATE_NORM2 = wp.constant(1)
GRADIENT_NORM2 = wp.constant(2)


@wp.func
def clear_memory(rho: wp.array(dtype=Any), num_memory: int):
    """Mark every row of the memory unused (rho = 0; the rows stay, ignored)."""
    for k in range(num_memory):
        rho[k] = type(rho[0])(0.0)


@wp.func
def first_scale(g_norm1: wp.float64):
    """min(1, 1 / |g|_1): torch's first L-BFGS step, and ours after a clear."""
    return wp.min(wp.float64(1.0), wp.float64(1.0) / wp.max(g_norm1, wp.float64(1.0e-30)))


@wp.func
def add_block_sum(value: wp.vec4d, sums: wp.array(dtype=wp.float64), offset: int, lane: int):
    """Add the block's sum of `value` (one per thread) to sums[offset:offset + 4] (one atomic each)."""
    total = wp.tile_sum(wp.tile(value, preserve_type=True))
    if lane == 0:
        v = total[0]
        for c in range(4):
            wp.atomic_add(sums, offset + c, v[c])


@wp.func
def max_block(value: wp.float64, out: wp.array(dtype=wp.float64), index: int, lane: int):
    """out[index] = max(out[index], the block's largest `value`)."""
    top = wp.tile_max(wp.tile(value))
    if lane == 0:
        wp.atomic_max(out, index, top[0])


@wp.kernel
def lbfgs_trial_kernel(
    # In:
    x: wp.array(dtype=Any),
    g: wp.array(dtype=Any),
    candidate: wp.array(dtype=Any),
    candidate_sums: wp.array(dtype=wp.float64),
    g_norm1: wp.array(dtype=wp.float64),
    t: wp.array(dtype=Any),
    max_step: wp.float64,
    num_memory: int,
    # Out:
    d_out: wp.array(dtype=Any),
    trial_out: wp.array(dtype=Any),
    t_trial_out: wp.array(dtype=Any),
    rho: wp.array(dtype=Any),
    products: wp.array(dtype=wp.float64),
):
    """One thread per component: the direction, the trial's step length and the trial point.

    The direction is the memory's candidate where it descends (g . candidate < 0), else
    -first_scale g with first_scale = min(1, 1 / |g|_1), the memory then dropped (thread 0
    zeroes rho). The step t is shrunk so that no point moves farther than `max_step` (each
    thread computes the same scalar). Thread 0 also zeroes the sums of `lbfgs_products_kernel`.
    """
    i = wp.tid()
    descent = candidate_sums[CANDIDATE_DOT] < wp.float64(0.0)
    first = first_scale(g_norm1[0])
    norm = wp.sqrt(candidate_sums[CANDIDATE_NORM2])
    if not descent:
        norm = first * wp.sqrt(candidate_sums[GRADIENT_NORM2])
    t0 = wp.float64(t[0])
    move = t0 * norm
    tt = type(t[0])(t0 * wp.min(wp.float64(1.0), max_step / wp.max(move, wp.float64(1.0e-30))))
    di = candidate[i]
    if not descent:
        di = -type(t[0])(first) * g[i]
    d_out[i] = di
    trial_out[i] = x[i] + tt * di
    if i == 0:
        t_trial_out[0] = tt
        if not descent:
            clear_memory(rho, num_memory)
        for k in range(products.shape[0]):
            products[k] = wp.float64(0.0)


@wp.kernel
def lbfgs_products_kernel(
    # In:
    g: wp.array(dtype=Any),
    g_trial: wp.array(dtype=Any),
    d: wp.array(dtype=Any),
    S: wp.array(dtype=Any),
    Y: wp.array(dtype=Any),
    n: int,
    num_memory: int,
    chunks: int,
    # Out:
    products: wp.array(dtype=wp.float64),
):
    """The sums of an iteration's decision, before anything moves (y = g_t - g):
    rows j < m: products[4 j:4 j + 4] = (y_j . d, s_j . y, s_j . g_t, s_j . g);
    row m (TRIAL_ROW): (g . d, y . d, y . y, d . d); row m + 1 (GRADIENT_ROW): (g_t . d, |g_t|_1,
    |g_t|_inf (a max), 0). Blocks (m + 2) * chunks.
    """
    block, lane = wp.tid()
    row, i, stride = row_chunk_start(block, lane, chunks)
    acc = wp.vec4d()
    if row < num_memory:
        base = row * n
        while i < n:
            gi = wp.float64(g[i])
            gt = wp.float64(g_trial[i])
            s = wp.float64(S[base + i])
            acc += wp.vec4d(wp.float64(Y[base + i]) * wp.float64(d[i]), s * (gt - gi), s * gt, s * gi)
            i += stride
        add_block_sum(acc, products, 4 * row, lane)
    elif row == num_memory + TRIAL_ROW:
        while i < n:
            gi = wp.float64(g[i])
            y = wp.float64(g_trial[i]) - gi
            di = wp.float64(d[i])
            acc += wp.vec4d(gi * di, y * di, y * y, di * di)
            i += stride
        add_block_sum(acc, products, 4 * row, lane)
    else:
        top = wp.float64(0.0)
        while i < n:
            gt = wp.float64(g_trial[i])
            acc += wp.vec4d(gt * wp.float64(d[i]), wp.abs(gt), wp.float64(0.0), wp.float64(0.0))
            top = wp.max(top, wp.abs(gt))
            i += stride
        add_block_sum(acc, products, 4 * row, lane)
        max_block(top, products, 4 * row + 2, lane)


@wp.kernel
def lbfgs_accept_kernel(
    # In:
    f_trial: wp.array(dtype=Any),
    products: wp.array(dtype=wp.float64),
    t_trial: wp.array(dtype=Any),
    num_memory: int,
    armijo_c1: wp.float64,
    curvature_eps: wp.float64,
    restart: int,
    # In and out:
    f: wp.array(dtype=Any),
    t: wp.array(dtype=Any),
    rho: wp.array(dtype=Any),
    gamma: wp.array(dtype=Any),
    head: wp.array(dtype=wp.int64),
    rejections: wp.array(dtype=wp.int32),
    trace: wp.array(dtype=Any),
    position: wp.array(dtype=wp.int64),
    SY: wp.array(dtype=wp.float64),
    g_norm1: wp.array(dtype=wp.float64),
    g_max: wp.array(dtype=Any),
    # Out:
    flags_out: wp.array(dtype=wp.int32),
    a_out: wp.array(dtype=wp.float64),
    a_rows_out: wp.array(dtype=Any),
    row_sums: wp.array(dtype=wp.float64),
    candidate_sums: wp.array(dtype=wp.float64),
):
    """Armijo's test of the trial, what follows from it, and the first loop (one thread).

    Accepted: f moves, the next t is 1, the rejections count restarts, |g|_1 and |g|_inf are
    the trial's; the pair (s = t d, y) enters the memory over the oldest row when
    s.y > curvature_eps |s|^2 (the cautious update), with rho = 1 / s.y and gamma = s.y / y.y.
    A non-finite trial (loss or y.y) fails the test. Rejected: t shrinks to the safeguarded
    quadratic's minimiser in [0.1 t, 0.5 t] (0.25 t without curvature); `restart` rejections in
    a row clear the memory and reset t to 1. The new loss goes to trace[position].

    Then the stored row's products into SY, and the first loop in closed form, newest first
    (k = 0, 1, ...): a_k = rho_k (s_k . g - sum_{j<k} a_j s_k . y_j); gamma becomes
    min(1, 1/|g|_1) when the newest row is unused. `a_out` keeps a in float64 (the second loop),
    `a_rows_out` by row in the state's precision. Zeroes the sums of the later reductions.
    """
    m = num_memory
    trial_row = 4 * (m + TRIAL_ROW)
    gradient_row = 4 * (m + GRADIENT_ROW)
    tt = wp.float64(t_trial[0])
    f0 = wp.float64(f[0])
    ft = wp.float64(f_trial[0])
    gd = products[trial_row + 0]
    yd = products[trial_row + 1]
    yy = products[trial_row + 2]
    dd = products[trial_row + 3]
    finite = wp.isfinite(ft) and wp.isfinite(yy)
    accept = finite and ft <= f0 + armijo_c1 * tt * gd
    sy = tt * yd
    store = accept and sy > curvature_eps * tt * tt * dd
    row = head[0]
    if store:
        row = (row + wp.int64(1)) % wp.int64(m)
        rho[int(row)] = type(rho[0])(wp.float64(1.0) / wp.max(sy, wp.float64(1.0e-30)))
        gamma[0] = type(gamma[0])(sy / wp.max(yy, wp.float64(1.0e-30)))
    head[0] = row
    count = rejections[0] + 1
    if accept:
        f[0] = f_trial[0]
        t[0] = type(t[0])(1.0)
        count = 0
        g_norm1[0] = products[gradient_row + 1]
        g_max[0] = type(g_max[0])(products[gradient_row + 2])
    else:
        curvature = wp.float64(2.0) * (ft - f0 - gd * tt)
        shrunk = wp.float64(0.25) * tt
        if curvature > wp.float64(0.0):
            quadratic = -gd * tt * tt / curvature
            if wp.isfinite(quadratic):
                shrunk = wp.min(wp.max(quadratic, wp.float64(0.1) * tt), wp.float64(0.5) * tt)
        t[0] = type(t[0])(shrunk)
    if restart > 0 and count >= restart:
        clear_memory(rho, m)
        t[0] = type(t[0])(1.0)
        count = 0
    rejections[0] = count
    trace[int(position[0])] = f[0]
    position[0] = (position[0] + wp.int64(1)) % wp.int64(trace.shape[0])
    flags_out[FLAG_ACCEPT] = 0
    flags_out[FLAG_STORE] = 0
    if accept:
        flags_out[FLAG_ACCEPT] = 1
    if store:
        flags_out[FLAG_STORE] = 1
    new_row = int(row)
    if store:
        for j in range(m):
            y_j_d = products[4 * j + 0]  # y_j . d, or the new y's
            s_j_y = products[4 * j + 1]  # s_j . y, or the new s's: t d . y
            if j == new_row:
                y_j_d = yd
                s_j_y = tt * yd
            SY[new_row * m + j] = tt * y_j_d  # s_row . y_j
            SY[j * m + new_row] = s_j_y  # s_j . y_row
    first = first_scale(g_norm1[0])
    if rho[new_row] == type(rho[0])(0.0):
        gamma[0] = type(gamma[0])(first)
    for k in range(m):
        rk = (new_row - k + m) % m
        acc = products[4 * rk + 3]  # s_k . g, g the one kept
        if accept:
            acc = products[4 * rk + 2]
        if store and rk == new_row:
            acc = tt * products[gradient_row + 0]  # t d . g_t
        for j in range(k):
            rj = (new_row - j + m) % m
            acc -= SY[rk * m + rj] * a_out[j]
        a = wp.float64(rho[rk]) * acc
        a_out[k] = a
        a_rows_out[rk] = type(a_rows_out[0])(a)
    for k in range(row_sums.shape[0]):
        row_sums[k] = wp.float64(0.0)
    for k in range(candidate_sums.shape[0]):
        candidate_sums[k] = wp.float64(0.0)


@wp.kernel
def lbfgs_update_kernel(
    # In:
    flags: wp.array(dtype=wp.int32),
    t_trial: wp.array(dtype=Any),
    d: wp.array(dtype=Any),
    trial: wp.array(dtype=Any),
    g_trial: wp.array(dtype=Any),
    head: wp.array(dtype=wp.int64),
    a_rows: wp.array(dtype=Any),
    gamma: wp.array(dtype=Any),
    n: int,
    num_memory: int,
    # In and out:
    x: wp.array(dtype=Any),
    g: wp.array(dtype=Any),
    S: wp.array(dtype=Any),
    Y: wp.array(dtype=Any),
    # Out:
    r_out: wp.array(dtype=Any),
):
    """One thread per component: a stored pair's row (s = t d, y = g_t - g), an accepted trial's
    x and g, then r = gamma (g - sum_j a_j y_j) (rows with rho = 0 have a_j = 0).
    """
    i = wp.tid()
    gi = g[i]
    gt = g_trial[i]
    if flags[FLAG_STORE] != 0:
        row = int(head[0])
        S[row * n + i] = t_trial[0] * d[i]
        Y[row * n + i] = gt - gi
    if flags[FLAG_ACCEPT] != 0:
        x[i] = trial[i]
        g[i] = gt
        gi = gt
    r = gi
    for j in range(num_memory):
        r -= a_rows[j] * Y[j * n + i]
    r_out[i] = gamma[0] * r


@wp.kernel
def lbfgs_rows_dot_kernel(
    # In:
    Y: wp.array(dtype=Any),
    r: wp.array(dtype=Any),
    n: int,
    chunks: int,
    # Out:
    row_sums: wp.array(dtype=wp.float64),
):
    """row_sums[j] += y_j . r (blocks m * chunks; zeroed by `lbfgs_accept_kernel`)."""
    block, lane = wp.tid()
    row, i, stride = row_chunk_start(block, lane, chunks)
    base = row * n
    acc = wp.float64(0.0)
    while i < n:
        acc += wp.float64(Y[base + i]) * wp.float64(r[i])
        i += stride
    total = wp.tile_sum(wp.tile(acc))
    if lane == 0:
        wp.atomic_add(row_sums, row, total[0])


@wp.kernel
def lbfgs_second_loop_kernel(
    # In:
    a: wp.array(dtype=wp.float64),
    Yr: wp.array(dtype=Any),
    rho: wp.array(dtype=Any),
    SY: wp.array(dtype=wp.float64),
    head: wp.array(dtype=wp.int64),
    num_memory: int,
    # Out:
    c_rows_out: wp.array(dtype=Any),
    c_work: wp.array(dtype=wp.float64),
):
    """The second loop in closed form (one thread), oldest to newest (k = m - 1, ..., 0):
    c_k = a_k - rho_k (y_k . r + sum_{j>k} c_j s_j . y_k), with y_k . r = Yr; the direction is
    then -(r + sum_k c_k s_k).
    """
    m = num_memory
    newest = int(head[0])
    for step in range(m):
        k = m - 1 - step
        rk = (newest - k + m) % m
        acc = wp.float64(Yr[rk])
        for j in range(k + 1, m):
            rj = (newest - j + m) % m
            acc += SY[rj * m + rk] * c_work[j]
        c = a[k] - wp.float64(rho[rk]) * acc
        c_work[k] = c
        c_rows_out[rk] = type(c_rows_out[0])(c)


@wp.kernel
def lbfgs_candidate_kernel(
    # In:
    r: wp.array(dtype=Any),
    g: wp.array(dtype=Any),
    S: wp.array(dtype=Any),
    c_rows: wp.array(dtype=Any),
    n: int,
    num_memory: int,
    point_size: int,
    chunks: int,
    # Out:
    candidate_out: wp.array(dtype=Any),
    candidate_sums: wp.array(dtype=wp.float64),
):
    """The memory's direction -(r + sum_j c_j s_j) by points (blocks `chunks`), with its product
    with g and the largest squared point norms of it and of g (zeroed by `lbfgs_accept_kernel`).
    """
    block, lane = wp.tid()
    stride = chunks * wp.block_dim()
    p = block * wp.block_dim() + lane
    points = n // point_size
    acc = wp.vec4d()
    top_candidate = wp.float64(0.0)
    top_gradient = wp.float64(0.0)
    while p < points:
        norm_candidate = wp.float64(0.0)
        norm_gradient = wp.float64(0.0)
        for k in range(point_size):
            i = p * point_size + k
            value = r[i]
            for j in range(num_memory):
                value += c_rows[j] * S[j * n + i]
            candidate_out[i] = -value
            gi = wp.float64(g[i])
            ci = -wp.float64(value)
            acc += wp.vec4d(gi * ci, wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
            norm_candidate += ci * ci
            norm_gradient += gi * gi
        top_candidate = wp.max(top_candidate, norm_candidate)
        top_gradient = wp.max(top_gradient, norm_gradient)
        p += stride
    total = wp.tile_sum(wp.tile(acc[0]))
    if lane == 0:
        wp.atomic_add(candidate_sums, CANDIDATE_DOT, total[0])
    max_block(top_candidate, candidate_sums, CANDIDATE_NORM2, lane)
    max_block(top_gradient, candidate_sums, GRADIENT_NORM2, lane)
