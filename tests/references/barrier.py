"""numpy float64 reference of the contact barrier B(d), written from HairFormer Eq. 12-14.

Written independently of `kernels/barrier.py`: the derivatives of B_0 are taken through
u = d^2 (chain rule), not in the kernel's expanded form, so a slip in either shows up as a
mismatch.

    B_0(d)  = max(0, -(u - A)^2 log((u - X) / C)),  u = d^2, A = (xi + dhat)^2, X = xi^2,
              C = 2 xi dhat + dhat^2                                             (Eq. 12)
    B(d)    = B_0(d) for d >= d_b = xi + bp dhat, else an extrapolation in tau = d - d_b:
      "paper":    max(0, f_b + f_b' tau + D_f tau^2 + a_3 tau^3 + a_4 tau^4)  (Eq. 12-14)
      "monotone": f_b + f_b' tau + D_f tau^2 (1 + (tau / t_0)^2)
      "quadratic": f_b + f_b' tau + D_f tau^2                       (the project's default)
"""

from __future__ import annotations

import numpy as np

VARIANTS = ("paper", "monotone", "quadratic")


def _log_barrier_u(u, xi, dhat):
    """-(u - A)^2 log((u - X)/C) and its first two u-derivatives (u > xi^2), unclamped."""
    a = (xi + dhat) ** 2
    x = xi**2
    c = 2.0 * xi * dhat + dhat**2
    w = u - a
    g = u - x
    lg = np.log(g / c)
    f = -(w**2) * lg
    f_u = -2.0 * w * lg - w**2 / g
    f_uu = -2.0 * lg - 4.0 * w / g + w**2 / g**2
    return f, f_u, f_uu


def log_barrier(d, xi, dhat):
    """B_0 unclamped with dB_0/dd and d^2B_0/dd^2, for d > xi (float64 arrays)."""
    d = np.asarray(d, dtype=np.float64)
    f, f_u, f_uu = _log_barrier_u(d * d, xi, dhat)
    return f, 2.0 * d * f_u, 2.0 * f_u + 4.0 * d * d * f_uu


def coefficients(xi, dhat, bp):
    """Join point and polynomial coefficients of Eq. 13-14: dict of floats."""
    db = xi + bp * dhat
    fb, fb1, fb2 = (float(v) for v in log_barrier(db, xi, dhat))
    df = 0.5 * fb2
    t0 = -(xi + dhat) - db
    e1 = -(fb + fb1 * t0 + df * t0**2)
    e2 = -(fb1 + 2.0 * df * t0)
    a3 = 4.0 * e1 / t0**3 - e2 / t0**2
    a4 = e2 / t0**3 - 3.0 * e1 / t0**4
    return {"db": db, "fb": fb, "fb1": fb1, "df": df, "t0": t0, "a3": a3, "a4": a4}


def barrier(d, xi, dhat, bp, variant="quadratic"):
    """B(d) of Eq. 12 (float64), element-wise over an array of distances [m]."""
    return barrier_and_gradient(d, xi, dhat, bp, variant)[0]


def barrier_and_gradient(d, xi, dhat, bp, variant="quadratic"):
    """(B(d), dB/dd), the gradient being zero wherever a max(0, .) clamp is active."""
    if variant not in VARIANTS:
        raise ValueError(variant)
    d = np.asarray(d, dtype=np.float64)
    k = coefficients(xi, dhat, bp)
    energy = np.zeros_like(d)
    grad = np.zeros_like(d)

    log_piece = (d >= k["db"]) & (d < xi + dhat)
    if np.any(log_piece):
        f, f1, _ = log_barrier(d[log_piece], xi, dhat)
        energy[log_piece] = np.maximum(0.0, f)
        grad[log_piece] = np.where(f > 0.0, f1, 0.0)

    poly_piece = d < k["db"]
    tau = d[poly_piece] - k["db"]
    if variant == "paper":
        p = k["fb"] + k["fb1"] * tau + k["df"] * tau**2 + k["a3"] * tau**3 + k["a4"] * tau**4
        p1 = k["fb1"] + 2.0 * k["df"] * tau + 3.0 * k["a3"] * tau**2 + 4.0 * k["a4"] * tau**3
        energy[poly_piece] = np.maximum(0.0, p)
        grad[poly_piece] = np.where(p > 0.0, p1, 0.0)
    elif variant == "quadratic":
        energy[poly_piece] = k["fb"] + k["fb1"] * tau + k["df"] * tau**2
        grad[poly_piece] = k["fb1"] + 2.0 * k["df"] * tau
    else:
        r2 = (tau / k["t0"]) ** 2
        energy[poly_piece] = k["fb"] + k["fb1"] * tau + k["df"] * tau**2 * (1.0 + r2)
        grad[poly_piece] = k["fb1"] + 2.0 * k["df"] * tau + 4.0 * k["df"] * tau**3 / k["t0"] ** 2
    return energy, grad
