"""Tests of the primitive distances: `hairwarp.ops.edge_edge_distance` and
`hairwarp.ops.point_triangle_distance` (Warp kernels in `hairwarp.kernels.distances`) against
numpy float64 brute-force references, finite differences, and degenerate configurations."""

import numpy as np
import pytest
import torch

from hairwarp.ops import edge_edge_distance, point_triangle_distance
from hairwarp.ops.distances import edge_edge_parameters, point_triangle_barycentric
from references import distances as ref

# float64 kernel vs brute force: the reference's ternary search is exact to ~1e-15 in the
# parameter, the distance then to rounding of O(1) coordinates.
F64_ATOL = 1e-12  # [m] for unit-scale inputs
# float32 relative to the coordinate scale: a few ulps of the inputs' differences.
F32_RTOL = 2e-6
# Central differences in float64 with h = 1e-7 m on unit-scale inputs.
FD_H = 1e-7
FD_ATOL = 1e-7


def _t(a, dtype=torch.float64, device="cpu"):
    return torch.tensor(np.asarray(a), dtype=dtype, device=device)


def _random_segments(rng, k, scale=1.0):
    return [rng.normal(size=(k, 3)) * scale for _ in range(4)]


def test_edge_edge_random_matches_reference(rng, device):
    pts = _random_segments(rng, 300)
    d_ref, s_ref, t_ref = ref.edge_edge_distance(*pts)
    assert np.count_nonzero(d_ref > 1e-3) > 250
    d = edge_edge_distance(*(_t(p, device=device) for p in pts))
    assert d.shape == (300,) and d.dtype == torch.float64 and d.device.type == device.type
    np.testing.assert_allclose(d.cpu().numpy(), d_ref, rtol=0, atol=F64_ATOL)
    # Random segments are never parallel: the closest points are unique and must agree too.
    s, t = edge_edge_parameters(*(_t(p, device=device) for p in pts))
    np.testing.assert_allclose(s.cpu().numpy(), s_ref, atol=1e-6)
    np.testing.assert_allclose(t.cpu().numpy(), t_ref, atol=1e-6)
    # Interior, one-clamped and both-clamped closest points all occur in the sample.
    s_np, t_np = s.cpu().numpy(), t.cpu().numpy()
    interior = (s_np > 0) & (s_np < 1) & (t_np > 0) & (t_np < 1)
    assert 10 < np.count_nonzero(interior) < 290


def test_edge_edge_float32_matches_reference(rng, device):
    pts = _random_segments(rng, 300)
    d_ref, _, _ = ref.edge_edge_distance(*pts)
    d = edge_edge_distance(*(_t(p, torch.float32, device) for p in pts))
    assert d.dtype == torch.float32
    np.testing.assert_allclose(d.cpu().double().numpy(), d_ref, rtol=0, atol=F32_RTOL * 4.0)


def test_edge_edge_float32_hair_scale_far_from_origin(rng):
    """Millimetre gaps between 3 mm segments 1.7 m from the origin stay accurate in float32."""
    k = 200
    centre = np.array([0.3, 1.6, 0.2])
    base = centre + rng.normal(size=(k, 3)) * 0.05
    dir_p = rng.normal(size=(k, 3))
    dir_q = rng.normal(size=(k, 3))
    normal = np.cross(dir_p, dir_q)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    p0 = base - 1.5e-3 * dir_p / np.linalg.norm(dir_p, axis=1, keepdims=True)
    p1 = base + 1.5e-3 * dir_p / np.linalg.norm(dir_p, axis=1, keepdims=True)
    gap = rng.uniform(5e-4, 5e-3, size=(k, 1))
    q0 = base + gap * normal - 1.5e-3 * dir_q / np.linalg.norm(dir_q, axis=1, keepdims=True)
    q1 = base + gap * normal + 1.5e-3 * dir_q / np.linalg.norm(dir_q, axis=1, keepdims=True)
    # Round to float32 first so both sides measure the same segments.
    pts32 = [_t(v, torch.float32) for v in (p0, p1, q0, q1)]
    d_ref, _, _ = ref.edge_edge_distance(*(v.double().numpy() for v in pts32))
    assert np.all(d_ref > 4e-4)
    d = edge_edge_distance(*pts32).double().numpy()
    # Differences of nearby float32 coordinates are exact (Sterbenz) and taken before any
    # product, so the error is a few ulps of the gap itself (measured 1.8e-7 relative), not
    # the ~1e-7 m ulp of a 1.7 m coordinate (2e-4 of a 0.5 mm gap) that world-space products
    # would leave.
    np.testing.assert_allclose(d, d_ref, rtol=F32_RTOL, atol=0)


def test_edge_edge_gradient_matches_central_differences(rng):
    pts = _random_segments(rng, 120)
    x = [_t(p).requires_grad_(True) for p in pts]
    d = edge_edge_distance(*x)
    grads = torch.autograd.grad(d.sum(), x)
    assert min(float(g.norm()) for g in grads) > 1.0
    for which in range(4):
        for axis in range(3):
            plus = [p.copy() for p in pts]
            minus = [p.copy() for p in pts]
            plus[which][:, axis] += FD_H
            minus[which][:, axis] -= FD_H
            fd = (ref.edge_edge_distance(*plus)[0] - ref.edge_edge_distance(*minus)[0]) / (2 * FD_H)
            np.testing.assert_allclose(grads[which][:, axis].numpy(), fd, rtol=0, atol=FD_ATOL * 100)


def test_edge_edge_gradcheck():
    rng = np.random.default_rng(7)
    x = [_t(p).requires_grad_(True) for p in _random_segments(rng, 8)]
    assert torch.autograd.gradcheck(edge_edge_distance, x, eps=1e-7, atol=1e-6)


def _segment_cases():
    """Named degenerate configurations: (name, p0, p1, q0, q1, expected distance)."""
    o, ex, ey, ez = np.zeros(3), np.eye(3)[0], np.eye(3)[1], np.eye(3)[2]
    return [
        ("crossing X", -ex, ex, -ey, ey, 0.0),
        ("crossing offset", -ex, ex, -ey + 0.3 * ez, ey + 0.3 * ez, 0.3),
        ("T touching", -ex, ex, o, ey, 0.0),
        ("endpoints touching", o, ex, ex, ex + ey, 0.0),
        ("collinear overlap", o, 2 * ex, ex, 3 * ex, 0.0),
        ("collinear disjoint", o, ex, 2 * ex, 3 * ex, 1.0),
        ("parallel overlap", o, 2 * ex, ex + 0.5 * ey, 3 * ex + 0.5 * ey, 0.5),
        ("parallel disjoint", o, ex, 2 * ex + ey, 3 * ex + ey, np.sqrt(2.0)),
        ("antiparallel", o, 2 * ex, 3 * ex + 0.25 * ez, ex + 0.25 * ez, 0.25),
        ("identical", o, ex, o, ex, 0.0),
        ("zero-length p", ey, ey, -ex, ex, 1.0),
        ("zero-length q", -ex, ex, 2 * ex + ey, 2 * ex + ey, np.sqrt(2.0)),
        ("both zero-length", ey, ey, ez, ez, np.sqrt(2.0)),
        ("same point", ey, ey, ey, ey, 0.0),
        ("point on segment", -ex, ex, 0.5 * ex, 0.5 * ex, 0.0),
        ("near-parallel 1e-6 rad", o, ex, 0.1 * ey + 0.5 * ex, 0.1 * ey + 1.5 * ex + 1e-6 * ey, 0.1),
        ("near-parallel crossing", -ex, ex, -ex - 1e-7 * ey, ex + 1e-7 * ey, 0.0),
    ]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_edge_edge_degenerate_cases(dtype, device):
    cases = _segment_cases()
    names = [c[0] for c in cases]
    pts = [np.stack([c[i] for c in cases]) for i in range(1, 5)]
    expected = np.array([c[5] for c in cases])
    x = [_t(p, dtype, device).requires_grad_(True) for p in pts]
    d = edge_edge_distance(*x)
    grads = torch.autograd.grad(d.sum(), x)
    d = d.detach()
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    for i, name in enumerate(names):
        assert abs(float(d[i]) - expected[i]) <= tol, (name, float(d[i]), expected[i])
        for g in grads:
            assert bool(torch.isfinite(g[i]).all()), name
    # Away from contact the gradient of a distance has unit norm on each side (weights sum to 1).
    g_p = (grads[0] + grads[1]).norm(dim=1)
    g_q = (grads[2] + grads[3]).norm(dim=1)
    apart = expected > 0
    assert int(apart.sum()) >= 8
    np.testing.assert_allclose(g_p.cpu().double().numpy()[apart], 1.0, atol=1e-5)
    np.testing.assert_allclose(g_q.cpu().double().numpy()[apart], 1.0, atol=1e-5)
    # The parameters are in [0, 1] and finite everywhere.
    s, t = edge_edge_parameters(*(v.detach() for v in x))
    assert bool(((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)).all())
    # Crossing X: the subgradient is the unit normal of the two directions (+-z), split by weights.
    i = names.index("crossing X")
    np.testing.assert_allclose(g_p[i].item(), 1.0, atol=1e-6)
    np.testing.assert_allclose(abs((grads[0][i] + grads[1][i])[2].item()), 1.0, atol=1e-6)


def test_edge_edge_near_parallel_matches_reference(rng):
    """Angles from 1e-2 down to 1e-9 rad between overlapping or staggered segments."""
    k = 160
    angles = np.logspace(-9, -2, k)
    offsets = rng.uniform(-1.5, 1.5, size=k)
    gaps = rng.uniform(1e-3, 0.2, size=k)
    p0 = np.zeros((k, 3))
    p1 = np.tile([1.0, 0.0, 0.0], (k, 1))
    q0 = np.stack([offsets, gaps, np.zeros(k)], axis=1)
    q1 = q0 + np.stack([np.cos(angles), np.sin(angles) * rng.choice([-1, 1], size=k), np.zeros(k)], axis=1)
    d_ref, _, _ = ref.edge_edge_distance(p0, p1, q0, q1)
    d = edge_edge_distance(*(_t(v) for v in (p0, p1, q0, q1))).numpy()
    np.testing.assert_allclose(d, d_ref, rtol=0, atol=F64_ATOL)
    d32 = edge_edge_distance(*(_t(v, torch.float32) for v in (p0, p1, q0, q1))).double().numpy()
    np.testing.assert_allclose(d32, d_ref, rtol=0, atol=F32_RTOL)


def test_point_triangle_random_matches_reference(rng, device):
    k = 300
    p, a, b, c = (rng.normal(size=(k, 3)) for _ in range(4))
    d_ref, bary_ref = ref.point_triangle_distance(p, a, b, c)
    d = point_triangle_distance(*(_t(v, device=device) for v in (p, a, b, c)))
    assert d.shape == (k,) and d.device.type == device.type
    np.testing.assert_allclose(d.cpu().numpy(), d_ref, rtol=0, atol=F64_ATOL)
    bary = point_triangle_barycentric(*(_t(v, device=device) for v in (p, a, b, c))).cpu().numpy()
    np.testing.assert_allclose(bary, bary_ref, atol=1e-6)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-12)
    # Face, edge and vertex regions all occur.
    zeros = np.count_nonzero(bary <= 0.0, axis=1)
    for region in (0, 1, 2):  # zero barycentrics: face, edge, vertex
        assert np.count_nonzero(zeros == region) > 5
    d32 = point_triangle_distance(*(_t(v, torch.float32, device) for v in (p, a, b, c)))
    np.testing.assert_allclose(d32.cpu().double().numpy(), d_ref, rtol=0, atol=F32_RTOL * 4.0)


def test_point_triangle_gradient_matches_central_differences(rng):
    k = 120
    pts = [rng.normal(size=(k, 3)) for _ in range(4)]
    x = [_t(v).requires_grad_(True) for v in pts]
    d = point_triangle_distance(*x)
    grads = torch.autograd.grad(d.sum(), x)
    assert float(grads[0].norm()) > 1.0
    for which in range(4):
        for axis in range(3):
            plus = [v.copy() for v in pts]
            minus = [v.copy() for v in pts]
            plus[which][:, axis] += FD_H
            minus[which][:, axis] -= FD_H
            fd = (ref.point_triangle_distance(*plus)[0] - ref.point_triangle_distance(*minus)[0]) / (2 * FD_H)
            np.testing.assert_allclose(grads[which][:, axis].numpy(), fd, rtol=0, atol=FD_ATOL * 100)
    x = [_t(v[:6]).requires_grad_(True) for v in pts]
    assert torch.autograd.gradcheck(point_triangle_distance, x, eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_point_triangle_degenerate_cases(dtype):
    o, ex, ey, ez = np.zeros(3), np.eye(3)[0], np.eye(3)[1], np.eye(3)[2]
    cases = [
        ("above face", 0.2 * ex + 0.2 * ey + 0.5 * ez, o, ex, ey, 0.5),
        ("on face", 0.2 * ex + 0.2 * ey, o, ex, ey, 0.0),
        ("on edge", 0.5 * ex, o, ex, ey, 0.0),
        ("at vertex", ex, o, ex, ey, 0.0),
        ("edge region", 0.5 * ex - ey, o, ex, ey, 1.0),
        ("vertex region", -ex - ey, o, ex, ey, np.sqrt(2.0)),
        ("collinear triangle", ez, o, ex, 2 * ex, 1.0),
        ("collinear beyond", 3 * ex, o, ex, 2 * ex, 1.0),
        ("point triangle", ez, ex, ex, ex, np.sqrt(2.0)),
        ("all one point", ex, ex, ex, ex, 0.0),
    ]
    pts = [np.stack([c[i] for c in cases]) for i in range(1, 5)]
    expected = np.array([c[5] for c in cases])
    x = [_t(v, dtype).requires_grad_(True) for v in pts]
    d = point_triangle_distance(*x)
    grads = torch.autograd.grad(d.sum(), x)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    np.testing.assert_allclose(d.detach().double().numpy(), expected, rtol=0, atol=tol)
    for g in grads:
        assert bool(torch.isfinite(g).all())
    # On the face: the subgradient is the unit normal (+-z); away from it, |dd/dp| = 1.
    assert abs(abs(grads[0][1, 2].item()) - 1.0) < 1e-6
    apart = expected > 0
    np.testing.assert_allclose(grads[0].norm(dim=1).double().numpy()[apart], 1.0, atol=1e-6)
    # dd/dp and the vertex gradients cancel: translating everything leaves d unchanged.
    total = sum(grads)
    assert float(total.abs().max()) < 1e-6


def test_empty_input_and_device(device):
    for fn in (edge_edge_distance, point_triangle_distance):
        empty = [torch.zeros(0, 3, device=device) for _ in range(4)]
        out = fn(*empty)
        assert out.shape == (0,) and out.device.type == device.type


def test_bad_inputs_raise_naming_the_argument():
    good = [torch.rand(5, 3, dtype=torch.float64) for _ in range(4)]
    ops = ((edge_edge_distance, ("p0", "p1", "q0", "q1")), (point_triangle_distance, ("p", "a", "b", "c")))
    for fn, names in ops:
        for i, name in enumerate(names):
            args = list(good)
            args[i] = torch.rand(4, 3, dtype=torch.float64)  # wrong K
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i] = torch.rand(5, 2, dtype=torch.float64)  # wrong last dim
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i] = good[i].float()  # mixed dtype
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i] = good[i].clone()
            args[i][2, 1] = float("nan")
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i][2, 1] = float("inf")
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i] = torch.ones(5, 3, dtype=torch.int32)
            with pytest.raises(ValueError, match=name):
                fn(*args)
            args[i] = good[i].numpy()
            with pytest.raises(ValueError, match=name):
                fn(*args)
