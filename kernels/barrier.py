"""IPC-style contact barrier extended to negative distances (HairFormer Eq. 12-14).

Notation (all lengths in metres):
    xi     hard barrier: the distance at which the log barrier B_0 diverges.
    dhat   soft barrier width: B_0 is zero for d >= xi + dhat.
    bp     join fraction in (0, 1): the log barrier is used for d >= d_b = xi + bp * dhat and a
           polynomial extrapolation of it below d_b, so that d < xi (and d < 0, penetration)
           still has a finite energy and a useful gradient.

Three extrapolations, chosen by an integer `variant`:
    BARRIER_PAPER     Eq. 12-14 literally: quartic with the max(0, .) clamp, a3/a4 from the
                      "deep penetration distance" t0 = -(xi + dhat) - d_b. Those coefficients
                      give P(t0) = P'(t0) = 0, so the penalty falls back to zero at
                      d = -(xi + dhat) and a vertex pushed that deep sits in a local minimum.
    BARRIER_MONOTONE  P(tau) = f_b + f_b' tau + D_f tau^2 (1 + (tau / t0)^2).
                      It matches B_0, B_0', B_0'' at d_b (C2), and since f_b' < 0, D_f > 0
                      every term of P'(tau) is negative for tau < 0: the penalty increases
                      strictly with penetration depth, quadratically near d_b and quartically
                      beyond |t0|, as the paper intends for its quartic.
    BARRIER_QUADRATIC the default: P(tau) = f_b + f_b' tau + D_f tau^2, the second-order
                      Taylor polynomial of B_0 at d_b: C2 there and strictly increasing with
                      depth, with a push-out force that grows linearly. The quartic's force
                      grows with depth cubed: a vertex 5 cm inside feels ~2e3 times the force
                      of one 2.5 mm inside (b_p = 0.01), far more than the stretch term (Eq. 7) resists, so
                      drapes of deeply penetrating hair trade strand length for contact (33 %
                      length change on the Table 1 scene; docs/stability.md).

All functions are generic over float32/float64 (`Any`); literals are cast with `type(d)`.
Differences of squares are evaluated in factored form, (d - a)(d + a), to keep float32
precision near the barrier where d is within micrometres of xi.
"""

from typing import Any

import warp as wp

# Gradients are hand-written beside each energy: no generated adjoints to compile.
wp.set_module_options({"enable_backward": False})

BARRIER_PAPER = wp.constant(0)
BARRIER_MONOTONE = wp.constant(1)
BARRIER_QUADRATIC = wp.constant(2)


@wp.func
def barrier_log_energy(d: Any, xi: Any, dhat: Any):
    """B_0(d) of Eq. 12 for d > xi, without the clamp (negative for d > xi + dhat)."""
    c = dhat * (type(d)(2.0) * xi + dhat)  # (xi + dhat)^2 - xi^2
    s = (d - xi) * (d + xi)  # d^2 - xi^2
    q = (d - xi - dhat) * (d + xi + dhat)  # d^2 - (xi + dhat)^2
    return -q * q * wp.log(s / c)


@wp.func
def barrier_log_gradient(d: Any, xi: Any, dhat: Any):
    """dB_0/dd for d > xi (unclamped)."""
    c = dhat * (type(d)(2.0) * xi + dhat)
    s = (d - xi) * (d + xi)
    q = (d - xi - dhat) * (d + xi + dhat)
    return -type(d)(2.0) * d * (type(d)(2.0) * q * wp.log(s / c) + q * q / s)


@wp.func
def barrier_log_hessian(d: Any, xi: Any, dhat: Any):
    """d^2 B_0/dd^2 for d > xi (unclamped)."""
    c = dhat * (type(d)(2.0) * xi + dhat)
    s = (d - xi) * (d + xi)
    q = (d - xi - dhat) * (d + xi + dhat)
    log_sc = wp.log(s / c)
    d2 = d * d
    return -(
        type(d)(4.0) * q * log_sc
        + type(d)(8.0) * d2 * log_sc
        + type(d)(16.0) * d2 * q / s
        + type(d)(2.0) * q * q / s
        - type(d)(4.0) * d2 * q * q / (s * s)
    )


@wp.func
def barrier_join(xi: Any, dhat: Any, bp: Any):
    """The extrapolation's coefficients at the join d_b = xi + bp dhat (Eq. 13-14).

    Returns:
        (f_b, f_b', D_f = f_b'' / 2, t0 = -(xi + dhat) - d_b, a3, a4); a3 and a4 are the
        paper's quartic terms (used by BARRIER_PAPER only).
    """
    db = xi + bp * dhat
    fb = barrier_log_energy(db, xi, dhat)
    fb1 = barrier_log_gradient(db, xi, dhat)
    df = type(xi)(0.5) * barrier_log_hessian(db, xi, dhat)
    t0 = -(xi + dhat) - db
    e1 = -(fb + fb1 * t0 + df * t0 * t0)
    e2 = -(fb1 + type(xi)(2.0) * df * t0)
    a3 = type(xi)(4.0) * e1 / (t0 * t0 * t0) - e2 / (t0 * t0)
    a4 = e2 / (t0 * t0 * t0) - type(xi)(3.0) * e1 / (t0 * t0 * t0 * t0)
    return fb, fb1, df, t0, a3, a4


@wp.func
def barrier_energy(d: Any, xi: Any, dhat: Any, bp: Any, variant: int):
    """B(d) of Eq. 12, [energy units of the caller's weight]. Zero for d >= xi + dhat."""
    zero = type(d)(0.0)
    if d >= xi + dhat:
        return zero
    db = xi + bp * dhat
    if d >= db:
        return wp.max(zero, barrier_log_energy(d, xi, dhat))
    fb, fb1, df, t0, a3, a4 = barrier_join(xi, dhat, bp)
    tau = d - db
    if variant == BARRIER_PAPER:
        return wp.max(zero, fb + fb1 * tau + df * tau * tau + a3 * tau * tau * tau + a4 * tau * tau * tau * tau)
    if variant == BARRIER_QUADRATIC:
        return fb + fb1 * tau + df * tau * tau
    r = tau / t0
    return fb + fb1 * tau + df * tau * tau * (type(d)(1.0) + r * r)


@wp.func
def barrier_gradient(d: Any, xi: Any, dhat: Any, bp: Any, variant: int):
    """dB/dd, consistent with `barrier_energy` (zero where a max(0, .) clamp is active)."""
    zero = type(d)(0.0)
    if d >= xi + dhat:
        return zero
    db = xi + bp * dhat
    if d >= db:
        if barrier_log_energy(d, xi, dhat) <= zero:
            return zero
        return barrier_log_gradient(d, xi, dhat)
    fb, fb1, df, t0, a3, a4 = barrier_join(xi, dhat, bp)
    tau = d - db
    if variant == BARRIER_PAPER:
        value = fb + fb1 * tau + df * tau * tau + a3 * tau * tau * tau + a4 * tau * tau * tau * tau
        if value <= zero:
            return zero
        return fb1 + type(d)(2.0) * df * tau + type(d)(3.0) * a3 * tau * tau + type(d)(4.0) * a4 * tau * tau * tau
    if variant == BARRIER_QUADRATIC:
        return fb1 + type(d)(2.0) * df * tau
    return fb1 + type(d)(2.0) * df * tau + type(d)(4.0) * df * tau * tau * tau / (t0 * t0)


@wp.func
def barrier_hessian(d: Any, xi: Any, dhat: Any, bp: Any, variant: int):
    """d^2B/dd^2, consistent with `barrier_gradient` (zero where a max(0, .) clamp is active)."""
    zero = type(d)(0.0)
    if d >= xi + dhat:
        return zero
    db = xi + bp * dhat
    if d >= db:
        if barrier_log_energy(d, xi, dhat) <= zero:
            return zero
        return barrier_log_hessian(d, xi, dhat)
    fb, fb1, df, t0, a3, a4 = barrier_join(xi, dhat, bp)
    tau = d - db
    if variant == BARRIER_PAPER:
        value = fb + fb1 * tau + df * tau * tau + a3 * tau * tau * tau + a4 * tau * tau * tau * tau
        if value <= zero:
            return zero
        return type(d)(2.0) * df + type(d)(6.0) * a3 * tau + type(d)(12.0) * a4 * tau * tau
    if variant == BARRIER_QUADRATIC:
        return type(d)(2.0) * df
    return type(d)(2.0) * df + type(d)(12.0) * df * tau * tau / (t0 * t0)


@wp.kernel
def barrier_kernel(
    # In:
    d_in: wp.array(dtype=Any),
    xi: Any,
    dhat: Any,
    bp: Any,
    variant: int,
    # Out:
    energy_out: wp.array(dtype=Any),
    gradient_out: wp.array(dtype=Any),
):
    """Element-wise B(d) and dB/dd; `gradient_out` feeds the torch backward."""
    i = wp.tid()
    d = d_in[i]
    energy_out[i] = barrier_energy(d, xi, dhat, bp, variant)
    gradient_out[i] = barrier_gradient(d, xi, dhat, bp, variant)


@wp.kernel
def barrier_hessian_kernel(
    # In:
    d_in: wp.array(dtype=Any),
    xi: Any,
    dhat: Any,
    bp: Any,
    variant: int,
    # Out:
    hessian_out: wp.array(dtype=Any),
):
    """Element-wise d^2B/dd^2: the torch double backward (Newton-type solvers, gradgradcheck)."""
    i = wp.tid()
    hessian_out[i] = barrier_hessian(d_in[i], xi, dhat, bp, variant)
