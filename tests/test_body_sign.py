"""The sign of the body's signed distance on medial axes (`hairwarp.ops.hair_body_contact`).

On a medial axis (a capsule's axis, a slab's mid-plane, a sphere's centre, the middle of the
neck and torso) faces from opposite sides of the surface are equally close. The sign used to
come from `wp.mesh_query_point_sign_normal`, which pools the normals of every face within a
tolerance of the closest distance: opposite normals cancelled and 31 of 300 points on a
capsule's axis, 22 of 400 on a slab's mid-plane, and 22 of 200 medial points of the default
body's neck were called outside. The sign now comes from the pseudo-normal of the single
closest feature, which is exact whichever of the tied faces the query keeps.

Every test first checks that its points are the hard case (inside by the float64 winding
number, with tied closest faces whose normals point against each other), then that none is
called outside, in float32 and float64, with gradient unit length.
"""

import numpy as np
import pytest
import torch

import meshes
from hairwarp.evaluation.stability import winding_numbers
from hairwarp.ops.hair_body_contact import BodyMesh, hair_body_signed_distance, point_mesh_signed_distance
from references import hair_body_contact as ref

# Faces whose distance is within this of the closest count as tied [m]: float32 rounding of
# unit-scale coordinates is ~6e-8 m, so the query may keep any of them.
_TIE_ATOL = 1e-6
# The medial points are found by bisection to this depth resolution [m].
_BISECTION_ATOL = 1e-9

DTYPES = [torch.float32, torch.float64]


def _orient_outward(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum()
    return f if volume > 0 else f[:, [0, 2, 1]]


def capsule(radius=0.1, half_length=0.3, segments=24, rings=8):
    """Closed capsule along y: a cylinder of `radius` with hemispherical caps, outward faces."""
    latitudes = []
    for i in range(1, rings + 1):
        t = -np.pi / 2 + np.pi / 2 * i / rings
        latitudes.append((-half_length + radius * np.sin(t), radius * np.cos(t)))
    for i in range(rings):
        t = np.pi / 2 * i / rings
        latitudes.append((half_length + radius * np.sin(t), radius * np.cos(t)))
    angles = 2 * np.pi * np.arange(segments) / segments
    ring_points = [np.stack([r * np.cos(angles), np.full(segments, y), r * np.sin(angles)], 1) for y, r in latitudes]
    v = np.concatenate([[[0.0, -half_length - radius, 0.0]], *ring_points, [[0.0, half_length + radius, 0.0]]])
    top = len(v) - 1
    f = [[0, 1 + k, 1 + (k + 1) % segments] for k in range(segments)]
    for ring in range(len(latitudes) - 1):
        for k in range(segments):
            a = 1 + ring * segments + k
            b = 1 + ring * segments + (k + 1) % segments
            f += [[a, a + segments, b], [b, a + segments, b + segments]]
    base = 1 + (len(latitudes) - 1) * segments
    f += [[top, base + (k + 1) % segments, base + k] for k in range(segments)]
    f = np.asarray(f)
    return v, _orient_outward(v, f)


def slab(width=0.4, thickness=0.02, n=10):
    """Closed box width x thickness x width (thin along y), each side an n x n grid."""
    v, f = [], []

    def side(origin, u, w):
        base = len(v)
        for i in range(n + 1):
            for j in range(n + 1):
                v.append(np.asarray(origin) + np.asarray(u) * i / n + np.asarray(w) * j / n)
        for i in range(n):
            for j in range(n):
                a = base + i * (n + 1) + j
                f.extend([[a, a + n + 1, a + 1], [a + 1, a + n + 1, a + n + 2]])

    x, y, z = np.array([width, 0, 0]), np.array([0, thickness, 0]), np.array([0, 0, width])
    o = -(x + y + z) / 2
    side(o, z, x), side(o + y, x, z), side(o, x, y), side(o + z, y, x), side(o, y, z), side(o + x, z, y)
    v, f = np.asarray(v), np.asarray(f)
    # Weld the shared borders of the six sides.
    _, first, inverse = np.unique(np.round(v * 1e9).astype(np.int64), axis=0, return_index=True, return_inverse=True)
    v, f = v[first], inverse.reshape(-1)[f]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3).sum() > 0
    return v, f if outward else f[:, [0, 2, 1]]


def _opposite_ties(points, v, f):
    """Per point: whether faces tied (within _TIE_ATOL) for the closest distance include two
    whose normals point against each other: the case that broke the pooled pseudo-normal."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = []
    for p in points:
        _, sq, _ = ref.point_triangle_closest(p[None], a, b, c)
        dist = np.sqrt(sq)
        tied = n[dist <= dist.min() + _TIE_ATOL]
        out.append(bool((tied @ tied.T).min() < 0.0))
    return np.asarray(out)


def _check_inside_everywhere(points, v, f, dtype, *, min_ties):
    p64, v64, f_t = torch.as_tensor(points), torch.as_tensor(v), torch.as_tensor(f)
    winding = winding_numbers(p64, v64, f_t)
    assert bool((winding > 0.5).all()), "the test points must lie inside"
    assert int(_opposite_ties(points, v, f).sum()) >= min_ties, "the test points must be medial (tied faces)"
    p = p64.to(dtype).requires_grad_(True)
    d = point_mesh_signed_distance(p, v64.to(dtype), f_t)
    d.sum().backward()
    called_outside = int((d >= 0).sum())
    assert called_outside == 0, f"{called_outside} of {len(points)} medial points called outside"
    np.testing.assert_allclose(torch.linalg.vector_norm(p.grad, dim=1).double().numpy(), 1.0, atol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES)
def test_capsule_axis_is_inside(rng, dtype):
    v, f = capsule()
    points = np.stack([np.zeros(300), rng.uniform(-0.35, 0.35, 300), np.zeros(300)], axis=1)
    _check_inside_everywhere(points, v, f, dtype, min_ties=200)
    # Depth on the axis between the caps: the inscribed radius of the 24-gon.
    d = point_mesh_signed_distance(torch.as_tensor(points[np.abs(points[:, 1]) < 0.29]), torch.as_tensor(v),
                                   torch.as_tensor(f))
    np.testing.assert_allclose(d.numpy(), -0.1 * np.cos(np.pi / 24), rtol=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_slab_mid_plane_is_inside(rng, dtype):
    v, f = slab()
    points = np.stack([rng.uniform(-0.18, 0.18, 400), np.zeros(400), rng.uniform(-0.18, 0.18, 400)], axis=1)
    _check_inside_everywhere(points, v, f, dtype, min_ties=400)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sphere_centre_is_inside(rng, dtype):
    v, f = meshes.icosphere(4)
    # The centre, and points within 1e-4 of it (edge ~0.08: all faces tie within rounding).
    dirs = rng.normal(size=(100, 3))
    points = np.concatenate([np.zeros((1, 3)), dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * 1e-4])
    _check_inside_everywhere(points, v, f, dtype, min_ties=1)


def _default_body_medial_points(count, lower_joint, upper_joint, seed=0):
    """Points on the medial axis of the default body between two joints' heights: from random
    face centres (|x| < 12 cm: neck and torso, not arms) inward along the face normal, bisected
    to the depth where another face becomes as close as the starting one."""
    from hairwarp.scene.body import default_body
    from hairwarp.scene.skeleton import SMPL_JOINT_NAMES

    body = default_body()
    posed = body.pose()
    v = posed.vertices[0].double()
    f = body.faces.long()
    joints = posed.joints[0, :, :3, 3].double()
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    centre = (a + b + c) / 3
    normal = torch.cross(b - a, c - a, dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    y_lo = joints[SMPL_JOINT_NAMES.index(lower_joint), 1]
    y_hi = joints[SMPL_JOINT_NAMES.index(upper_joint), 1]
    candidates = ((centre[:, 1] > y_lo) & (centre[:, 1] < y_hi) & (centre[:, 0].abs() < 0.12)).nonzero().reshape(-1)
    pick = candidates[torch.randperm(len(candidates), generator=torch.Generator().manual_seed(seed))[:count]]
    start, inward = centre[pick], -normal[pick]
    mesh = BodyMesh(v, f)
    lo = torch.zeros(count, dtype=torch.float64)
    hi = torch.full((count,), 0.3, dtype=torch.float64)
    while bool((hi - lo > _BISECTION_ATOL).any()):
        t = (lo + hi) / 2
        depth = hair_body_signed_distance((start + t[:, None] * inward)[None], mesh)[0].abs()
        past = depth < t - _BISECTION_ATOL  # another face is closer: past the medial axis
        hi, lo = torch.where(past, t, hi), torch.where(past, lo, t)
    return (start + lo[:, None] * inward).numpy(), v.numpy(), f.numpy()


@pytest.mark.parametrize("region", [("neck", "head"), ("pelvis", "spine3")], ids=["neck", "torso"])
def test_default_body_neck_and_torso_medial_axes_are_inside(region):
    points, v, f = _default_body_medial_points(100, *region)
    for dtype in DTYPES:
        _check_inside_everywhere(points, v, f, dtype, min_ties=20)
