"""Plain-torch contact barrier B(d) (HairFormer Eq. 12-14), differentiable by autograd.

The same function as `hairwarp.ops.barrier` (Warp kernel `hairwarp.kernels.barrier`), written
with torch operations only, so the plain-torch reference energies of the contact terms can be
built from it and checked against the fused kernels. The three variants:

    "paper"     Eq. 12-14 literally: B_Q = max(0, f_b + f_b' tau + D_f tau^2 + a_3 tau^3 + a_4 tau^4)
                for d < d_b, whose penalty falls back to zero at d = -(xi + dhat).
    "monotone"  P(tau) = f_b + f_b' tau + D_f tau^2 (1 + (tau / t_0)^2): C2 at d_b and strictly
                increasing with penetration depth, the force growing with depth cubed.
    "quadratic" P(tau) = f_b + f_b' tau + D_f tau^2: C2 at d_b, strictly increasing, the force
                growing linearly with depth (the project's default).

The join coefficients (Eq. 13-14) depend only on (xi, dhat, bp), so they are computed once in
Python float64 and enter the graph as constants. Each branch is evaluated on an input clamped
into its own domain before `torch.where` picks one, so the unused branch never produces the
NaN (log of a negative number) that would otherwise leak into the gradient.
"""

from __future__ import annotations

import math

import torch

from hairwarp.config import BARRIER_VARIANTS


def _log_barrier_derivatives(d: float, xi: float, dhat: float) -> tuple[float, float, float]:
    """B_0(d), dB_0/dd, d^2B_0/dd^2 at a scalar d > xi (unclamped), in float64."""
    c = dhat * (2.0 * xi + dhat)
    s = (d - xi) * (d + xi)
    q = (d - xi - dhat) * (d + xi + dhat)
    log_sc = math.log(s / c)
    f = -q * q * log_sc
    f1 = -2.0 * d * (2.0 * q * log_sc + q * q / s)
    d2 = d * d
    f2 = -(
        4.0 * q * log_sc
        + 8.0 * d2 * log_sc
        + 16.0 * d2 * q / s
        + 2.0 * q * q / s
        - 4.0 * d2 * q * q / (s * s)
    )
    return f, f1, f2


def barrier_coefficients(xi: float, dhat: float, bp: float) -> dict[str, float]:
    """Join point d_b and the extrapolation coefficients of Eq. 13-14 (Python floats).

    Returns:
        dict with d_b [m], f_b, f_b' [1/m], D_f [1/m^2], t_0 [m], a_3 [1/m^3], a_4 [1/m^4].
    """
    db = xi + bp * dhat
    fb, fb1, fb2 = _log_barrier_derivatives(db, xi, dhat)
    df = 0.5 * fb2
    t0 = -(xi + dhat) - db
    e1 = -(fb + fb1 * t0 + df * t0 * t0)
    e2 = -(fb1 + 2.0 * df * t0)
    a3 = 4.0 * e1 / t0**3 - e2 / t0**2
    a4 = e2 / t0**3 - 3.0 * e1 / t0**4
    return {"db": db, "fb": fb, "fb1": fb1, "df": df, "t0": t0, "a3": a3, "a4": a4}


def barrier(d: torch.Tensor, xi: float, dhat: float, bp: float, variant: str = "quadratic") -> torch.Tensor:
    """Contact barrier B(d) of Eq. 12 in plain torch, element-wise, differentiable w.r.t. `d`.

    Args:
        d: distances [m], any shape, float32 or float64.
        xi: hard barrier [m], > 0.
        dhat: soft barrier width [m], > 0.
        bp: join fraction in (0, 1): d_b = xi + bp * dhat.
        variant: "quadratic", "monotone" or "paper".

    Returns:
        Tensor like `d` (dimensionless barrier value; zero for d >= xi + dhat).
    """
    if variant not in BARRIER_VARIANTS:
        raise ValueError(f"variant: expected one of {list(BARRIER_VARIANTS)}, got {variant!r}")
    k = barrier_coefficients(float(xi), float(dhat), float(bp))
    db = k["db"]
    zero = torch.zeros_like(d)

    # Log piece (d >= d_b): evaluated at max(d, d_b) so s = d^2 - xi^2 > 0 everywhere.
    d_log = torch.clamp(d, min=db)
    c = dhat * (2.0 * xi + dhat)
    s = (d_log - xi) * (d_log + xi)
    q = (d_log - xi - dhat) * (d_log + xi + dhat)
    e_log = torch.clamp(-q * q * torch.log(s / c), min=0.0)

    # Polynomial piece (d < d_b): evaluated at min(d, d_b), tau <= 0.
    tau = torch.clamp(d, max=db) - db
    if variant == "paper":
        poly = k["fb"] + tau * (k["fb1"] + tau * (k["df"] + tau * (k["a3"] + tau * k["a4"])))
        e_poly = torch.clamp(poly, min=0.0)
    elif variant == "quadratic":
        e_poly = k["fb"] + k["fb1"] * tau + k["df"] * tau * tau
    else:
        r = tau / k["t0"]
        e_poly = k["fb"] + k["fb1"] * tau + k["df"] * tau * tau * (1.0 + r * r)

    energy = torch.where(d >= db, e_log, e_poly)
    return torch.where(d >= xi + dhat, zero, energy)
