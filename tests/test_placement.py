"""Rigid hair placement (Section 3.1.1, Eq. 1) against a numpy reference; rigidity under a
head rotation; roots on the posed surface; batching; gradients; the mesh helpers; bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hairwarp.scene import _geometry
from hairwarp.scene.body import AnimatedMeshBody, default_body
from hairwarp.scene.placement import RigidHair, RootSearch, rigid_placement, root_search
from hairwarp.scene.rotations import axis_angle_to_matrix
from hairwarp.scene.scalp import build_scalp
from references import placement as reference

# float64 placement vs the reference: the same formula, different summation orders.
_F64_TOL = 1e-9
# Roots on the posed surface (the brief: < 0.1 mm).
_ON_SURFACE_TOL = 1e-4
# float32 positions of ~1 m after a 4x4 transform and a mean over 4 000 head vertices.
_F32_TOL = 2e-6
# Faces within this distance [m] of the roots' centroid hold every closest point (the head is
# ~0.25 m across); the reference searches them by brute force.
_REFERENCE_RADIUS = 0.3
NUM_VERTS = 6


@pytest.fixture(scope="module")
def body():
    return default_body()


@pytest.fixture(scope="module")
def scalp(body):
    return build_scalp(body, resolution=32)


def make_strands(scalp, dtype=torch.float32):
    """Strands leaving along the normal and drooping, (M, NUM_VERTS, 3) [m]."""
    t = torch.linspace(0.0, 1.0, NUM_VERTS, dtype=torch.float64)
    p = scalp.positions.double()[:, None] + 0.05 * t[None, :, None] * scalp.normals.double()[:, None]
    p = p + torch.tensor([0.0, -0.03, 0.0], dtype=torch.float64) * (t**2)[None, :, None]
    return p.to(dtype)


@pytest.fixture(scope="module")
def strands(scalp):
    return make_strands(scalp)


def _poses(rng, batch, dtype, scale=0.3):
    poses = torch.from_numpy(rng.normal(0.0, scale, (batch, 66))).to(dtype)
    betas = torch.from_numpy(rng.normal(0.0, 1.0, (batch, 16))).to(dtype)
    trans = torch.from_numpy(rng.normal(0.0, 0.3, (batch, 3))).to(dtype)
    return betas, poses, trans




def test_rest_pose_keeps_the_strands(body, scalp, strands):
    out = rigid_placement(strands, body.pose(poses=torch.zeros(1, 66)), body, scalp)
    assert isinstance(out, RigidHair) and out.positions.shape == (1, 1024, NUM_VERTS, 3)
    assert (out.positions[0] - strands).abs().max() < _ON_SURFACE_TOL
    assert out.align.abs().max() < _F32_TOL
    assert out.root_offsets.norm(dim=-1).max() < _ON_SURFACE_TOL  # scalp roots are on the surface
    assert torch.allclose(out.normals[0], scalp.normals, atol=1e-6)


def test_matches_the_eq1_reference(body, scalp, rng):
    ids = torch.arange(0, 1024, 37)  # 28 strands over the whole grid
    strands = make_strands(scalp, torch.float64)[ids]
    betas, poses, trans = _poses(rng, 2, torch.float64)
    posed = body.pose(betas, poses, trans)
    out = rigid_placement(strands, posed, body, scalp, root_uv=scalp.uv[ids])
    faces = body.faces.long().numpy()
    for b in range(2):
        v = posed.vertices[b].numpy()
        head_centre = v[body.head_vertex_indices.numpy()].mean(0)
        near = np.linalg.norm(v[faces].mean(1) - head_centre, axis=1) < _REFERENCE_RADIUS
        positions, align, offsets = reference.rigid_placement(
            strands.numpy(), v, posed.head_transform[b].numpy(), body.rest_vertices.double().numpy(),
            body.head_vertex_indices.numpy(), faces[near],
        )
        assert np.abs(align).max() > 1e-3  # the pose, shape and translation moved the head
        assert np.abs(out.align[b].numpy() - align).max() < _F64_TOL
        assert np.abs(out.root_offsets[b].numpy() - offsets).max() < _F64_TOL
        assert np.abs(out.positions[b].numpy() - positions).max() < _F64_TOL
    # Normals: the scalp's, rotated by M_head.
    rot = posed.head_transform[:, :3, :3]
    want = torch.einsum("bij,mj->bmi", rot, scalp.normals.double()[ids])
    assert torch.allclose(out.normals, want, atol=1e-6)


def test_head_rotation_moves_the_hair_rigidly(body, scalp, strands):
    aa_head = torch.tensor([0.1, 0.6, -0.2])
    poses = torch.zeros(1, 66)
    poses[0, 45:48] = aa_head
    posed = body.pose(poses=poses)
    out = rigid_placement(strands, posed, body, scalp)
    rot = axis_angle_to_matrix(aa_head.double()).float()
    assert torch.allclose(posed.head_transform[0, :3, :3], rot, atol=1e-6)  # M_head is the rotation
    # Each strand's shape is rotated exactly (Eq. 1 only translates whole strands after M_head).
    rel = out.positions[0] - out.positions[0, :, :1]
    rel_init = strands - strands[:, :1]
    assert (rel - rel_init @ rot.T).abs().max() < _F32_TOL
    # Roots over the rigid part of the head (every vertex within 2 cm weighted to the head
    # joint alone) move rigidly: pairwise distances kept up to the small projection offsets.
    # (At the nape, skin weighted to the neck lags behind a head turn: dt_s0 reaches ~1.5 cm.)
    rest = body.rest_vertices
    near = torch.cdist(strands[:, 0], rest) < 0.02
    head_only = body.model.weights[:, 15] > 1 - 1e-6
    rigid = ~(near & ~head_only[None]).any(1)
    assert rigid.sum() > 500
    offsets = out.root_offsets[0].norm(dim=-1)
    print(f"head rotation: max root offset dt_s0 {offsets[rigid].max() * 1e3:.3f} mm over the rigid head, "
          f"{offsets.max() * 1e3:.2f} mm overall")
    assert offsets[rigid].max() < 1e-4
    roots_init, roots_out = strands[rigid, 0].double(), out.positions[0, rigid, 0].double()
    d_change = torch.cdist(roots_out, roots_out) - torch.cdist(roots_init, roots_init)
    assert d_change.abs().max() <= 2 * offsets[rigid].max() + 1e-6
    assert (out.positions[0] - strands).abs().max() > 0.02  # the hair really moved


def test_roots_lie_on_the_posed_surface(body, scalp, strands, rng):
    betas, poses, trans = _poses(rng, 2, torch.float32, scale=0.35)
    posed = body.pose(betas, poses, trans)
    out = rigid_placement(strands, posed, body, scalp)
    faces = body.faces.long().numpy()
    roots = out.positions[:, ::4, 0].double().numpy()  # every fourth strand: quick brute force
    for b in range(2):
        v = posed.vertices[b].double().numpy()
        near = np.linalg.norm(v[faces].mean(1) - roots[b].mean(0), axis=1) < _REFERENCE_RADIUS
        _, dist = reference.closest_point_on_mesh(roots[b], v, faces[near])
        print(f"frame {b}: max root distance to the posed surface {dist.max() * 1e3:.2e} mm, "
              f"largest dt_s0 {out.root_offsets[b].norm(dim=-1).max() * 1e3:.2f} mm")
        assert len(dist) == 256 and dist.max() < _ON_SURFACE_TOL


def test_batched_equals_per_frame(body, scalp, strands, rng):
    betas, poses, trans = _poses(rng, 3, torch.float32)
    posed = body.pose(betas, poses, trans)
    search = root_search(body, strands[:, 0])
    batched = rigid_placement(strands, posed, body, scalp, search=search)
    for b in range(3):
        single = body.pose(betas[b:b + 1], poses[b:b + 1], trans[b:b + 1])
        one = rigid_placement(strands, single, body, scalp, search=search)
        assert torch.allclose(batched.positions[b], one.positions[0], atol=1e-5)
        assert torch.allclose(batched.normals[b], one.normals[0], atol=1e-6)
    default = rigid_placement(strands, posed, body, scalp)  # builds its own search
    assert torch.equal(default.positions, batched.positions)


def test_normals_without_scalp_and_with_root_uv(body, scalp, strands):
    posed = body.pose(poses=torch.zeros(1, 66))
    own = rigid_placement(strands, posed, body)
    assert torch.allclose(own.normals.norm(dim=-1), torch.ones(1, 1024), atol=1e-5)
    assert ((own.normals[0] * scalp.normals).sum(-1) > np.cos(np.radians(25.0))).all()
    ids = torch.tensor([5, 100, 511, 1000])
    sub = rigid_placement(strands[ids], posed, body, scalp, root_uv=scalp.uv[ids] + 0.004)
    assert torch.allclose(sub.normals[0], scalp.normals[ids])


def test_gradient_with_respect_to_strands_matches_finite_differences(body, scalp):
    ids = torch.tensor([3, 200, 600, 1020])
    strands = make_strands(scalp, torch.float64)[ids][:, :3].clone().requires_grad_()
    poses = torch.zeros(1, 66, dtype=torch.float64)
    poses[0, 36:39] = torch.tensor([0.2, 0.3, 0.0], dtype=torch.float64)
    posed = body.pose(poses=poses)
    search = root_search(body, strands[:, 0].detach())

    def f(s):
        return rigid_placement(s, posed, body, scalp, root_uv=scalp.uv[ids], search=search).positions

    assert torch.autograd.gradcheck(f, (strands,), eps=1e-7, atol=1e-6)
    grad = torch.autograd.grad(f(strands).sum(), strands)[0]
    assert grad.abs().sum() > 0


def test_animated_mesh_body_gives_the_same_placement(body, scalp, strands, rng):
    betas, poses, trans = _poses(rng, 2, torch.float32)
    posed = body.pose(betas, poses, trans)
    anim = AnimatedMeshBody(torch.cat([body.rest_vertices[None], posed.vertices]), body.faces,
                            torch.cat([torch.eye(4)[None], posed.head_transform]),
                            head_vertex_indices=body.head_vertex_indices)
    a = rigid_placement(strands, anim.pose(frames=torch.tensor([1, 2])), anim, scalp)
    b = rigid_placement(strands, posed, body, scalp)
    assert torch.allclose(a.positions, b.positions, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Mesh helpers


def test_closest_point_on_triangles_matches_reference(rng):
    a, b, c = (rng.normal(size=(400, 3)) for _ in range(3))
    c[:20] = a[:20] + 1e-9 * rng.normal(size=(20, 3))  # near-degenerate slivers
    p = rng.normal(size=(400, 3)) * 2.0
    q, bary = _geometry.closest_point_on_triangles(*(torch.from_numpy(x) for x in (p, a, b, c)))
    want = reference.closest_points_on_triangles(p, a, b, c)
    dist_got = np.linalg.norm(q.numpy() - p, axis=1)
    dist_want = np.linalg.norm(want - p, axis=1)
    assert np.abs(dist_got - dist_want).max() < 1e-9
    assert np.abs(q.numpy()[20:] - want[20:]).max() < 1e-9
    assert (bary >= -1e-12).all() and torch.allclose(bary.sum(-1), torch.ones(400, dtype=torch.float64))
    regions = {(int(k > 1e-12), int(m > 1e-12), int(n > 1e-12)) for k, m, n in bary.numpy()}
    assert len(regions) == 7  # vertices, edges and the interior were all exercised


def test_vertex_normals_point_outward(body):
    n = _geometry.vertex_normals(body.rest_vertices.double(), body.faces)
    assert torch.allclose(n.norm(dim=-1), torch.ones(body.num_vertices, dtype=torch.float64))
    top = body.rest_vertices[:, 1].argmax()
    assert n[top, 1] > 0.9


# ------------------------------------------------------------------------------------------
# Bad input


def test_bad_input(body, scalp, strands):
    posed = body.pose(poses=torch.zeros(1, 66))
    with pytest.raises(ValueError, match="strands"):
        rigid_placement(strands[:, 0], posed, body, scalp)
    with pytest.raises(ValueError, match="strands"):
        rigid_placement(torch.full_like(strands, float("nan")), posed, body, scalp)
    with pytest.raises(ValueError, match="strands"):
        rigid_placement(strands[:0], posed, body, scalp)
    with pytest.raises(ValueError, match="posed.vertices"):
        rigid_placement(strands.double(), posed, body, scalp)
    with pytest.raises(ValueError, match="posed"):
        rigid_placement(strands, posed.vertices, body, scalp)
    with pytest.raises(ValueError, match="posed.vertices"):
        cropped = type(posed)(posed.vertices[:, :100], None, posed.head_transform)
        rigid_placement(strands, cropped, body, scalp)
    with pytest.raises(ValueError, match="root_uv"):
        rigid_placement(strands[:10], posed, body, scalp)
    with pytest.raises(ValueError, match="root_uv"):
        rigid_placement(strands[:10], posed, body, scalp, root_uv=scalp.uv[:9])
    with pytest.raises(ValueError, match="search"):
        rigid_placement(strands, posed, body, scalp, search=torch.zeros(10, 4, dtype=torch.int64))
    other = RootSearch(torch.tensor([10**7]), torch.zeros(1, 6, dtype=torch.int64))
    with pytest.raises(ValueError, match="search"):
        rigid_placement(strands, posed, body, scalp, search=other)
    with pytest.raises(ValueError, match="radius"):
        root_search(body, strands[:, 0], radius=-1.0)
    with pytest.raises(ValueError, match="roots"):
        root_search(body, strands[:, 0] + 10.0)
