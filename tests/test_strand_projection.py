"""Follow-the-leader length projection (`hairwarp.ops.follow_the_leader`): a numpy float64
reference written from the recurrence, finite differences, rest lengths kept, degenerate
targets, bad input, and the network option that uses it (`StaticConfig.length_projection`)."""

import numpy as np
import pytest
import torch

from hairwarp.models import StaticConfig, StaticNetwork, apply_deformation
from hairwarp.ops import follow_the_leader


def reference_follow_the_leader(rigid: np.ndarray, target: np.ndarray) -> np.ndarray:
    """x_0 = q_0, x_1 = q_1, x_i = x_{i-1} + |r_i - r_{i-1}| (q_i - x_{i-1}) / |q_i - x_{i-1}|."""
    x = target.copy()
    for i in range(2, rigid.shape[-2]):
        rest = np.linalg.norm(rigid[..., i, :] - rigid[..., i - 1, :], axis=-1, keepdims=True)
        d = target[..., i, :] - x[..., i - 1, :]
        x[..., i, :] = x[..., i - 1, :] + rest * d / np.linalg.norm(d, axis=-1, keepdims=True)
    return x


def make_pair(seed: int, batch=2, strands=5, vertices=9, dtype=torch.float64):
    g = np.random.default_rng(seed)
    rigid = np.cumsum(g.normal(scale=0.01, size=(batch, strands, vertices, 3)), axis=-2)
    target = rigid + g.normal(scale=0.01, size=rigid.shape)
    target[..., :2, :] = rigid[..., :2, :]
    return torch.tensor(rigid, dtype=dtype), torch.tensor(target, dtype=dtype)


@pytest.mark.parametrize("tiled", [False, True])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_matches_float64_reference_and_keeps_rest_lengths(dtype, tol, tiled):
    """Both kernels: a thread per strand, and a block per strand with the strand in shared memory
    (the CUDA default; on the CPU a block is one thread)."""
    rigid, target = make_pair(0, dtype=dtype)
    x = follow_the_leader(rigid, target, tiled=tiled)
    expected = reference_follow_the_leader(rigid.double().numpy(), target.double().numpy())
    assert np.abs(x.double().numpy() - expected).max() < tol
    seg = (x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1)
    rest = (rigid[..., 1:, :] - rigid[..., :-1, :]).norm(dim=-1)
    assert float((seg - rest).abs().max()) < tol
    assert torch.equal(x[..., :2, :], target[..., :2, :])


@pytest.mark.parametrize("tiled", [False, True])
@pytest.mark.parametrize("vertices", [3, 6, 7, 12])  # the adjoint's four-vertex chunks and what is left
def test_gradient_matches_central_differences(vertices, tiled):
    rigid, target = make_pair(1, batch=1, strands=3, vertices=vertices)
    target.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: follow_the_leader(rigid, t, tiled=tiled), (target,), eps=1e-7, atol=1e-7)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the tile kernels' blocks of 32 threads need a CUDA device")
def test_cuda_tile_kernels_match_the_one_thread_kernels():
    rigid, target = make_pair(4, batch=2, strands=64, vertices=100, dtype=torch.float32)
    rigid, target = rigid.cuda(), target.cuda().requires_grad_(True)
    weights = torch.randn_like(target)
    for max_gain in (None, 3.0):  # the exact adjoint, and training's capped one
        results = []
        for tiled in (False, True):
            x = follow_the_leader(rigid, target, tiled=tiled, max_gain=max_gain)
            (g,) = torch.autograd.grad((x * weights).sum(), target)
            results.append((x, g))
        assert torch.allclose(results[0][0], results[1][0], atol=1e-6)
        # float32 rounding in another order along a 100-vertex carry: measured 1.8e-5 of the
        # largest gradient on an H100.
        scale = float(results[0][1].abs().max())
        assert torch.allclose(results[0][1], results[1][1], rtol=0, atol=1e-4 * scale)


def test_a_rigid_target_is_left_where_it_is():
    rigid, _ = make_pair(2)
    assert torch.allclose(follow_the_leader(rigid, rigid), rigid, atol=1e-14, rtol=0)


def capped_gain_adjoint_reference(rigid, target, grad, max_gain):
    """dL/dq of the projection with each gain l_i / |q_i - x_(i-1)| capped, float64, a torch
    reverse sweep written from x_i = x_(i-1) + l_i unit(q_i - x_(i-1)): d x_i / d q_i = J_i =
    min(l_i / |v_i|, cap) (I - u_i u_i^T), d x_i / d x_(i-1) = I - J_i."""
    x = follow_the_leader(rigid, target)
    rest = (rigid[..., 1:, :] - rigid[..., :-1, :]).norm(dim=-1, keepdim=True)
    g = grad.clone()
    out = torch.zeros_like(target)
    for i in range(target.shape[-2] - 1, 1, -1):
        v = target[..., i, :] - x[..., i - 1, :]
        u = v / v.norm(dim=-1, keepdim=True)
        gain = (rest[..., i - 1, :] / v.norm(dim=-1, keepdim=True)).clamp(max=max_gain)
        gi = g[..., i, :]
        out[..., i, :] = gain * (gi - (gi * u).sum(-1, keepdim=True) * u)
        g[..., i - 1, :] += gi - out[..., i, :]
    out[..., :2, :] = g[..., :2, :]
    return out


@pytest.mark.parametrize("tiled", [False, True])
def test_a_capped_gain_matches_the_reference_sweep_and_bounds_the_gradient(tiled):
    """`max_gain`: the same forward; the adjoint equals a float64 sweep with the gains capped;
    a cap no vertex reaches is the exact adjoint; a target near its leader (gain ~100) gets a
    gradient bounded by the cap."""
    torch.manual_seed(3)
    rigid = torch.zeros(2, 3, 9, 3, dtype=torch.float64)
    rigid[..., 1] = -0.01 * torch.arange(9, dtype=torch.float64)
    target = rigid + 0.003 * torch.randn_like(rigid)
    weights = torch.randn_like(rigid)

    def grad(**kw):
        t = target.clone().requires_grad_(True)
        x = follow_the_leader(rigid, t, tiled=tiled, **kw)
        (x * weights).sum().backward()
        return x.detach(), t.grad

    exact_x, exact = grad()
    x, capped = grad(max_gain=1e9)
    torch.testing.assert_close(x, exact_x, atol=0, rtol=0)
    torch.testing.assert_close(capped, exact, atol=1e-12, rtol=1e-10)
    # vertex 5's target 1e-4 m from where vertex 4 lands: its exact gain is ~100
    target[:, :, 5] = follow_the_leader(rigid, target)[:, :, 4] + torch.tensor([1e-4, 0.0, 0.0], dtype=torch.float64)
    _, exact = grad()
    _, capped = grad(max_gain=2.0)
    torch.testing.assert_close(capped, capped_gain_adjoint_reference(rigid, target, weights, 2.0), atol=1e-12, rtol=1e-10)
    assert float(exact[:, :, 5].norm(dim=-1).max()) > 20 * float(weights.abs().max())
    assert float(capped[:, :, 5].norm(dim=-1).max()) < 2.0 * float(weights[:, :, 5:].norm(dim=-1).sum(-1).max()) + 1e-9
    with pytest.raises(ValueError, match="max_gain"):
        follow_the_leader(rigid, target, max_gain=0.0)


def test_target_on_its_leader_keeps_the_rigid_direction_with_a_finite_gradient():
    rigid, target = make_pair(3, batch=1, strands=1, vertices=5)
    target[0, 0, 2] = target[0, 0, 1]  # q_2 on top of x_1: no direction to follow
    target.requires_grad_(True)
    x = follow_the_leader(rigid, target)
    assert torch.allclose(x[0, 0, 2] - x[0, 0, 1], rigid[0, 0, 2] - rigid[0, 0, 1], atol=1e-14)
    (g,) = torch.autograd.grad(x.sum(), target)
    assert torch.isfinite(g).all() and float(g[0, 0, 2].abs().max()) == 0.0


def test_bad_input_names_the_argument():
    rigid, target = make_pair(4)
    with pytest.raises(ValueError, match="target: expected shape"):
        follow_the_leader(rigid, target[:, :3])
    with pytest.raises(ValueError, match="target: expected dtype"):
        follow_the_leader(rigid, target.float())
    with pytest.raises(ValueError, match="rigid: expected"):
        follow_the_leader(rigid[..., :2, :], target[..., :2, :])
    bad = target.clone()
    bad[0, 0, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="target: contains NaN"):
        follow_the_leader(rigid, bad)
    with pytest.raises(ValueError, match="length_projection"):
        apply_deformation(rigid, torch.zeros(2, 8, 8, 9, 3, dtype=rigid.dtype), torch.rand(5, 2, dtype=rigid.dtype),
                          "stretchy")
    with pytest.raises(ValueError, match="length_projection"):
        StaticConfig(length_projection="stretchy")


def test_network_with_the_projection_drapes_inextensibly():
    """A tiny static network whose (large, random) map would stretch strands keeps every rest
    length when its config asks for the projection, and trains through it (finite gradient)."""
    torch.manual_seed(0)
    cfg = StaticConfig.tiny()
    cfg.head_init_gain = 1.0  # decimetre deformations: stretch without the projection
    rigid, _ = make_pair(5, batch=2, strands=6, vertices=cfg.num_vertices, dtype=torch.float32)
    root_uv = torch.rand(6, 2)
    z, beta, theta = torch.randn(2, cfg.latent_dim), torch.randn(2, 16), torch.randn(2, 66) * 0.1
    rest = (rigid[..., 1:, :] - rigid[..., :-1, :]).norm(dim=-1)
    for projection, stretched in (("none", True), ("follow_the_leader", False)):
        net = StaticNetwork(StaticConfig(**{**cfg.to_dict(), "length_projection": projection}))
        x = net.drape(z, beta, theta, rigid, root_uv)
        change = float(((x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1) - rest).abs().max().detach())
        assert (change > 1e-2) == stretched, (projection, change)
    x.square().sum().backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads)
