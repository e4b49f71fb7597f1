"""The scalar logic and masked updates of one L-BFGS iteration on the device
(`hairwarp.solvers.device_lbfgs`), so that an iteration is a few kernels instead of ~150.

The solver's state lives in device arrays; its n-sized products (dots, (m, n) x n products)
stay with cuBLAS on the torch side. What is left is the per-iteration decision logic on a few
scalars and the memory's m x m triangular solves: each a single-thread kernel here (a few
microseconds) where a chain of 0-d torch ops cost one kernel launch per operation.

Memory layout (see the solver): S, Y (m, n) ring buffers, flat; rho (m,) with 0 marking an
unused row; SY (m, m) float64 with SY[i, j] = s_i . y_j; head the newest row; the k-th newest
row is (head - k) mod m. Decisions of the accept kernel, read by the later kernels:
flags[0] = accepted, flags[1] = pair stored (then in row head).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

FLAG_ACCEPT = wp.constant(0)
FLAG_STORE = wp.constant(1)


@wp.func
def clear_memory(rho: wp.array(dtype=Any), num_memory: int):
    """Mark every row of the memory unused (rho = 0; the rows stay, ignored)."""
    for k in range(num_memory):
        rho[k] = type(rho[0])(0.0)


@wp.kernel
def lbfgs_trial_scale_kernel(
    # In:
    t: wp.array(dtype=Any),
    step_max_norm: wp.array(dtype=Any),
    max_step: wp.float64,
    # Out:
    t_trial_out: wp.array(dtype=Any),
):
    """The trial's step length: t, shrunk so that no point moves farther than `max_step`
    (`step_max_norm` = the largest point norm of d; t > 0).
    """
    move = wp.float64(t[0]) * wp.float64(step_max_norm[0])
    scale = wp.min(wp.float64(1.0), max_step / wp.max(move, wp.float64(1.0e-30)))
    t_trial_out[0] = type(t[0])(wp.float64(t[0]) * scale)


@wp.kernel
def lbfgs_accept_kernel(
    # In:
    f_trial: wp.array(dtype=Any),
    gram: wp.array(dtype=Any),
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
    # Out:
    flags_out: wp.array(dtype=wp.int32),
):
    """Armijo's test of the trial and what follows from it (one thread).

    `gram` (3 x 3, row-major) holds the products of g (the current gradient), y = g_trial - g
    and d: g.d = gram[2], y.d = gram[5], y.y = gram[4], d.d = gram[8]. A non-finite trial gradient
    makes y.y non-finite, which fails the test like a non-finite loss. Accepted: f moves, the next
    t is 1, the rejections count restarts; the pair (s = t d, y) enters the memory over the
    oldest row when s.y > curvature_eps |s|^2 (the cautious update), with rho = 1 / s.y and the
    scale gamma = s.y / y.y. Rejected: t shrinks to the safeguarded quadratic's minimiser in
    [0.1 t, 0.5 t] (0.25 t without curvature); `restart` rejections in a row clear the memory and
    reset t to 1. The new loss goes to trace[position].
    """
    tt = wp.float64(t_trial[0])
    f0 = wp.float64(f[0])
    ft = wp.float64(f_trial[0])
    gd = wp.float64(gram[2])
    yd = wp.float64(gram[5])
    yy = wp.float64(gram[4])
    dd = wp.float64(gram[8])
    finite = wp.isfinite(ft) and wp.isfinite(yy)
    accept = finite and ft <= f0 + armijo_c1 * tt * gd
    sy = tt * yd
    store = accept and sy > curvature_eps * tt * tt * dd
    row = head[0]
    if store:
        row = (row + wp.int64(1)) % wp.int64(num_memory)
        rho[int(row)] = type(rho[0])(wp.float64(1.0) / wp.max(sy, wp.float64(1.0e-30)))
        gamma[0] = type(gamma[0])(sy / wp.max(yy, wp.float64(1.0e-30)))
    head[0] = row
    count = rejections[0] + 1
    if accept:
        f[0] = f_trial[0]
        t[0] = type(t[0])(1.0)
        count = 0
    else:
        curvature = wp.float64(2.0) * (ft - f0 - gd * tt)
        shrunk = wp.float64(0.25) * tt
        if curvature > wp.float64(0.0):
            quadratic = -gd * tt * tt / curvature
            if wp.isfinite(quadratic):
                shrunk = wp.min(wp.max(quadratic, wp.float64(0.1) * tt), wp.float64(0.5) * tt)
        t[0] = type(t[0])(shrunk)
    if restart > 0 and count >= restart:
        clear_memory(rho, num_memory)
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


@wp.kernel
def lbfgs_update_kernel(
    # In:
    flags: wp.array(dtype=wp.int32),
    t_trial: wp.array(dtype=Any),
    d: wp.array(dtype=Any),
    y: wp.array(dtype=Any),
    trial: wp.array(dtype=Any),
    g_trial: wp.array(dtype=Any),
    head: wp.array(dtype=wp.int64),
    n: int,
    # In and out:
    x: wp.array(dtype=Any),
    g: wp.array(dtype=Any),
    S: wp.array(dtype=Any),
    Y: wp.array(dtype=Any),
):
    """One thread per component: a stored pair's row (s = t d, y), an accepted trial's x and g."""
    i = wp.tid()
    if flags[FLAG_STORE] != 0:
        row = int(head[0])
        S[row * n + i] = t_trial[0] * d[i]
        Y[row * n + i] = y[i]
    if flags[FLAG_ACCEPT] != 0:
        x[i] = trial[i]
        g[i] = g_trial[i]


@wp.kernel
def lbfgs_first_loop_kernel(
    # In:
    flags: wp.array(dtype=wp.int32),
    t_trial: wp.array(dtype=Any),
    Yd: wp.array(dtype=Any),
    Sy: wp.array(dtype=Any),
    Sg: wp.array(dtype=Any),
    g_norm1: wp.array(dtype=Any),
    rho: wp.array(dtype=Any),
    head: wp.array(dtype=wp.int64),
    num_memory: int,
    # In and out:
    SY: wp.array(dtype=wp.float64),
    gamma: wp.array(dtype=Any),
    # Out:
    first_scale_out: wp.array(dtype=Any),
    a_out: wp.array(dtype=wp.float64),
    a_rows_out: wp.array(dtype=Any),
):
    """The stored row's products into SY, then the two-loop recursion's first loop in closed
    form (one thread; Byrd, Nocedal & Schnabel 1994): newest first (k = 0, 1, ...),
    a_k = rho_k (s_k . g - sum_{j<k} a_j s_k . y_j), with s_k . g = Sg and s_k . y_j from SY.

    Also the fallback scale min(1, 1 / |g|_1) (torch's first step), which becomes gamma when the
    newest row is unused (empty or cleared memory). `a_out` keeps a in float64 (the second loop),
    `a_rows_out` by row in the state's precision (the (m, n) product).
    """
    m = num_memory
    if flags[FLAG_STORE] != 0:
        row = int(head[0])
        for j in range(m):
            SY[row * m + j] = wp.float64(t_trial[0]) * wp.float64(Yd[j])  # s_row . y_j
            SY[j * m + row] = wp.float64(Sy[j])  # s_j . y_row
    first = wp.min(wp.float64(1.0), wp.float64(1.0) / wp.max(wp.float64(g_norm1[0]), wp.float64(1.0e-30)))
    first_scale_out[0] = type(first_scale_out[0])(first)
    newest = int(head[0])
    if rho[newest] == type(rho[0])(0.0):
        gamma[0] = type(gamma[0])(first)
    for k in range(m):
        rk = (newest - k + m) % m
        acc = wp.float64(Sg[rk])
        for j in range(k):
            rj = (newest - j + m) % m
            acc -= SY[rk * m + rj] * a_out[j]
        a = wp.float64(rho[rk]) * acc
        a_out[k] = a
        a_rows_out[rk] = type(a_rows_out[0])(a)


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
def lbfgs_direction_kernel(
    # In:
    candidate: wp.array(dtype=Any),
    g_dot_candidate: wp.array(dtype=Any),
    fallback: wp.array(dtype=Any),
    first_scale: wp.array(dtype=Any),
    num_memory: int,
    # Out:
    d_out: wp.array(dtype=Any),
    rho: wp.array(dtype=Any),
):
    """One thread per component: the memory's direction if it descends (g . d < 0), else
    -first_scale * fallback, the memory then dropped (thread 0 zeroes rho). The fallback is g
    with first_scale = min(1, 1 / |g|_1) (torch's first step).
    """
    i = wp.tid()
    if g_dot_candidate[0] < type(g_dot_candidate[0])(0.0):
        d_out[i] = candidate[i]
        return
    d_out[i] = -first_scale[0] * fallback[i]
    if i == 0:
        clear_memory(rho, num_memory)
