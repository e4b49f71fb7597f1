"""Tests of the contact barrier B(d) (HairFormer Eq. 12-14): `hairwarp.ops.barrier` (Warp) and
`hairwarp.torch_reference.barrier` (plain torch) against the numpy float64 reference."""

import itertools

import numpy as np
import pytest
import torch

from hairwarp.ops import barrier
from hairwarp.torch_reference import barrier as torch_barrier
from references import barrier as ref

VARIANTS = ("paper", "monotone", "quadratic")
XIS = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1)  # hard barrier [m], swept over orders of magnitude
BPS = (0.01, 0.1, 0.5, 0.9)  # join fractions: the paper anneals bp from 0.9 to 0.01
DHAT_OVER_XI = 1.5  # the paper's soft barrier width

# Values relative to the largest |B| on the sweep: float64 kernel vs reference differ only by
# rounding of the same formulas (measured 1.4e-14).
VALUE_RTOL_F64 = 1e-11
# Central differences with h = 1e-6 (xi + dhat): truncation ~h^2 B''' / B', rounding ~eps B / h.
FD_RTOL = 1e-5
# float32 vs float64 just above xi: log(s / c) amplifies the rounding of d^2 - xi^2 (measured
# 1.2e-6 relative).
F32_RTOL = 2e-5
# One-sided limits at d_b: linear extrapolation from steps of h = 1e-5 (d_b - xi) leaves O(h^2).
JOIN_RTOL = 1e-6
# B'' at d_b from one-sided differences of B' (step h / 8): O(step B''' / B'') truncation.
JOIN_SECOND_RTOL = 1e-3


def _cases():
    return list(itertools.product(VARIANTS, XIS, BPS))


def _sweep(xi, dhat, n=2001):
    """Distances from deep penetration to beyond the support, plus points hugging xi."""
    return np.concatenate(
        [
            np.linspace(-2.0 * (xi + dhat), 2.0 * (xi + dhat), n),
            xi * (1.0 + np.logspace(-6, -1, 60)),
        ]
    )


def _kernel(d, xi, dhat, bp, variant, dtype=torch.float64, device=torch.device("cpu")):
    """(B, dB/dd) from the Warp bridge, the gradient through autograd."""
    t = torch.tensor(np.asarray(d, dtype=np.float64), dtype=dtype, device=device, requires_grad=True)
    e = barrier(t, xi, dhat, bp, variant)
    (g,) = torch.autograd.grad(e.sum(), t)
    return e.detach().double().cpu().numpy(), g.double().cpu().numpy()


@pytest.mark.parametrize("variant,xi,bp", _cases())
def test_values_match_reference(variant, xi, bp, device):
    dhat = DHAT_OVER_XI * xi
    d = _sweep(xi, dhat)
    expected, expected_grad = ref.barrier_and_gradient(d, xi, dhat, bp, variant)
    assert np.count_nonzero(expected > 0) > 1000  # the sweep covers the active region
    energy, grad = _kernel(d, xi, dhat, bp, variant, device=device)
    scale = np.abs(expected).max()
    gscale = np.abs(expected_grad).max()
    np.testing.assert_allclose(energy, expected, rtol=0, atol=VALUE_RTOL_F64 * scale)
    np.testing.assert_allclose(grad, expected_grad, rtol=0, atol=VALUE_RTOL_F64 * gscale)
    # The plain-torch twin agrees too, value and autograd gradient.
    t = torch.tensor(d, requires_grad=True)
    e_t = torch_barrier.barrier(t, xi, dhat, bp, variant)
    (g_t,) = torch.autograd.grad(e_t.sum(), t)
    np.testing.assert_allclose(e_t.detach().numpy(), expected, rtol=0, atol=VALUE_RTOL_F64 * scale)
    np.testing.assert_allclose(g_t.numpy(), expected_grad, rtol=0, atol=VALUE_RTOL_F64 * gscale)


@pytest.mark.parametrize("variant,xi,bp", _cases())
def test_gradient_matches_central_differences(variant, xi, bp, device):
    dhat = DHAT_OVER_XI * xi
    k = ref.coefficients(xi, dhat, bp)
    h = 1e-6 * (xi + dhat)
    d = np.linspace(-1.9 * (xi + dhat), 1.05 * (xi + dhat), 397)
    # Away from the pieces' joins: d_b, the support end, and (paper) the clamp's double root.
    keep = (np.abs(d - k["db"]) > 4 * h) & (np.abs(d - (xi + dhat)) > 4 * h) & (np.abs(d + xi + dhat) > 4 * h)
    d = d[keep]
    _, grad = _kernel(d, xi, dhat, bp, variant, device=device)
    e_plus, _ = _kernel(d + h, xi, dhat, bp, variant, device=device)
    e_minus, _ = _kernel(d - h, xi, dhat, bp, variant, device=device)
    fd = (e_plus - e_minus) / (2 * h)
    assert np.count_nonzero(grad != 0) > 200
    np.testing.assert_allclose(grad, fd, rtol=0, atol=FD_RTOL * np.abs(grad).max())


def test_bridge_gradcheck_float64(device):
    xi, dhat, bp = 2e-3, 3e-3, 0.1
    d = torch.tensor([-0.01, -4e-3, 0.0, 1e-3, 2.05e-3, 2.5e-3, 3.5e-3, 4.9e-3, 6e-3], dtype=torch.float64,
                     device=device)
    for variant in VARIANTS:
        x = d.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(
            lambda t: barrier(t, xi, dhat, bp, variant), (x,), eps=1e-9, atol=1e-9
        )


def test_bridge_gradgradcheck_float64(device):
    """The double backward is the true second derivative (a Newton step or a Hessian-vector
    product through the barrier gets B'', not a silent zero)."""
    xi, dhat, bp = 2e-3, 3e-3, 0.1
    # Away from the join d_b = 2.3e-3 and the support end 5e-3 (B'' jumps at the paper's clamp).
    d = torch.tensor([-0.01, -4e-3, 0.0, 1e-3, 2.05e-3, 2.5e-3, 3.5e-3, 4.9e-3, 6e-3], dtype=torch.float64,
                     device=device)
    for variant in VARIANTS:
        x = d.clone().requires_grad_(True)
        assert torch.autograd.gradgradcheck(lambda t: barrier(t, xi, dhat, bp, variant), (x,), eps=1e-9, atol=1e-7)
        (g,) = torch.autograd.grad(barrier(x, xi, dhat, bp, variant).sum(), x, create_graph=True)
        (h,) = torch.autograd.grad(g.sum(), x)
        assert torch.count_nonzero(h) >= 6  # the second derivative is really there
        ref = torch.tensor([reference_hessian(float(v), xi, dhat, bp, variant) for v in d], dtype=torch.float64,
                           device=device)
        torch.testing.assert_close(h, ref, rtol=1e-6, atol=1e-6 * float(ref.abs().max()))


def reference_hessian(d, xi, dhat, bp, variant, h=1e-8):
    """B''(d) by central differences of the float64 torch reference's B'."""
    from hairwarp.torch_reference.barrier import barrier as torch_barrier

    def grad(v):
        t = torch.tensor([v], dtype=torch.float64, requires_grad=True)
        (g,) = torch.autograd.grad(torch_barrier(t, xi, dhat, bp, variant).sum(), t)
        return float(g)

    return (grad(d + h) - grad(d - h)) / (2 * h)


def _one_sided_limits(f, x0, h):
    """Left and right limits of f at x0, by linear extrapolation from two one-sided samples."""
    left = 2.0 * f(x0 - h) - f(x0 - 2.0 * h)
    right = 2.0 * f(x0 + h) - f(x0 + 2.0 * h)
    return left, right


@pytest.mark.parametrize("variant,xi,bp", _cases())
def test_c0_c1_c2_at_join(variant, xi, bp):
    """B, B' and B'' each agree from both sides of d_b: the kernel, and the reference."""
    dhat = DHAT_OVER_XI * xi
    k = ref.coefficients(xi, dhat, bp)
    # The step scales with the join's distance to the singularity at xi, where B_0 varies fastest.
    db, h = k["db"], 1e-5 * bp * dhat
    assert k["fb"] > 0 and k["fb1"] < 0 and k["df"] > 0  # a live join, not a flat one

    def kernel_energy(x):
        return _kernel([x], xi, dhat, bp, variant)[0][0]

    def kernel_grad(x):
        return _kernel([x], xi, dhat, bp, variant)[1][0]

    def kernel_second(x):
        # One-sided difference of the kernel gradient, never straddling d_b.
        step = h / 8
        if x < db:
            return (kernel_grad(x) - kernel_grad(x - step)) / step
        return (kernel_grad(x + step) - kernel_grad(x)) / step

    def ref_energy(x):
        return ref.barrier(np.array([x]), xi, dhat, bp, variant)[0]

    def ref_grad(x):
        return ref.barrier_and_gradient(np.array([x]), xi, dhat, bp, variant)[1][0]

    # (function, exact value at d_b, tolerance relative to |exact| on |left - right| and on
    # |right - exact|). B'' comes from one-sided differences of the gradient, whose O(step)
    # truncation error dominates: a looser, stated tolerance.
    checks = [
        (kernel_energy, k["fb"], JOIN_RTOL),
        (kernel_grad, k["fb1"], JOIN_RTOL),
        (kernel_second, 2 * k["df"], JOIN_SECOND_RTOL),
        (ref_energy, k["fb"], JOIN_RTOL),
        (ref_grad, k["fb1"], JOIN_RTOL),
    ]
    for f, exact, rtol in checks:
        left, right = _one_sided_limits(f, db, h)
        assert abs(left - right) <= rtol * abs(exact), (f.__name__, left, right)
        assert abs(right - exact) <= rtol * abs(exact), (f.__name__, right, exact)
    # The kernel's B(d_b) is exactly the log branch.
    assert kernel_energy(db) == pytest.approx(k["fb"], rel=1e-12)


@pytest.mark.parametrize("variant,xi,bp", _cases())
def test_zero_beyond_support(variant, xi, bp):
    dhat = DHAT_OVER_XI * xi
    d = (xi + dhat) * np.array([1.0, 1.0 + 1e-12, 1.001, 1.5, 10.0, 1e4])
    energy, grad = _kernel(d, xi, dhat, bp, variant)
    assert np.all(energy == 0.0) and np.all(grad == 0.0)
    energy32, grad32 = _kernel(d, xi, dhat, bp, variant, dtype=torch.float32)
    assert np.all(energy32 == 0.0) and np.all(grad32 == 0.0)
    # ... and strictly positive just inside it.
    inside, _ = _kernel([(xi + dhat) * (1 - 1e-3)], xi, dhat, bp, variant)
    assert inside[0] > 0.0


@pytest.mark.parametrize("variant,xi,bp", list(itertools.product(("monotone", "quadratic"), XIS, BPS)))
def test_extrapolation_strictly_increasing_with_depth(variant, xi, bp):
    dhat = DHAT_OVER_XI * xi
    k = ref.coefficients(xi, dhat, bp)
    # Down to 1 m of penetration, densely near the join and logarithmically beyond.
    d = np.unique(np.concatenate([np.linspace(-3 * (xi + dhat), k["db"], 4001), -np.logspace(-6, 0, 2001)]))
    d = d[d < k["db"]]
    d = d[np.concatenate([[True], np.diff(d) > 1e-9 * (xi + dhat)])]  # drop near-duplicates of the union
    for dtype in (torch.float64, torch.float32):
        energy, grad = _kernel(d, xi, dhat, bp, variant, dtype=dtype)
        assert d.size > 5000
        assert np.all(grad < 0.0), dtype  # the penalty grows as d decreases
        if dtype == torch.float64:
            assert np.all(np.diff(energy) < 0.0)  # d ascending, energy strictly descending


@pytest.mark.parametrize("bp", BPS)
def test_quadratic_force_grows_linearly_quartic_cubically(bp):
    """The default's push-out force is affine in depth; the quartic's grows with depth cubed
    (hair-body contact's xi = 1 mm, depths of the Table 1 scene)."""
    xi = 1e-3
    dhat = DHAT_OVER_XI * xi
    k = ref.coefficients(xi, dhat, bp)
    depths = np.array([0.0025, 0.01, 0.05])  # [m] inside the body
    _, g_quad = _kernel(-depths, xi, dhat, bp, "quadratic")
    _, g_quart = _kernel(-depths, xi, dhat, bp, "monotone")
    np.testing.assert_allclose(g_quad, k["fb1"] + 2.0 * k["df"] * (-depths - k["db"]), rtol=1e-10)
    # Force ratio between 5 cm and 1 cm deep: ~5 for the default, ~5^3 for the quartic.
    assert g_quad[2] / g_quad[1] == pytest.approx((0.05 + k["db"]) / (0.01 + k["db"]), rel=0.05)
    assert g_quart[2] / g_quart[1] > 50.0
    assert np.all(np.abs(g_quart) >= np.abs(g_quad))


def test_default_variant_is_quadratic():
    from hairwarp.config import EnergyConfig
    from hairwarp.ops import barrier

    assert EnergyConfig().barrier_variant == "quadratic"
    d = torch.tensor([-0.02, 0.0005, 0.0012], dtype=torch.float64)
    np.testing.assert_array_equal(barrier(d, 1e-3, 1.5e-3, 0.01).numpy(),
                                  barrier(d, 1e-3, 1.5e-3, 0.01, "quadratic").numpy())


@pytest.mark.parametrize("xi,bp", list(itertools.product(XIS, BPS)))
def test_paper_variant_local_minimum_at_minus_xi_plus_dhat(xi, bp):
    """Pins the documented flaw of Eq. 14: B = B' = 0 at d = -(xi + dhat), a local minimum."""
    dhat = DHAT_OVER_XI * xi
    k = ref.coefficients(xi, dhat, bp)
    d0 = -(xi + dhat)
    e0, g0 = _kernel([d0], xi, dhat, bp, "paper")
    assert abs(e0[0]) <= 1e-9 * k["fb"]
    assert abs(g0[0]) <= 1e-9 * abs(k["fb1"])
    # Positive on both sides: pushing deeper than -(xi + dhat) is no longer resisted.
    side = np.array([d0 - 0.1 * (xi + dhat), d0 + 0.1 * (xi + dhat)])
    e_side, _ = _kernel(side, xi, dhat, bp, "paper")
    assert np.all(e_side > 1e3 * max(abs(e0[0]), 1e-300))
    assert np.all(e_side > 0.0)
    # The monotone and quadratic extrapolations have no such minimum there.
    for variant in ("monotone", "quadratic"):
        e_m, g_m = _kernel([d0], xi, dhat, bp, variant)
        assert e_m[0] > k["fb"] and g_m[0] < 0.0


@pytest.mark.parametrize("variant", VARIANTS)
def test_exactly_at_xi_and_at_join(variant):
    for xi, bp in itertools.product(XIS, BPS):
        dhat = DHAT_OVER_XI * xi
        k = ref.coefficients(xi, dhat, bp)
        d = np.array([xi, k["db"]])
        expected, expected_grad = ref.barrier_and_gradient(d, xi, dhat, bp, variant)
        energy, grad = _kernel(d, xi, dhat, bp, variant)
        assert np.all(np.isfinite(energy)) and np.all(np.isfinite(grad))
        assert np.all(energy > 0.0) and np.all(grad < 0.0)
        np.testing.assert_allclose(energy, expected, rtol=1e-11)
        np.testing.assert_allclose(grad, expected_grad, rtol=1e-10)
        assert energy[1] == pytest.approx(k["fb"], rel=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_nan_on_dense_sweep(dtype):
    count = 0
    for variant, xi, bp in _cases():
        dhat = DHAT_OVER_XI * xi
        k = ref.coefficients(xi, dhat, bp)
        special = np.array([0.0, xi, -xi, k["db"], xi + dhat, -(xi + dhat), k["db"] + k["t0"]])
        d = np.concatenate(
            [
                np.linspace(-10.0, 10.0, 2001),
                np.linspace(-3 * (xi + dhat), 3 * (xi + dhat), 2001),
                special,
                np.nextafter(special, np.inf),
                np.nextafter(special, -np.inf),
            ]
        )
        energy, grad = _kernel(d, xi, dhat, bp, variant, dtype=dtype)
        assert np.all(np.isfinite(energy)) and np.all(np.isfinite(grad)), (variant, xi, bp)
        assert np.all(energy >= 0.0)
        count += int(np.count_nonzero(energy > 0))
    assert count > 40 * 1000


@pytest.mark.parametrize("variant,bp", list(itertools.product(VARIANTS, BPS)))
def test_float32_matches_float64_near_contact(variant, bp):
    for xi in XIS:
        dhat = DHAT_OVER_XI * xi
        # d just above xi, rounded to float32 first so both precisions see the same distance.
        d32 = torch.tensor(xi * (1.0 + np.logspace(-4, -1, 80)), dtype=torch.float32)
        e32 = barrier(d32, xi, dhat, bp, variant).double()
        e64 = barrier(d32.double(), xi, dhat, bp, variant)
        assert bool((e64 > 0).all())
        rel = ((e32 - e64).abs() / e64.abs()).max().item()
        assert rel < F32_RTOL, (xi, rel)


def test_bad_inputs_raise_naming_the_argument():
    d = torch.linspace(0.0, 0.01, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match="xi"):
        barrier(d, 0.0, 3e-3, 0.1)
    with pytest.raises(ValueError, match="xi"):
        barrier(d, -1e-3, 3e-3, 0.1)
    with pytest.raises(ValueError, match="dhat"):
        barrier(d, 2e-3, 0.0, 0.1)
    for bp in (0.0, 1.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="bp"):
            barrier(d, 2e-3, 3e-3, bp)
    with pytest.raises(ValueError, match="variant"):
        barrier(d, 2e-3, 3e-3, 0.1, variant="cubic")
    with pytest.raises(ValueError, match="variant"):
        torch_barrier.barrier(d, 2e-3, 3e-3, 0.1, variant="cubic")
    bad = d.clone()
    bad[2] = float("nan")
    with pytest.raises(ValueError, match="d"):
        barrier(bad, 2e-3, 3e-3, 0.1)
    bad[2] = float("inf")
    with pytest.raises(ValueError, match="d"):
        barrier(bad, 2e-3, 3e-3, 0.1)
    with pytest.raises(ValueError, match="d"):
        barrier(torch.arange(5), 2e-3, 3e-3, 0.1)
    with pytest.raises(ValueError, match="d"):
        barrier([0.001, 0.002], 2e-3, 3e-3, 0.1)


def test_shape_kept_and_empty_input(device):
    d = torch.linspace(-0.01, 0.01, 24, dtype=torch.float32, device=device).reshape(2, 3, 4)
    out = barrier(d, 2e-3, 3e-3, 0.1)
    assert out.shape == d.shape and out.device == d.device and out.dtype == d.dtype
    assert int((out > 0).sum()) > 5
    empty = torch.zeros(0, dtype=torch.float32, device=device)
    assert barrier(empty, 2e-3, 3e-3, 0.1).shape == (0,)
