"""The scalp grid of the rest head (Section 3.1): roots on the surface, outward normals,
the UV layout, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hairwarp.scene.body import default_body
from hairwarp.scene.scalp import Scalp, build_scalp, fit_cranium_sphere, grid_subset, grid_uv, scalp_directions
from references.placement import closest_point_on_mesh

# Roots must lie on the rest surface (the brief: < 0.1 mm); ray hits are exact up to float32
# storage of ~0.5 m coordinates (~3e-8 m).
_ON_SURFACE_TOL = 1e-4
# Interpolated vertex normals vs the normal of the face that holds the root: smooth heads
# keep them within a few degrees; 25 deg bounds the sharpest crease of the scalp.
_NORMAL_ANGLE_TOL_DEG = 25.0


@pytest.fixture(scope="module")
def body():
    return default_body()


@pytest.fixture(scope="module")
def scalp(body):
    return build_scalp(body, resolution=32)


def test_grid_layout(scalp):
    assert isinstance(scalp, Scalp) and scalp.num_roots == 1024 and scalp.resolution == 32
    assert scalp.uv.dtype == scalp.positions.dtype == scalp.normals.dtype == torch.float32
    uv = scalp.uv.reshape(32, 32, 2)
    assert torch.allclose(uv[0, :, 0], (torch.arange(32) + 0.5) / 32)  # u along a row
    assert torch.allclose(uv[:, 0, 1], (torch.arange(32) + 0.5) / 32)  # v down the columns
    assert ((scalp.uv > 0) & (scalp.uv < 1)).all()


def test_roots_lie_on_the_rest_surface(body, scalp):
    v = body.rest_vertices.double().numpy()
    f = body.faces.long().numpy()
    near = np.linalg.norm(v[f].mean(1) - scalp.positions.double().numpy().mean(0), axis=1) < 0.25
    roots = scalp.positions.double().numpy()[::3]  # every third root keeps the brute force quick
    _, dist = closest_point_on_mesh(roots, v, f[near])
    assert len(dist) == 342
    print(f"scalp roots: max distance to the rest surface {dist.max() * 1e3:.2e} mm")
    assert dist.max() < _ON_SURFACE_TOL


def test_normals_are_unit_outward_and_match_the_surface(body, scalp):
    n = scalp.normals.double()
    assert torch.allclose(n.norm(dim=1), torch.ones(1024, dtype=torch.float64), atol=1e-6)
    centre, _ = fit_cranium_sphere(body.rest_vertices.double()[body.head_vertex_indices])
    radial = scalp.positions.double() - centre
    assert ((radial * n).sum(1) > 0.5 * radial.norm(dim=1)).all()  # outward, within 60 deg of radial
    # Against the face normal at the closest triangle.
    v = body.rest_vertices.double()
    f = body.faces.long()
    tri = v[f]
    face_n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nearest = torch.cdist(scalp.positions.double(), tri.mean(1)).argmin(1)
    cos = (torch.nn.functional.normalize(face_n[nearest], dim=1) * n).sum(1)
    assert cos.min() > np.cos(np.radians(_NORMAL_ANGLE_TOL_DEG))


def test_scalp_covers_the_top_of_the_head_only(body, scalp):
    v = body.rest_vertices
    head = v[body.head_vertex_indices]
    p = scalp.positions
    # Top of the head reached; the front row (the hairline) stays on the forehead, well above
    # the middle of the head region (chin to crown), so off the face.
    assert float(p[:, 1].max()) > float(v[:, 1].max()) - 2e-3
    low, top = float(head[:, 1].min()), float(head[:, 1].max())
    hairline = p.reshape(32, 32, 3)[0]
    assert float(hairline[:, 1].min()) > low + 0.6 * (top - low)
    # Distinct roots (the elliptical map has no collapsed pole); the closest pair (1.4 mm)
    # sits at a grid corner, where the square's corner cells squeeze onto the rim.
    d = torch.cdist(p.double(), p.double()) + torch.eye(1024, dtype=torch.float64)
    assert float(d.min()) > 1e-3
    # Left-right symmetric layout: u -> 1 - u mirrors x.
    grid = p.reshape(32, 32, 3)
    assert torch.allclose(grid.flip(1)[:, :, 0], -grid[:, :, 0], atol=2e-3)
    # v grows from the forehead (+z) to the nape (-z).
    assert float(grid[0, 16, 2]) > float(grid[31, 16, 2]) + 0.1


def test_deterministic_and_other_resolutions(body, scalp):
    again = build_scalp(body, resolution=32)
    assert torch.equal(again.positions, scalp.positions) and torch.equal(again.normals, scalp.normals)
    small = build_scalp(body, resolution=8)
    assert small.num_roots == 64 and small.resolution == 8
    assert torch.equal(small.uv, grid_uv(8))


def test_directions_are_unit_and_the_pole_is_up():
    uv = torch.tensor([[0.5, 0.5], [0.0, 0.5], [0.5, 0.0], [0.5, 1.0]], dtype=torch.float64)
    d = scalp_directions(uv, front_deg=50.0, side_deg=90.0, back_deg=130.0)
    assert torch.allclose(d.norm(dim=1), torch.ones(4, dtype=torch.float64))
    assert torch.allclose(d[0], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    angles = torch.rad2deg(torch.acos(d[1:, 1]))
    assert torch.allclose(angles, torch.tensor([90.0, 50.0, 130.0], dtype=torch.float64))
    assert d[1, 0] < 0 and d[2, 2] > 0 and d[3, 2] < 0  # u = 0: body's right; v = 0: front


def test_bad_input(body):
    for resolution in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="resolution"):
            build_scalp(body, resolution=resolution)
    with pytest.raises(ValueError, match="front_deg"):
        build_scalp(body, front_deg=0.0)
    with pytest.raises(ValueError, match="back_deg"):
        build_scalp(body, back_deg=190.0)


@pytest.mark.parametrize("stride", [2, 4, 8, 16, 64])
def test_a_strided_scalp_covers_the_whole_head(scalp, stride):
    """One root in `stride`, spread over the scalp: every quarter of the grid keeps its share,
    and no two kept roots are nearer than a square lattice of the same density allows (the
    row-major slice kept columns: stride 16 left two columns, one edge and the middle)."""
    quick = scalp.every(stride)
    keep = grid_subset(32, stride)
    assert quick.num_roots == keep.numel() == 1024 // stride
    assert torch.equal(quick.uv, scalp.uv[keep]) and torch.equal(quick.positions, scalp.positions[keep])
    assert keep.unique().numel() == keep.numel() and torch.equal(keep, keep.sort().values)
    u, v = quick.uv[:, 0], quick.uv[:, 1]
    for left in (u < 0.5, u >= 0.5):
        for top in (v < 0.5, v >= 0.5):
            assert int((left & top).sum()) == pytest.approx(quick.num_roots / 4, abs=max(1, quick.num_roots / 16))
    cells = torch.stack([keep // 32, keep % 32], 1).double()
    gap = torch.cdist(cells, cells).fill_diagonal_(float("inf")).min()
    assert gap >= 0.9 * stride ** 0.5
    # The whole head, side to side (x) and front to back (z): the kept roots span most of the
    # full scalp's extent.
    span = scalp.positions.max(0).values - scalp.positions.min(0).values
    kept = quick.positions.max(0).values - quick.positions.min(0).values
    assert (kept[[0, 2]] > 0.75 * span[[0, 2]]).all()


def test_grid_subset_edges(scalp):
    assert torch.equal(grid_subset(32, 1), torch.arange(1024))
    assert grid_subset(32, 5).numel() in (204, 205)
    assert grid_subset(32, 5000).numel() == 1
    assert scalp.every(1) is scalp
    odd = Scalp(uv=scalp.uv[:100], positions=scalp.positions[:100], normals=scalp.normals[:100], resolution=32)
    assert torch.equal(odd.every(3).uv, scalp.uv[:100:3])  # not a full grid: every 3rd, in its order
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="stride"):
            grid_subset(32, bad)
        with pytest.raises(ValueError, match="stride"):
            scalp.every(bad)
