"""The physics steps' per-strand preconditioner: the block-banded factor, its walks, the stiffness it
is built from (float64 references in dense torch)."""

import pytest
import torch

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.ops.strand_preconditioner import StrandPreconditioner


def _banded_spd(strands, moving, generator):
    """(M, 3V, 3V) float64 symmetric positive definite matrices of block bandwidth two."""
    size = 3 * moving
    near = (torch.arange(moving)[:, None] - torch.arange(moving)[None, :]).abs() <= 2
    mask = near.repeat_interleave(3, 0).repeat_interleave(3, 1).double()
    out = []
    for _ in range(strands):
        r = torch.randn(size, size, dtype=torch.float64, generator=generator)
        a = (r + r.T) * mask
        # diagonally dominant: positive definite whatever the band's entries
        out.append(a + torch.diag(a.abs().sum(dim=1) + 1.0))
    return torch.stack(out)


def _set_bands(pre, dense):
    m, v = pre.strands, pre.moving
    blocks = dense.reshape(m, v, 3, v, 3).permute(0, 1, 3, 2, 4)  # (M, V, V, 3, 3)
    i = torch.arange(v)
    pre.bands.zero_()
    pre.bands[0] = blocks[:, i, i].reshape(-1, 3, 3)
    off1 = torch.zeros(m, v, 3, 3, dtype=torch.float64)
    off1[:, :-1] = blocks[:, i[:-1], i[1:]]
    off2 = torch.zeros(m, v, 3, 3, dtype=torch.float64)
    off2[:, :-2] = blocks[:, i[:-2], i[2:]]
    pre.bands[1] = off1.reshape(-1, 3, 3)
    pre.bands[2] = off2.reshape(-1, 3, 3)


def _dense_factor(pre):
    """U (M, 3V, 3V) float64 from the factor's blocks."""
    m, v = pre.strands, pre.moving
    f = pre.factor.double().reshape(4, m, v, 3, 3)
    u = torch.zeros(m, v, v, 3, 3, dtype=torch.float64)
    i = torch.arange(v)
    u[:, i, i] = f[0]
    u[:, i[:-1], i[1:]] = f[2][:, :-1]
    u[:, i[:-2], i[2:]] = f[3][:, :-2]
    return u.permute(0, 1, 3, 2, 4).reshape(m, 3 * v, 3 * v)


@pytest.mark.parametrize("dtype,tolerance", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_the_factor_and_its_walks_match_dense_float64(dtype, tolerance):
    generator = torch.Generator().manual_seed(3)
    strands, vertices = 3, 11
    pre = StrandPreconditioner(strands, vertices, "cpu", dtype)
    dense = _banded_spd(strands, pre.moving, generator)
    _set_bands(pre, dense)
    assert torch.allclose(pre.dense(), dense)
    pre.factor_bands(floor=1e-9)
    u = _dense_factor(pre)
    scale = float(dense.abs().max())
    assert float((u @ u.transpose(1, 2) - dense).abs().max()) < tolerance * scale
    # t = U^-T z, its adjoint U^-1 a, and z = U^T t
    z = torch.randn(strands, pre.moving, 3, dtype=dtype, generator=generator).requires_grad_(True)
    t = pre.targets(z)
    expected = torch.linalg.solve(u.transpose(1, 2), z.detach().double().reshape(strands, -1, 1))[..., 0]
    assert float((t.detach().double().reshape(strands, -1) - expected).abs().max()) < tolerance * 10 * float(
        expected.abs().max())
    a = torch.randn(strands, pre.moving, 3, dtype=dtype, generator=generator)
    (t * a).sum().backward()
    expected = torch.linalg.solve(u, a.double().reshape(strands, -1, 1))[..., 0]
    assert float((z.grad.double().reshape(strands, -1) - expected).abs().max()) < tolerance * 10 * float(
        expected.abs().max())
    assert torch.allclose(pre.variables(t.detach()), z.detach(), atol=tolerance * 10, rtol=0)
    # H0 = P^-1: the walks' round trip solves P q = g
    g = torch.randn(strands, pre.moving, 3, dtype=torch.float64, generator=generator)
    w = torch.empty_like(g.to(dtype))
    from hairwarp.kernels import strand_preconditioner as kernels

    pre._walk(kernels.strand_band_solve_kernel, g.to(dtype).contiguous(), w)  # U^-1 g
    q = pre.targets(w)  # U^-T U^-1 g = P^-1 g
    expected = torch.linalg.solve(dense, g.reshape(strands, -1, 1))[..., 0]
    assert float((q.double().reshape(strands, -1) - expected).abs().max()) < tolerance * 100 * float(
        expected.abs().max())


def test_an_indefinite_strand_is_factored_with_a_shift_not_passed_on_as_nan():
    """P = -I (negative definite): the strand is factored again as P + mu I with mu growing from the
    floor until every pivot clears floor / 2 (1 fails, 8 passes), and its walks stay finite."""
    pre = StrandPreconditioner(2, 6, "cpu", torch.float64)
    eye = torch.eye(3 * pre.moving, dtype=torch.float64)
    generator = torch.Generator().manual_seed(5)
    dense = torch.stack([-eye, _banded_spd(1, pre.moving, generator)[0]])  # one bad strand, one good
    _set_bands(pre, dense)
    pre.factor_bands(floor=1.0)
    assert torch.isfinite(pre.factor).all()
    u = _dense_factor(pre)
    product = u @ u.transpose(1, 2)
    assert torch.allclose(product[0], 7.0 * eye)  # -I + 8 I
    assert torch.allclose(product[1], dense[1])  # the good strand is not shifted
    t = pre.targets(torch.ones(2, pre.moving, 3, dtype=torch.float64))
    assert torch.isfinite(t).all()


def test_build_reads_the_hessian_of_a_banded_energy_and_the_tension_of_a_hanging_chain():
    """build() on a known energy: a quadratic coupling each vertex with its neighbours two away
    (its Hessian is known) plus gravity on a vertical chain, whose tensions are the weights below."""
    torch.manual_seed(0)
    strands, vertices = 2, 9
    moving = vertices - NUM_FIXED_VERTICES
    dtype = torch.float64
    pre = StrandPreconditioner(strands, vertices, "cpu", dtype)
    # vertical chains hanging down from y = 0, segments 0.01 m
    x = torch.zeros(1, strands, vertices, 3, dtype=dtype)
    x[..., 1] = -0.01 * torch.arange(vertices, dtype=dtype)
    x[0, 1, :, 0] = 0.05
    generator = torch.Generator().manual_seed(1)
    hessian = _banded_spd(strands, moving, generator)
    weight = 2.0  # N per moving vertex, downwards

    def gradient(p):
        free = p[..., NUM_FIXED_VERTICES:, :] - x[..., NUM_FIXED_VERTICES:, :]
        g = (hessian @ free.reshape(strands, -1, 1))[..., 0].reshape(1, strands, moving, 3)
        g = g + torch.tensor([0.0, weight, 0.0], dtype=dtype)  # d/dp of weight * height
        out = torch.zeros_like(p)
        out[..., NUM_FIXED_VERTICES:, :] = g
        return out

    stiffness, stretch = 4.0, 100.0
    pre.build(x, gradient, stiffness, stretch)
    # the chain's tension: segment e carries the weight of the vertices below it
    tension = torch.zeros(strands, moving, 3, 3, dtype=dtype)  # diag blocks
    coupling = torch.zeros(strands, moving, 3, 3, dtype=dtype)
    across = torch.diag(torch.tensor([1.0, 0.0, 1.0], dtype=dtype))
    along = torch.diag(torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    for segment in range(NUM_FIXED_VERTICES - 1, vertices - 1):  # segment e joins e and e+1
        below = vertices - 1 - segment  # moving vertices hanging from it
        block = (weight * below / 0.01) * across + stretch * along
        b = segment + 1 - NUM_FIXED_VERTICES
        tension[:, b] += block
        if b - 1 >= 0:
            tension[:, b - 1] += block
            coupling[:, b - 1] -= block
    expected = hessian.clone()
    blocks = expected.reshape(strands, moving, 3, moving, 3)
    i = torch.arange(moving)
    blocks[:, i, :, i, :] += tension.permute(1, 0, 2, 3)
    blocks[:, i[:-1], :, i[1:], :] += coupling[:, :-1].permute(1, 0, 2, 3)
    blocks[:, i[1:], :, i[:-1], :] += coupling[:, :-1].transpose(-1, -2).permute(1, 0, 2, 3)
    got = pre.dense()
    assert float((got * stiffness - expected).abs().max()) < 1e-6 * float(expected.abs().max())
    # and its factor reproduces it
    u = _dense_factor(pre)
    assert float((u @ u.transpose(1, 2) - got).abs().max()) < 1e-10 * float(got.abs().max())


def test_hanging_tension_of_a_uniform_strand():
    """w_j = h^2 g (L - s_j) / l^2 for the segment whose top end lies at arc length s_j (float64
    by hand: a strand of equal segments)."""
    from hairwarp.ops.strand_preconditioner import hanging_tension

    n, seg, h, g = 6, 0.01, 1.0 / 60.0, 9.81
    rest = torch.full((2, n), seg)
    w = hanging_tension(rest, h, g)
    expected = torch.tensor([h * h * g * (n * seg - j * seg) / seg ** 2 for j in range(n)], dtype=torch.float64)
    torch.testing.assert_close(w, expected.expand(2, n), rtol=1e-6, atol=0.0)
    assert w.dtype == torch.float64


def test_the_chain_preconditioner_is_the_hanging_chain_in_float64():
    """P = diag((k / k_min)^(2a)) + L_w with w the hanging tension over the inertia (and over
    k_min), from a float64 reference assembled entry by entry; its factor's change of variables
    is P^-1 = R R^T and `variables` inverts `targets`."""
    from hairwarp.config import EnergyConfig
    from hairwarp.ops.strand_preconditioner import ChainPreconditioner

    generator = torch.Generator().manual_seed(3)
    strands, vertices = 3, 9
    rest = 0.002 + 0.01 * torch.rand(strands, vertices - 1, generator=generator, dtype=torch.float64)
    n = vertices - NUM_FIXED_VERTICES
    stiffness = 0.5 + 10.0 * torch.rand(strands, n, generator=generator, dtype=torch.float64)
    config = EnergyConfig(time_step=1.0 / 30.0, reference_strand_count=strands)
    exponent, tension = 0.125, 0.7
    pre = ChainPreconditioner(rest, stiffness, config, exponent=exponent, tension=tension, device=torch.device("cpu"),
                              dtype=torch.float64)
    h = config.time_step
    g = 9.81 * config.gravity_weight
    inertia = config.inertia_weight * config.vertex_mass / (strands * n * h * h)
    k_min = float(stiffness.min())
    for s in range(strands):
        lengths = rest[s].tolist()
        total = sum(lengths)
        # w of segment j (vertices j, j+1): the weight below its top end
        w = [tension * h * h * g * (total - sum(lengths[:j])) / lengths[j] ** 2 * inertia / k_min
             for j in range(vertices - 1)]
        P = torch.zeros(n, n, dtype=torch.float64)
        for i in range(n):  # free vertex i is strand vertex i + 2: segments i + 1 (above) and i + 2 (below)
            P[i, i] = (float(stiffness[s, i]) / k_min) ** (2 * exponent) + w[i + 1]
            if i + 1 < n:
                P[i, i] += w[i + 2]
                P[i, i + 1] = P[i + 1, i] = -w[i + 2]
        torch.testing.assert_close(pre.matrix[s], P, rtol=1e-12, atol=1e-12)
        R = pre.inverse_factor[s]
        torch.testing.assert_close(R @ R.T, torch.linalg.inv(P), rtol=1e-9, atol=1e-12)
    t = torch.randn(2, strands, n, 3, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(pre.targets(pre.variables(t)), t, rtol=1e-10, atol=1e-12)
    # Without tension it is the stiffness scaling's diagonal: z = t (k / k_min)^a.
    diagonal = ChainPreconditioner(rest, stiffness, config, exponent=exponent, tension=0.0,
                                   device=torch.device("cpu"), dtype=torch.float64)
    torch.testing.assert_close(diagonal.variables(t), t * ((stiffness / k_min) ** exponent)[None, :, :, None])
