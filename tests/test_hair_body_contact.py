"""Tests of hair-body contact (`hairwarp.ops.hair_body_contact`, Warp kernels in
`hairwarp.kernels.hair_body_contact`): signed distance to a closed body mesh against an exact
numpy float64 brute force, finite-difference gradients, refit, crop, batched bodies, the
Eq. 12 contact energy against the numpy barrier reference, the plain-torch peer, bad input."""

import numpy as np
import pytest
import torch

import meshes
from hairwarp.ops.barrier import barrier_variant_id
from hairwarp.ops.hair_body_contact import (
    BodyMesh,
    _energy_forward,
    hair_body_contact_energy,
    hair_body_signed_distance,
    point_mesh_signed_distance,
)
from hairwarp.torch_reference import hair_body_contact as torch_ref
from references import hair_body_contact as ref

# The paper's hair-body barrier: xi = 1 mm, dhat = 1.5 xi; bp at its final training value.
XI, DHAT, BP = 1.0e-3, 1.5e-3, 0.01
REACH = XI + DHAT

# float64: the kernel refines the closest point in float64 on the face the float32 query
# found, so it matches the brute force to rounding of unit-scale coordinates.
F64_ATOL = 1e-12  # [m]
# float32: coordinates of order 1 m carry ~6e-8 m of rounding, a few operations deep.
F32_ATOL = 1e-6  # [m]
# Central differences in float64 on millimetre distances: truncation ~h^2 d''' is negligible,
# rounding ~1e-16 / h.
FD_H = 1e-7  # [m]
FD_RTOL = 1e-6
# Energies in float32: d carries ~1e-7 m of rounding while B varies on the scale of
# xi = 1 mm, so the barrier values agree to ~1e-4 relative.
F32_ENERGY_RTOL = 2e-3


def _t(a, dtype=torch.float64, device="cpu"):
    return torch.tensor(np.asarray(a), dtype=dtype, device=device)


def _sphere(frequency=8, dtype=torch.float64, device="cpu"):
    v, f = meshes.icosphere(frequency)
    return v, f, _t(v, dtype, device), torch.tensor(f, device=device)


def _random_directions(rng, k):
    u = rng.normal(size=(k, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _face_points(rng, v, f, k, offsets):
    """Points at signed offsets [m] along the outward normal of random face interiors (away
    from edges and vertices): the closest point is the interior point, d = offset."""
    faces = rng.choice(len(f), size=k, replace=False)
    bary = rng.dirichlet([4.0, 4.0, 4.0], size=k)  # concentrated away from the borders
    bary = 0.1 + 0.7 * bary  # every barycentric >= 0.1
    bary /= bary.sum(axis=1, keepdims=True)
    a, b, c = v[f[faces, 0]], v[f[faces, 1]], v[f[faces, 2]]
    on = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return on + np.asarray(offsets)[:, None] * n, on, n


# ---------------------------------------------------------------------------- test meshes


def test_icosphere_is_closed_outward_and_on_the_sphere():
    for freq, (nv, nf) in ((1, (12, 20)), (8, (642, 1280)), (37, (13692, 27380))):
        v, f = meshes.icosphere(freq)
        assert v.shape == (nv, 3) and f.shape == (nf, 3)
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
        directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        assert len(np.unique(directed, axis=0)) == len(directed)  # consistent orientation
        assert len(np.unique(np.sort(directed, axis=1), axis=0)) * 2 == len(directed)  # closed
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        assert np.einsum("ij,ij->i", np.cross(b - a, c - a), a).min() > 0  # outward


# ---------------------------------------------------------------------------- signed distance


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_signed_distance_matches_brute_force(rng, device, dtype):
    v, f, vt, ft = _sphere(dtype=dtype, device=device)
    k = 300
    radius = np.concatenate([rng.uniform(0.2, 1.6, k - 100), 1.0 + rng.uniform(-3e-3, 3e-3, 100)])
    points = _random_directions(rng, k) * radius[:, None]
    points = _t(points, dtype).double().numpy()  # both sides measure the same points
    d_ref, _, g_ref = ref.signed_distance(points, v, f)
    assert np.count_nonzero(d_ref < 0) > 50 and np.count_nonzero(d_ref > 0) > 50
    assert np.count_nonzero(np.abs(d_ref) < REACH) > 30  # points within the barrier's reach

    d = point_mesh_signed_distance(_t(points, dtype, device), vt, ft)
    assert d.shape == (k,) and d.dtype == dtype and d.device.type == device.type
    atol = F64_ATOL if dtype == torch.float64 else F32_ATOL
    np.testing.assert_allclose(d.cpu().double().numpy(), d_ref, rtol=0, atol=atol)
    # Faceting: the icosphere lies within 1 - cos(half the largest edge angle) inside the sphere.
    sagitta = 1.0 - np.min(np.linalg.norm((v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3.0, axis=1))
    assert sagitta < 0.01
    assert np.all(np.abs(d_ref - (np.linalg.norm(points, axis=1) - 1.0)) <= sagitta + 1e-12)


def test_deep_point_depth_matches_sphere_within_faceting():
    v, f, vt, ft = _sphere()
    p = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3], [0.0, 0.6, 0.0]])
    d = point_mesh_signed_distance(_t(p), vt, ft).numpy()
    d_ref, _, _ = ref.signed_distance(p, v, f)
    np.testing.assert_allclose(d, d_ref, atol=F64_ATOL)
    depth = 1.0 - np.linalg.norm(p, axis=1)
    assert np.all(d < 0)
    np.testing.assert_allclose(-d, depth, atol=0.005)  # the sphere's faceting error at f = 8


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_points_on_the_mesh_have_zero_distance_and_finite_gradient(rng, dtype):
    v, f, vt, ft = _sphere(dtype=dtype)
    centroids = v[f].mean(axis=1)
    midpoints = 0.5 * (v[f[:, 0]] + v[f[:, 1]])
    points = np.concatenate([v[:50], centroids[:50], midpoints[:50]])
    p = _t(points, dtype).requires_grad_(True)
    d = point_mesh_signed_distance(p, vt, ft)
    d.sum().backward()
    atol = F64_ATOL if dtype == torch.float64 else F32_ATOL
    assert torch.isfinite(d).all() and torch.isfinite(p.grad).all()
    np.testing.assert_allclose(d.detach().double().numpy(), 0.0, atol=atol)
    # On the surface the gradient is the unit outward face normal: |g| = 1, pointing out.
    norms = torch.linalg.vector_norm(p.grad, dim=1).double().numpy()
    np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    outward = (p.grad.double() * _t(points)).sum(dim=1).numpy()
    assert np.all(outward > 0.9)


def test_signed_distance_gradient_matches_central_differences(rng):
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    offsets = rng.uniform(-0.05, 0.05, 40)
    points, _, normals = _face_points(rng, v, f, 40, offsets)
    x = _t(points).reshape(1, 40, 3).requires_grad_(True)
    d = hair_body_signed_distance(x, body)
    np.testing.assert_allclose(d.detach().numpy().reshape(-1), offsets, atol=1e-9)
    (g,) = torch.autograd.grad(d.sum(), x)
    fd = np.zeros((40, 3))
    for k in range(3):
        step = torch.zeros_like(x)
        step[..., k] = FD_H
        plus = hair_body_signed_distance(x.detach() + step, body)
        minus = hair_body_signed_distance(x.detach() - step, body)
        fd[:, k] = ((plus - minus) / (2 * FD_H)).numpy().reshape(-1)
    np.testing.assert_allclose(g.numpy().reshape(-1, 3), fd, rtol=0, atol=FD_RTOL)
    # Away from edges the gradient is the face normal for every point, inside or out.
    np.testing.assert_allclose(g.numpy().reshape(-1, 3), normals, atol=1e-9)
    # And the reference's gradient agrees for random points near edges and vertices too.
    p = _random_directions(rng, 60) * rng.uniform(0.5, 1.5, (60, 1))
    _, _, g_ref = ref.signed_distance(p, v, f)
    pt = _t(p).requires_grad_(True)
    point_mesh_signed_distance(pt, vt, ft).sum().backward()
    np.testing.assert_allclose(pt.grad.numpy(), g_ref, atol=1e-9)


# ---------------------------------------------------------------------------- energy


def _hair_near_sphere(rng, batch, m, n):
    """Strands whose moving vertices sit at random depths around the unit sphere: inside,
    within the barrier's reach, and beyond it."""
    x = np.empty((batch, m, n, 3))
    for b in range(batch):
        roots = _random_directions(rng, m)
        x[b, :, 0] = roots
        x[b, :, 1] = roots * 1.002
        depth = rng.choice([-0.02, -3e-3, -5e-4, 3e-4, 1.2e-3, 2e-3, 0.05], size=(m, n - 2))
        depth = depth + rng.uniform(-2e-4, 2e-4, size=depth.shape)
        dirs = roots[:, None] + rng.normal(scale=0.05, size=(m, n - 2, 3))
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        x[b, :, 2:] = dirs * (1.0 + depth[..., None])
    return x


@pytest.mark.parametrize("variant", ["quadratic", "monotone", "paper"])
def test_energy_matches_reference(rng, device, variant):
    v, f, vt, ft = _sphere(device=device)
    x = _hair_near_sphere(rng, 2, 6, 9)
    e_ref, g_ref = ref.hair_body_contact_energy(x, v, f, XI, DHAT, BP, weight=3.0, variant=variant)
    d_ref, _, _ = ref.signed_distance(x[:, :, 2:].reshape(-1, 3), v, f)
    assert np.count_nonzero((d_ref < REACH) & (d_ref > 0)) > 10 and np.count_nonzero(d_ref < 0) > 10
    assert np.all(e_ref > 0)

    body = BodyMesh(vt, ft)
    xt = _t(x, device=device).requires_grad_(True)
    e = hair_body_contact_energy(xt, body, XI, DHAT, BP, weight=3.0, variant=variant)
    assert e.shape == (2,) and e.dtype == torch.float64
    np.testing.assert_allclose(e.detach().cpu().numpy(), e_ref, rtol=1e-9)
    e.sum().backward()
    scale = np.abs(g_ref).max()
    np.testing.assert_allclose(xt.grad.cpu().numpy(), g_ref, rtol=0, atol=1e-9 * scale)
    assert torch.count_nonzero(xt.grad[:, :, :2]) == 0  # fixed vertices

    # float32: same hair rounded, energies to the float32 tolerance.
    x32 = _t(x, torch.float32, device)
    e32 = hair_body_contact_energy(x32, BodyMesh(vt.float(), ft), XI, DHAT, BP, weight=3.0, variant=variant)
    assert e32.dtype == torch.float32
    e_ref32, _ = ref.hair_body_contact_energy(x32.double().cpu().numpy(), v, f, XI, DHAT, BP, 3.0, variant)
    np.testing.assert_allclose(e32.cpu().double().numpy(), e_ref32, rtol=F32_ENERGY_RTOL)


def test_energy_gradient_matches_central_differences(rng):
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    m, n = 4, 7
    # Moving vertices in face interiors at offsets spanning the polynomial piece (inside and
    # d < d_b) and the log piece (d_b < d < xi + dhat), away from the pieces' joins.
    offsets = rng.choice([-2e-3, -4e-4, 5e-4, 1.3e-3, 1.9e-3, 2.3e-3], size=m * (n - 2))
    offsets = offsets + rng.uniform(-5e-5, 5e-5, size=offsets.shape)
    points, _, _ = _face_points(rng, v, f, m * (n - 2), offsets)
    x = np.zeros((1, m, n, 3))
    x[0, :, 2:] = points.reshape(m, n - 2, 3)
    x[0, :, 0] = x[0, :, 2] * 1.01
    x[0, :, 1] = x[0, :, 2] * 1.02
    xt = _t(x).requires_grad_(True)
    e = hair_body_contact_energy(xt, body, XI, DHAT, BP, weight=1e6)
    (g,) = torch.autograd.grad(e.sum(), xt)
    assert torch.count_nonzero(torch.linalg.vector_norm(g, dim=-1)) == m * (n - 2)
    fd = torch.zeros_like(g)
    for s in range(m):
        for vtx in range(2, n):
            for k in range(3):
                step = torch.zeros_like(xt)
                step[0, s, vtx, k] = FD_H
                plus = hair_body_contact_energy(xt.detach() + step, body, XI, DHAT, BP, weight=1e6)
                minus = hair_body_contact_energy(xt.detach() - step, body, XI, DHAT, BP, weight=1e6)
                fd[0, s, vtx, k] = ((plus - minus) / (2 * FD_H))[0]
    np.testing.assert_allclose(g.numpy(), fd.numpy(), rtol=0, atol=FD_RTOL * g.abs().max().item())


def test_deep_penetration_is_pushed_out_and_fixed_vertices_ignored():
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    x = np.zeros((1, 1, 4, 3))
    x[0, 0, 0] = [0.0, 0.0, 0.0]  # fixed vertices deep inside: no energy, no gradient
    x[0, 0, 1] = [0.0, 0.1, 0.0]
    x[0, 0, 2] = [0.0, 0.5, 0.0]  # 0.5 m deep
    x[0, 0, 3] = [0.0, 2.0, 0.0]  # far outside
    xt = _t(x).requires_grad_(True)
    e = hair_body_contact_energy(xt, body, XI, DHAT, BP)
    e.sum().backward()
    d = ref.signed_distance(x[0, 0, 2:], v, f)[0]
    e_ref, _ = ref.hair_body_contact_energy(x, v, f, XI, DHAT, BP)
    assert e.item() > 0 and d[0] < -0.4
    np.testing.assert_allclose(e.detach().numpy(), e_ref, rtol=1e-9)
    assert torch.count_nonzero(xt.grad[0, 0, [0, 1, 3]]) == 0
    # Descent moves the deep vertex outward (the default barrier keeps increasing with depth).
    assert xt.grad[0, 0, 2, 1].item() < 0


def test_strand_walk_skips_queries_and_matches_per_vertex_kernel(rng):
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    m, n = 16, 40
    # Strands that graze the surface near the root and leave it radially: most vertices are
    # far outside, a few within the reach or inside.
    roots = _random_directions(rng, m)
    t = np.clip(np.arange(n) - 2.0, 0.0, None) / (n - 3)
    radius = 1.0 - 3e-3 + 0.6 * t[None, :, None] ** 2 + rng.normal(scale=2e-4, size=(m, n, 1))
    hair = roots[:, None] * radius
    x = _t(hair)[None]
    variant_id = barrier_variant_id("quadratic")  # the reference's default
    e_s, g_s, q_s = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "strand")
    e_v, g_v, q_v = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "vertex")
    e_ref, g_ref = ref.hair_body_contact_energy(hair[None], v, f, XI, DHAT, BP)
    d_ref = ref.signed_distance(hair[:, 2:].reshape(-1, 3), v, f)[0]
    assert np.count_nonzero(d_ref < REACH) > m and e_ref[0] > 0
    np.testing.assert_allclose(e_s.numpy(), e_ref, rtol=1e-9)
    np.testing.assert_allclose(e_v.numpy(), e_ref, rtol=1e-9)
    torch.testing.assert_close(g_s, g_v, rtol=0, atol=1e-12 * g_v.abs().max().item())
    np.testing.assert_allclose(g_s.numpy(), g_ref, rtol=0, atol=1e-9 * np.abs(g_ref).max())
    # The walk proves most vertices far outside without a query; the per-vertex kernel
    # queries every moving vertex at least once.
    assert int(q_s.sum()) < 0.3 * m * (n - 2)
    assert int(q_v.sum()) >= m * (n - 2)


def _in_and_out_strands(rng, m=24, n=30):
    """Strands through a unit sphere with segments longer than the reach: each starts at a
    random radius (far outside, near the surface or deep inside), then crosses the surface in
    and out along a wavy radial path, so capped queries miss on both sides of the body."""
    directions = _random_directions(rng, m)
    t = np.linspace(0.0, 1.0, n)
    start = rng.uniform(0.3, 1.6, size=(m, 1))
    phase = rng.uniform(0, 6, size=(m, 1))
    radius = start + 0.7 * np.sin(2 * np.pi * (t[None] * rng.uniform(0.5, 1.5, size=(m, 1))) + phase)
    radius = np.clip(radius, 0.05, None)
    wobble = rng.normal(scale=0.02, size=(m, n, 3))
    return directions[:, None] * radius[..., None] + wobble


def test_two_pass_vertex_kernel_matches_unbounded_queries_in_and_out(rng):
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    hair = _in_and_out_strands(rng)
    m, n = hair.shape[:2]
    x = _t(hair)[None]
    variant_id = barrier_variant_id("quadratic")
    e_v, g_v, q_v = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "vertex")
    e_s, g_s, _ = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "strand")
    e_ref, g_ref = ref.hair_body_contact_energy(hair[None], v, f, XI, DHAT, BP)
    d_ref = ref.signed_distance(hair.reshape(-1, 3), v, f)[0].reshape(m, n)
    # The scene holds every case: deep inside, far outside, segments longer than the reach.
    seg = np.linalg.norm(np.diff(hair, axis=1), axis=2)
    assert (d_ref[:, 2:] < -0.2).sum() > 20 and (d_ref[:, 2:] > 0.2).sum() > 20 and np.median(seg) > 10 * REACH
    np.testing.assert_allclose(e_v.numpy(), e_ref, rtol=1e-9)
    np.testing.assert_allclose(e_v.numpy(), e_s.numpy(), rtol=1e-12)
    np.testing.assert_allclose(g_v.numpy(), g_ref, rtol=0,
                               atol=1e-9 * np.abs(g_ref).max())
    torch.testing.assert_close(g_v, g_s, rtol=0, atol=1e-12 * g_s.abs().max().item())
    # Unbounded queries only where a capped query missed inside (and at a root that missed):
    # never for a moving vertex outside beyond its cap.
    q = q_v.numpy().reshape(m, n)
    far_outside = d_ref > 1.01 * np.maximum(REACH, np.concatenate([np.zeros((m, 1)), seg], axis=1))
    assert (q[:, 2:][far_outside[:, 2:]] == 1).all()
    assert (q[:, 2:][d_ref[:, 2:] < 0] >= 1).all() and (q == 2).sum() > 0


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_capped_signed_distance_equals_clamped_unbounded(rng, dtype):
    from hairwarp.ops.hair_body_contact import hair_body_signed_distance_and_normal

    _, _, vt, ft = _sphere(dtype=dtype)
    body = BodyMesh(vt, ft)
    x = _t(_in_and_out_strands(rng, m=16, n=20), dtype)[None].expand(2, -1, -1, -1)
    d, g = hair_body_signed_distance_and_normal(x, body)
    cap = 0.1
    dc, gc = hair_body_signed_distance_and_normal(x, body, max_distance=cap)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(dc, d.clamp(max=cap), rtol=0, atol=tol)
    near = d <= cap
    torch.testing.assert_close(gc[near], g[near], rtol=0, atol=tol)
    assert torch.count_nonzero(gc[~near]) == 0 and (d > cap).sum() > 10 and (d < -cap).sum() > 10
    with pytest.raises(ValueError, match="max_distance"):
        hair_body_signed_distance_and_normal(x, body, max_distance=0.0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_keep_out_push_moves_near_and_inside_vertices_to_the_margin(rng, device, dtype):
    """`hair_body_keep_out_push`: each moving vertex with push_above < d < push_below (d the capped
    signed distance) lands `margin` outside, moved along the outward direction; fixed and far
    vertices are untouched bit for bit, and the count is theirs (added to a caller's counter)."""
    from hairwarp.ops import hair_body_keep_out_push
    from hairwarp.ops.hair_body_contact import hair_body_signed_distance_and_normal

    _, _, vt, ft = _sphere(dtype=dtype, device=device)
    body = BodyMesh(vt, ft)
    x = _t(_in_and_out_strands(rng, m=16, n=20), dtype, device)[None].expand(2, -1, -1, -1)
    margin, below, cap = 0.05, 0.025, 0.1
    tol = F64_ATOL if dtype == torch.float64 else F32_ATOL
    d, g = hair_body_signed_distance_and_normal(x, body, max_distance=cap)
    moving = torch.zeros_like(d, dtype=torch.bool)
    moving[..., 2:] = True
    for above in (-float("inf"), -0.2):
        chosen = moving & (d < below) & (d > above)
        counter = torch.full((1,), 7, dtype=torch.int32, device=device)
        pushed, count = hair_body_keep_out_push(x, body, margin=margin, push_below=below, push_above=above,
                                                max_distance=cap, pushed_count=counter)
        assert count is counter and int(count) == 7 + int(chosen.sum())
        assert int(chosen.sum()) > 20 and int((moving & ~chosen).sum()) > 20  # both kinds present
        assert bool((d[..., :2] < below).any())  # fixed vertices that would be pushed if they moved
        assert torch.equal(pushed[~chosen], x[~chosen])
        torch.testing.assert_close(pushed[chosen], x[chosen] + (margin - d[chosen])[:, None] * g[chosen], rtol=0, atol=tol)
        # On this convex body the closest point stays: the pushed vertices are `margin` outside.
        after = hair_body_signed_distance(pushed, body)[chosen]
        torch.testing.assert_close(after, torch.full_like(after, margin), rtol=0, atol=10 * tol)
    assert bool((d < -0.2).any())  # the window left deep ones where they were
    pushed, count = hair_body_keep_out_push(x[0], body, margin=margin, push_below=below, max_distance=cap)
    assert pushed.shape == x[0].shape and int(count) == int((moving[0] & (d[0] < below)).sum())


def test_keep_out_push_queries_only_the_active_strands_and_flags_the_pushed_ones(rng, device):
    """`hair_body_keep_out_push(active_strands=, pushed_strands=)`: a strand flagged 0 is copied
    bit for bit even where it is inside; the active ones are pushed as with no flags; every strand
    with a pushed vertex, and no other, is flagged 1 (the next round's active strands)."""
    from hairwarp.ops import hair_body_keep_out_push

    _, _, vt, ft = _sphere(dtype=torch.float64, device=device)
    body = BodyMesh(vt, ft)
    x = _t(_in_and_out_strands(rng, m=16, n=20), torch.float64, device)[None].expand(2, -1, -1, -1).contiguous()
    x[:, 10:] += 10.0  # six strands far from the body
    settings = dict(margin=0.05, push_below=0.025, max_distance=0.1)
    everything, _ = hair_body_keep_out_push(x, body, **settings)
    moved = (everything != x).any(-1).any(-1)  # (2, 16): strands with a pushed vertex
    assert bool(moved[:, :10].all()) and not bool(moved[:, 10:].any())
    active = torch.ones((2, 16), dtype=torch.int32, device=device)
    active[0, ::2] = 0
    active[1, 1::2] = 0
    flagged = torch.zeros((2, 16), dtype=torch.int32, device=device)
    pushed, count = hair_body_keep_out_push(x, body, **settings, active_strands=active, pushed_strands=flagged)
    on = active.bool()
    assert torch.equal(pushed[~on], x[~on]) and torch.equal(pushed[on], everything[on])
    assert torch.equal(flagged.bool(), moved & on)
    assert int(count) == int(((everything != x).any(-1) & on[..., None]).sum())
    with pytest.raises(ValueError, match="active_strands"):
        hair_body_keep_out_push(x, body, **settings, active_strands=active[0])
    with pytest.raises(ValueError, match="pushed_strands"):
        hair_body_keep_out_push(x, body, **settings, pushed_strands=flagged.long())


def test_keep_out_push_bad_input_raises_naming_the_argument():
    from hairwarp.ops import hair_body_keep_out_push

    _, _, vt, ft = _sphere(frequency=2)
    body = BodyMesh(vt, ft)
    x = torch.zeros(2, 4, 3, dtype=torch.float64)
    settings = dict(margin=1e-3, push_below=5e-4, max_distance=1e-2)
    with pytest.raises(ValueError, match="x: expected shape"):
        hair_body_keep_out_push(x[..., :2], body, **settings)
    with pytest.raises(ValueError, match="x: expected shape"):
        hair_body_keep_out_push(x[0], body, **settings)
    with pytest.raises(ValueError, match="x: contains NaN"):
        hair_body_keep_out_push(x + float("nan"), body, **settings)
    with pytest.raises(ValueError, match="x: expected dtype"):
        hair_body_keep_out_push(x.half(), body, **settings)
    with pytest.raises(ValueError, match="body: expected a BodyMesh"):
        hair_body_keep_out_push(x, (vt, ft), **settings)
    with pytest.raises(ValueError, match="body: batch size"):
        hair_body_keep_out_push(x[None].expand(3, -1, -1, -1), BodyMesh(vt[None].expand(2, -1, -1), ft), **settings)
    with pytest.raises(ValueError, match="margin"):
        hair_body_keep_out_push(x, body, **{**settings, "margin": -1e-3})
    with pytest.raises(ValueError, match="margin"):
        hair_body_keep_out_push(x, body, **{**settings, "margin": float("nan")})
    with pytest.raises(ValueError, match="max_distance"):
        hair_body_keep_out_push(x, body, **{**settings, "max_distance": 0.0})
    with pytest.raises(ValueError, match="push_below"):
        hair_body_keep_out_push(x, body, **{**settings, "push_below": 0.1})
    with pytest.raises(ValueError, match="push_above"):
        hair_body_keep_out_push(x, body, **settings, push_above=1e-3)
    with pytest.raises(ValueError, match="pushed_count: expected dtype"):
        hair_body_keep_out_push(x, body, **settings, pushed_count=torch.zeros(1))
    with pytest.raises(ValueError, match="pushed_count: expected shape"):
        hair_body_keep_out_push(x, body, **settings, pushed_count=torch.zeros(2, dtype=torch.int32))


def test_far_hair_has_zero_energy_and_gradient():
    _, _, vt, ft = _sphere()
    x = torch.zeros(2, 3, 5, 3, dtype=torch.float64)
    x[..., 1] = 1.5 + torch.arange(5, dtype=torch.float64) * 0.01
    x.requires_grad_(True)
    e = hair_body_contact_energy(x, BodyMesh(vt, ft), XI, DHAT, BP)
    e.sum().backward()
    assert torch.equal(e.detach(), torch.zeros(2, dtype=torch.float64))
    assert torch.count_nonzero(x.grad) == 0


def test_unbatched_hair_and_noncontiguous_inputs(rng):
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    x = _hair_near_sphere(rng, 1, 5, 6)[0]
    e_ref, g_ref = ref.hair_body_contact_energy(x[None], v, f, XI, DHAT, BP)
    # A transposed (non-contiguous) view of the same hair, as a leaf.
    leaf = _t(np.ascontiguousarray(x.transpose(1, 0, 2))).transpose(0, 1).requires_grad_(True)
    assert not leaf.is_contiguous()
    e = hair_body_contact_energy(leaf, body, XI, DHAT, BP)
    assert e.dim() == 0
    np.testing.assert_allclose(e.item(), e_ref[0], rtol=1e-9)
    e.backward()
    np.testing.assert_allclose(leaf.grad.numpy(), g_ref[0], atol=1e-9 * np.abs(g_ref).max())
    # A non-contiguous (expanded) upstream gradient for a batched call.
    xb = _t(x)[None].expand(3, -1, -1, -1).clone().requires_grad_(True)
    eb = hair_body_contact_energy(xb, body, XI, DHAT, BP)
    with torch.no_grad():
        xb.add_(0.5)  # mutated between forward and backward: the saved gradient is unaffected
    upstream = torch.tensor([2.0], dtype=torch.float64).expand(3)
    eb.backward(upstream)
    np.testing.assert_allclose(xb.grad[1].numpy(), 2.0 * g_ref[0], atol=1e-9 * np.abs(g_ref).max())


# ---------------------------------------------------------------------------- refit, batch


def _deform(v, t):
    """A smooth deformation that keeps the sphere closed and outward: stretch and twist."""
    angle = t * v[:, 1]
    c, s = np.cos(angle), np.sin(angle)
    out = v * np.array([1.0 + 0.3 * t, 1.0 - 0.2 * t, 1.0])
    x, z = out[:, 0].copy(), out[:, 2].copy()
    out[:, 0], out[:, 2] = c * x - s * z, s * x + c * z
    return out + np.array([0.1 * t, 0.0, -0.05 * t])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_refit_matches_fresh_build(rng, device, dtype):
    v, f, vt, ft = _sphere(dtype=dtype, device=device)
    body = BodyMesh(vt, ft)
    moved = _deform(v, 0.7)
    body.update(_t(moved, dtype, device))
    fresh = BodyMesh(_t(moved, dtype, device), ft)
    x = _hair_near_sphere(rng, 1, 6, 8)
    x[..., :] = _deform(x.reshape(-1, 3), 0.7).reshape(x.shape)
    xt = _t(x, dtype, device)
    d_refit = hair_body_signed_distance(xt, body)
    d_fresh = hair_body_signed_distance(xt, fresh)
    torch.testing.assert_close(d_refit, d_fresh, rtol=0, atol=0)
    moved_rounded = _t(moved, dtype).double().numpy()
    d_ref, _, _ = ref.signed_distance(xt.double().cpu().numpy().reshape(-1, 3), moved_rounded, f)
    atol = F64_ATOL if dtype == torch.float64 else F32_ATOL
    np.testing.assert_allclose(d_refit.cpu().double().numpy().reshape(-1), d_ref, atol=atol)
    torch.testing.assert_close(
        hair_body_contact_energy(xt, body, XI, DHAT, BP), hair_body_contact_energy(xt, fresh, XI, DHAT, BP)
    )
    np.testing.assert_allclose(body.vertices.cpu().double().numpy(), _t(moved, dtype).double().numpy())
    # The deformation moved the surface: the distances really changed.
    assert (hair_body_signed_distance(xt, BodyMesh(vt, ft)) - d_refit).abs().max() > 0.01


def test_batched_bodies_match_one_at_a_time(rng, device):
    v, f, _, ft = _sphere(device=device)
    poses = np.stack([_deform(v, t) for t in (0.0, 0.4, -0.6)])
    x = _hair_near_sphere(rng, 3, 5, 7)
    for b in range(3):
        x[b] = _deform(x[b].reshape(-1, 3), (0.0, 0.4, -0.6)[b]).reshape(x[b].shape)
    body = BodyMesh(_t(poses, device=device), ft)
    assert body.batch_size == 3 and body.batched
    xt = _t(x, device=device)
    e = hair_body_contact_energy(xt, body, XI, DHAT, BP)
    d = hair_body_signed_distance(xt, body)
    e_ref, _ = ref.hair_body_contact_energy(x, poses, f, XI, DHAT, BP)
    assert np.all(e_ref > 0) and len(set(np.round(e_ref, 20))) == 3
    np.testing.assert_allclose(e.cpu().numpy(), e_ref, rtol=1e-9)
    for b in range(3):
        single = BodyMesh(_t(poses[b], device=device), ft)
        torch.testing.assert_close(d[b], hair_body_signed_distance(xt[b], single), rtol=0, atol=0)
    # Batched refit: every pose moves.
    moved = np.stack([_deform(v, t) for t in (0.1, 0.2, 0.3)])
    body.update(_t(moved, device=device))
    e_ref2, _ = ref.hair_body_contact_energy(x, moved, f, XI, DHAT, BP)
    e2 = hair_body_contact_energy(xt, body, XI, DHAT, BP)
    np.testing.assert_allclose(e2.cpu().numpy(), e_ref2, rtol=1e-9)
    # One body shared by every hair batch item.
    shared = BodyMesh(_t(poses[1], device=device), ft)
    e_shared = hair_body_contact_energy(xt, shared, XI, DHAT, BP)
    e_ref3, _ = ref.hair_body_contact_energy(x, poses[1], f, XI, DHAT, BP)
    np.testing.assert_allclose(e_shared.cpu().numpy(), e_ref3, rtol=1e-9)
    with pytest.raises(ValueError, match="body"):
        hair_body_contact_energy(xt[:2], body, XI, DHAT, BP)


# ---------------------------------------------------------------------------- crop


def _cap_hair(rng, v, m=24, n=14, length=0.3):
    hair, roots, arc = meshes.hair_on_cap(v, (0.0, 0.0, 0.0), m, n, length, rng, jitter=2e-3)
    return hair, roots, arc


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_crop_keeps_every_distance_and_energy_within_reach(rng, dtype):
    v, f, vt, ft = _sphere(dtype=dtype)
    hair, roots, arc = _cap_hair(rng, v)
    body = BodyMesh(vt, ft)
    crop = body.crop_for_hair(_t(roots, dtype), _t(arc, dtype), margin=0.1)
    removed = 1.0 - crop.num_faces / body.num_faces
    assert removed > 0.3, removed
    assert not crop.watertight and crop.batch_size == 1
    # The crop's faces are the full body's faces it says they are.
    idx = crop.face_indices.numpy()
    np.testing.assert_array_equal(
        crop.vertices.double().numpy()[crop.faces.numpy()], _t(v, dtype).double().numpy()[f[idx]]
    )
    x = _t(hair, dtype)
    d_full = hair_body_signed_distance(x, body)
    d_crop = hair_body_signed_distance(x, crop)
    d_ref, _, _ = ref.signed_distance(x.double().numpy().reshape(-1, 3), _t(v, dtype).double().numpy(), f)
    assert np.count_nonzero(d_ref < 0) > 5 and np.count_nonzero(np.abs(d_ref) < REACH) > 5
    # Equal up to the rounding of a tie between faces that the two BVHs break differently.
    tie_atol = F64_ATOL if dtype == torch.float64 else 1e-7
    torch.testing.assert_close(d_crop, d_full, rtol=0, atol=tie_atol)
    e_full = hair_body_contact_energy(x, body, XI, DHAT, BP)
    e_crop = hair_body_contact_energy(x, crop, XI, DHAT, BP)
    assert e_full.item() > 0
    rtol = 1e-9 if dtype == torch.float64 else F32_ENERGY_RTOL
    torch.testing.assert_close(e_crop, e_full, rtol=rtol, atol=0)


def test_crop_outside_the_reach_may_differ():
    """The crop rule covers points whose closest body point lies inside the balls; a point
    elsewhere (here below the sphere, far from the crown balls) measures to the nearest kept
    triangle instead, and the open cap's pseudo-normal even calls it inside: the crop is
    only valid for the hair it was made for."""
    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    crop = body.crop(_t([[0.0, 1.0, 0.0]]), _t([0.5]))
    below = _t([[0.0, -1.2, 0.0]])
    d_full = point_mesh_signed_distance(below, vt, ft)
    d_crop = hair_body_signed_distance(below.reshape(1, 1, 3), crop).reshape(1)
    np.testing.assert_allclose(d_full.numpy(), [0.2], atol=0.01)
    assert abs(d_crop.item()) > 1.5
    # Inside the balls nothing changes.
    near = _t([[0.05, 1.002, 0.0], [0.0, 0.95, 0.1]])
    d_near = hair_body_signed_distance(near.reshape(1, 2, 3), crop).reshape(2)
    torch.testing.assert_close(d_near, point_mesh_signed_distance(near, vt, ft), rtol=0, atol=F64_ATOL)


def test_crop_of_batched_body_and_update_through_the_full_vertices(rng):
    v, f, _, ft = _sphere()
    poses = np.stack([_deform(v, t) for t in (0.0, 0.3)])
    body = BodyMesh(_t(poses), ft)
    hair, roots, arc = _cap_hair(rng, v, m=10, n=8)
    crop = body.crop_for_hair(_t(roots), _t(arc))
    assert crop.batch_size == 2 and crop.num_faces < body.num_faces
    moved = np.stack([_deform(v, t) for t in (0.05, 0.35)])
    body.update(_t(moved))
    crop.update(_t(moved))  # the full body's vertices: the crop picks its own
    x = _t(np.stack([hair, hair]))
    d_crop = hair_body_signed_distance(x, crop)
    torch.testing.assert_close(d_crop, hair_body_signed_distance(x, body), rtol=0, atol=F64_ATOL)


# ---------------------------------------------------------------------------- torch peer


def test_torch_reference_matches_numpy_reference(rng):
    v, f, vt, ft = _sphere(frequency=4)
    x = _hair_near_sphere(rng, 2, 3, 6)
    x[..., :] = x * 1.0  # same points
    d_ref, _, g_ref = ref.signed_distance(x.reshape(-1, 3), v, f)
    xt = _t(x).requires_grad_(True)
    d = torch_ref.hair_body_signed_distance(xt, vt, ft)
    np.testing.assert_allclose(d.detach().numpy().reshape(-1), d_ref, atol=F64_ATOL)
    e = torch_ref.hair_body_contact_energy(xt, vt, ft, XI, DHAT, BP, weight=2.0)
    e_ref, ge_ref = ref.hair_body_contact_energy(x, v, f, XI, DHAT, BP, weight=2.0)
    np.testing.assert_allclose(e.detach().numpy(), e_ref, rtol=1e-9)
    e.sum().backward()
    np.testing.assert_allclose(xt.grad.numpy(), ge_ref, atol=1e-9 * np.abs(ge_ref).max())
    # Batched poses and the small chunk path.
    poses = np.stack([v, _deform(v, 0.3)])
    dp = torch_ref.hair_body_signed_distance(_t(x), _t(poses), ft)
    d_pose = ref.signed_distance(x[1].reshape(-1, 3), poses[1], f)[0]
    np.testing.assert_allclose(dp[1].numpy().reshape(-1), d_pose, atol=F64_ATOL)
    small = torch_ref.point_mesh_signed_distance(_t(x.reshape(-1, 3)), vt, ft, chunk_pairs=100)
    np.testing.assert_allclose(small.numpy(), d_ref, atol=F64_ATOL)


# ---------------------------------------------------------------------------- bad input


def test_bvh_choice_gives_the_same_distances(rng, device):
    """The BVH ("sah", or "lbvh" built on the GPU; the CPU falls back to "sah") changes only the
    speed of the queries; a bad choice is an error naming `bvh`."""
    v, f, vt, ft = _sphere(device=device)
    x = _hair_near_sphere(rng, 2, 6, 9)
    xt = _t(x, device=device)
    results = [hair_body_signed_distance(xt, BodyMesh(vt, ft, bvh=bvh)) for bvh in ("sah", "lbvh")]
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=F64_ATOL)  # ties may pick other faces
    np.testing.assert_allclose(results[0].cpu().numpy().reshape(-1),
                               ref.signed_distance(x.reshape(-1, 3), v, f)[0], atol=F64_ATOL)
    with pytest.raises(ValueError, match="bvh"):
        BodyMesh(vt, ft, bvh="octree")


def test_bad_meshes_raise_naming_the_argument():
    v, f, vt, ft = _sphere(frequency=2)
    p = _t([[0.0, 0.0, 0.0]])
    _, open_faces = meshes.open_cap(v, f, above=-0.5)
    with pytest.raises(ValueError, match="faces: the mesh is not watertight"):
        point_mesh_signed_distance(p, vt, torch.tensor(open_faces))
    with pytest.raises(ValueError, match="faces: vertex index out of range"):
        point_mesh_signed_distance(p, vt, torch.where(ft == 5, 1000, ft))
    with pytest.raises(ValueError, match="faces: vertex index out of range"):
        BodyMesh(vt, torch.where(ft == 5, -1, ft))
    with pytest.raises(ValueError, match="faces: the mesh encloses a negative volume"):
        BodyMesh(vt, ft[:, [0, 2, 1]])
    flipped = ft.clone()
    flipped[0] = flipped[0, [0, 2, 1]]
    with pytest.raises(ValueError, match="faces: inconsistent orientation"):
        BodyMesh(vt, flipped)
    repeated = ft.clone()
    repeated[3, 1] = repeated[3, 0]
    with pytest.raises(ValueError, match="faces: 1 faces repeat"):
        BodyMesh(vt, repeated)
    with pytest.raises(ValueError, match="faces: expected dtype"):
        BodyMesh(vt, ft.float())
    with pytest.raises(ValueError, match="faces: expected shape"):
        BodyMesh(vt, ft[:, :2])
    with pytest.raises(ValueError, match="faces: expected a non-empty"):
        BodyMesh(vt, ft[:0])
    with pytest.raises(ValueError, match="vertices: expected a non-empty"):
        BodyMesh(vt[:0], ft)
    with pytest.raises(ValueError, match="vertices: contains NaN"):
        BodyMesh(torch.where(vt == vt[0, 0], float("nan"), vt), ft)
    with pytest.raises(ValueError, match="vertices: expected dtype"):
        BodyMesh(vt.half(), ft)
    with pytest.raises(ValueError, match="faces: expected a tensor on cpu"):
        BodyMesh(vt, ft.to("meta"))
    # Open meshes are accepted only on request (no sign guarantee near their borders).
    assert BodyMesh(vt, torch.tensor(open_faces), require_watertight=False).num_faces == len(open_faces)


def test_bad_points_and_hair_raise_naming_the_argument():
    _, _, vt, ft = _sphere(frequency=2)
    body = BodyMesh(vt, ft)
    with pytest.raises(ValueError, match="points: contains NaN"):
        point_mesh_signed_distance(_t([[float("nan"), 0.0, 0.0]]), vt, ft)
    with pytest.raises(ValueError, match="points: expected dtype"):
        point_mesh_signed_distance(torch.zeros(2, 3, dtype=torch.int64), vt, ft)
    with pytest.raises(ValueError, match="points: expected shape"):
        point_mesh_signed_distance(torch.zeros(2, 2, dtype=torch.float64), vt, ft)
    with pytest.raises(ValueError, match="points: expected a non-empty"):
        point_mesh_signed_distance(torch.zeros(0, 3, dtype=torch.float64), vt, ft)
    with pytest.raises(ValueError, match="vertices: expected a tensor on cpu"):
        point_mesh_signed_distance(_t([[0.0, 0.0, 0.0]]), vt.to("meta"), ft)
    x = torch.zeros(2, 4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="x: expected shape"):
        hair_body_contact_energy(x[..., :2], body, XI, DHAT, BP)
    with pytest.raises(ValueError, match="x: contains NaN"):
        hair_body_contact_energy(x + float("inf"), body, XI, DHAT, BP)
    with pytest.raises(ValueError, match="x: expected a non-empty"):
        hair_body_signed_distance(x[:0], body)
    with pytest.raises(ValueError, match="body: expected a BodyMesh"):
        hair_body_contact_energy(x, (vt, ft), XI, DHAT, BP)
    with pytest.raises(ValueError, match="x: expected a tensor on cpu"):
        hair_body_signed_distance(x.to("meta"), body)
    with pytest.raises(ValueError, match="xi"):
        hair_body_contact_energy(x, body, -1.0, DHAT, BP)
    with pytest.raises(ValueError, match="bp"):
        hair_body_contact_energy(x, body, XI, DHAT, 1.5)
    with pytest.raises(ValueError, match="variant"):
        hair_body_contact_energy(x, body, XI, DHAT, BP, variant="cubic")
    with pytest.raises(ValueError, match="weight"):
        hair_body_contact_energy(x, body, XI, DHAT, BP, weight=float("nan"))
    with pytest.raises(ValueError, match="vertices: expected shape"):
        body.update(vt[None])
    with pytest.raises(ValueError, match="vertices: expected 42 vertices"):
        body.update(vt[:-1])
    with pytest.raises(ValueError, match="vertices: expected dtype"):
        body.update(vt.half())
    with pytest.raises(ValueError, match="reach_radii: expected non-negative"):
        body.crop(vt[:2], _t([0.1, -0.1]))
    with pytest.raises(ValueError, match="reach_radii: expected shape"):
        body.crop(vt[:2], _t([0.1]))
    with pytest.raises(ValueError, match="reach_centers: no body triangle"):
        body.crop(_t([[10.0, 0.0, 0.0]]), _t([0.1]))
    with pytest.raises(ValueError, match="margin"):
        body.crop_for_hair(vt[:2], _t([0.1, 0.1]), margin=-1.0)


def test_the_distance_cache_skips_queries_and_changes_nothing(rng):
    """`HairBodyDistanceCache`: over a sequence of small moves (an optimizer's evaluations) the
    energy and gradient equal the uncached ones while most queries are skipped; after the body
    moves, a reset makes it exact again (a stale cache would not be)."""
    from hairwarp.ops.hair_body_contact import HairBodyDistanceCache

    v, f, vt, ft = _sphere()
    body = BodyMesh(vt, ft)
    # Hair-like strands: 3 mm segments from roots just under the surface, leaving it at
    # shallow angles (most vertices outside and a few millimetres to centimetres away, some
    # grazing or dipping inside).
    m, n = 32, 40
    roots = _random_directions(rng, m)
    tangent = np.cross(roots, _random_directions(rng, m))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    tilt = rng.uniform(-0.1, 0.4, size=(m, 1))
    direction = tangent + tilt * roots
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    hair = roots[:, None] * (1.0 - 5e-4) + 3e-3 * np.arange(n)[None, :, None] * direction[:, None]
    variant_id = barrier_variant_id("quadratic")
    cache = HairBodyDistanceCache()
    skipped = 0
    for step in range(6):
        moved = hair + rng.normal(scale=2e-4, size=hair.shape) * (step > 0)
        x = _t(moved)[None]
        e0, g0, q0 = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "vertex")
        e1, g1, q1 = _energy_forward(x, body, XI, DHAT, BP, 1.0, variant_id, "vertex", cache)
        assert torch.equal(e0, e1) and torch.equal(g0, g1)
        assert int(q1.sum()) <= int(q0.sum())
        skipped += int(q0.sum() - q1.sum())
    assert skipped > 2 * m * n  # most vertices skip, step after step
    # The body moves 5 cm: the cache's bounds no longer hold until it is reset.
    shifted = BodyMesh(vt + torch.tensor([0.05, 0.0, 0.0], dtype=vt.dtype), ft)
    x = _t(hair)[None]
    e0, g0, _ = _energy_forward(x, shifted, XI, DHAT, BP, 1.0, variant_id, "vertex")
    cache.reset()
    e1, g1, _ = _energy_forward(x, shifted, XI, DHAT, BP, 1.0, variant_id, "vertex", cache)
    assert torch.equal(e0, e1) and torch.equal(g0, g1)
