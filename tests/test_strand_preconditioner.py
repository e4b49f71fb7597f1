"""The physics solver's preconditioner: the strands' banded Hessian and its Cholesky solve."""

import numpy as np
import pytest
import torch

from hairwarp.config import EnergyConfig
from hairwarp.ops import strand_energies
from hairwarp.solvers.strand_preconditioner import StrandPreconditioner, strand_hessian_coefficients


def _wavy_strands(batch=2, strands=3, vertices=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, vertices)
    base = torch.stack([0.02 * torch.sin(6 * t), -0.2 * t, 0.01 * torch.cos(4 * t)], dim=-1)
    x = base.expand(batch, strands, vertices, 3).clone()
    x += 0.004 * torch.randn(batch, strands, vertices, 3, generator=g)
    return x


def _dense_reference(x, rest, c):
    """P over the moving vertices, float64, written from the module's formulas."""
    x = x.double().numpy()
    b, m, n, _ = x.shape
    size = 3 * (n - 2)
    out = np.zeros((b * m, size, size))
    for s in range(b * m):
        p = x[s // m, s % m]
        P = np.eye(size) * c["diagonal"]
        for v in range(1, n - 1):  # stretch, segment (v, v+1)
            e = p[v + 1] - p[v]
            length = np.linalg.norm(e)
            u = e / length
            tension = max(0.0, 1.0 - rest[s % m, v] / length)
            block = c["stretch"] * (np.outer(u, u) + tension * (np.eye(3) - np.outer(u, u)))
            if v <= c["root_segments"]:
                block = block + c["root"] / length ** 2 * (np.eye(3) - np.outer(u, u))
            rows = [v - 2, v - 1]
            signs = [-1.0, 1.0]
            for ra, sa in zip(rows, signs):
                for rb, sb in zip(rows, signs):
                    if ra >= 0 and rb >= 0:
                        P[3 * ra:3 * ra + 3, 3 * rb:3 * rb + 3] += sa * sb * block
        for v in range(1, n - 1):  # smoothness, joint v
            a = np.zeros(n)
            a[v - 1:v + 2] = (1.0, -2.0, 1.0)
            a = a[2:]
            P += c["smoothness"] * np.kron(np.outer(a, a), np.eye(3))
        out[s] = P
    return out


def test_solve_matches_dense_float64():
    x = _wavy_strands()
    rest = ((x[0, :, 1:] - x[0, :, :-1]).norm(dim=-1) * 0.97).contiguous()  # stretched: tension on
    c = strand_hessian_coefficients(EnergyConfig(), 3, 7, dynamic=True)
    pre = StrandPreconditioner(tuple(x.shape), rest, c, torch.device("cpu"))
    pre.factor(x)
    v = torch.randn(2, 3, 5, 3, generator=torch.Generator().manual_seed(1))
    got = pre.apply(v).clone().double().numpy().reshape(6, 15)
    P = _dense_reference(x, rest.double().numpy(), c)
    want = np.stack([np.linalg.solve(P[s], v.double().numpy().reshape(6, 15)[s]) for s in range(6)])
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-7 * np.abs(want).max())


def test_matches_the_energy_hessian_at_rest_lengths():
    """At rest lengths the Gauss-Newton stretch is the exact Hessian: P equals the finite-difference
    Hessian of stretch + smoothness + inertia (strand energies in float64)."""
    x = _wavy_strands(batch=1, strands=2, vertices=6).double()
    rest = (x[0, :, 1:] - x[0, :, :-1]).norm(dim=-1)
    config = EnergyConfig(stretch_weight=1e3)  # well-scaled for finite differences
    c = {**strand_hessian_coefficients(config, 2, 6, dynamic=True), "root": 0.0}  # Eq. 15 not in the energy below
    prev = x.clone()

    def gradient(y):
        y = y.clone().requires_grad_(True)
        total, _ = strand_energies(y, rest, config, prev=prev, prev2=prev,
                                   terms=("stretch", "smoothness", "inertia"))
        (g,) = torch.autograd.grad(total.sum(), y)
        return g[0, :, 2:].reshape(2, -1)

    h = 1e-6
    size = 3 * 4
    fd = np.zeros((2, size, size))
    for k in range(size):
        dx = torch.zeros_like(x)
        dx[0, :, 2 + k // 3, k % 3] = h
        fd[:, :, k] = ((gradient(x + dx) - gradient(x - dx)) / (2 * h)).numpy()
    P = _dense_reference(x.float(), rest.numpy(), c)
    P_no_aux = P - np.eye(size) * 2.0 * config.auxiliary_weight / (3 * 2 * 6)
    np.testing.assert_allclose(P_no_aux, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_bad_inputs():
    c = strand_hessian_coefficients(EnergyConfig(), 3, 7, dynamic=False)
    with pytest.raises(ValueError, match="rest_lengths"):
        StrandPreconditioner((1, 3, 7, 3), torch.ones(3, 5), c, torch.device("cpu"))
    with pytest.raises(ValueError, match="diagonal"):
        StrandPreconditioner((1, 3, 7, 3), torch.ones(3, 6), {**c, "diagonal": 0.0}, torch.device("cpu"))
    pre = StrandPreconditioner((1, 3, 7, 3), torch.ones(3, 6), c, torch.device("cpu"))
    with pytest.raises(ValueError, match="x: expected"):
        pre.factor(torch.zeros(1, 3, 6, 3))
