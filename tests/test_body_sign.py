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


# ------------------------------------------------------------------ self-intersecting bodies
# A posed body passes through itself (skinning puts the upper arm into the chest at the armpit):
# a point inside the arm whose closest face is a chest face lying inside the arm was signed by
# that face, "outside". On `table1` (the default body, arms down) 487 vertices of the rigid
# placement lay more than 1 mm inside by the winding number yet were called outside (up to
# 93 mm deep), and the contact energy let L-BFGS park hair there (docs/contact.md 14).


def box(lo, hi):
    """Closed box [lo, hi] (12 outward triangles)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return lo + corners * (hi - lo), f


def overlapping_boxes(shift=0.0):
    """One closed mesh of two boxes that pass through each other: A = [0, 2] x [0, 1]^2 and a
    thinner B = [1, 3] x [0.25, 0.75]^2 (moved by `shift` along x). B's face x = 1 lies wholly
    inside A; A's face x = 2 crosses B."""
    va, fa = box([0, 0, 0], [2, 1, 1])
    vb, fb = box([1 + shift, 0.25, 0.25], [3 + shift, 0.75, 0.75])
    return np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)])


# Points with their signed distance to the union's boundary, by hand: inside A only (closest
# face of the mesh: B's face x = 1, inside A), inside B only (closest: A's face x = 2, inside B),
# inside both, outside.
UNION_POINTS = np.array([[0.9, 0.5, 0.5], [2.1, 0.5, 0.5], [1.5, 0.5, 0.5], [2.9, 0.5, 0.5], [2.5, 0.9, 0.5],
                         [0.5, 0.5, 0.5], [-0.3, 0.5, 0.5]])
UNION_DISTANCES = np.array([-0.5, -0.25, -0.5, -0.1, 0.15, -0.5, 0.3])


@pytest.mark.parametrize("dtype", DTYPES)
def test_overlapping_boxes_are_signed_and_measured_as_their_union(rng, dtype):
    v, f = overlapping_boxes()
    vt, ft = torch.as_tensor(v, dtype=dtype), torch.as_tensor(f)
    plain = BodyMesh(vt, ft, split_self_intersections=False)
    body = BodyMesh(vt, ft)
    # The hard case: the uncut mesh signs the points inside one box near the other's face "outside".
    d_plain = hair_body_signed_distance(torch.as_tensor(UNION_POINTS, dtype=dtype)[None], plain)[0]
    assert float(d_plain[0]) > 0 and float(d_plain[1]) > 0
    cut = body.self_intersections
    assert cut["crossing_faces"] == 10 and cut["inside_faces"] == 2 and cut["pieces"] > 0
    d = hair_body_signed_distance(torch.as_tensor(UNION_POINTS, dtype=dtype)[None], body)[0]
    atol = 1e-12 if dtype == torch.float64 else 1e-6
    np.testing.assert_allclose(d.double().numpy(), UNION_DISTANCES, atol=atol)
    _check_union_of_boxes(rng, body, v, ft, dtype, atol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_body_split_over_the_poses_it_moves_through_is_signed_as_their_union_there(rng, dtype):
    """Built apart (nothing crossing) and moved by `update` into a pose where its parts cross, a
    body knows the crossing only if the split saw that pose (`split_poses`): then it is signed as
    the union there and measured exactly outside it; without, a point inside one part near the
    other's face is "outside" (the physics flung hair pinched between a swinging arm and the chest)."""
    apart, f = overlapping_boxes(shift=2.0)
    crossed, _ = overlapping_boxes()
    ft = torch.as_tensor(f)
    points = torch.as_tensor(UNION_POINTS, dtype=dtype)[None]
    moved = BodyMesh(torch.as_tensor(apart, dtype=dtype), ft)
    assert moved.self_intersections["pieces"] == 0
    moved.update(torch.as_tensor(crossed, dtype=dtype))
    d_moved = hair_body_signed_distance(points, moved)[0]
    assert float(d_moved[0]) > 0 and float(d_moved[1]) > 0  # signed wrong: the crossing was never cut
    body = BodyMesh(torch.as_tensor(apart, dtype=dtype), ft, split_poses=torch.as_tensor(crossed, dtype=dtype)[None])
    assert body.self_intersections["crossing_faces"] > 0 and body.self_intersections["pieces"] > 0
    apart_d = hair_body_signed_distance(points, body)[0]
    plain_apart = hair_body_signed_distance(points, BodyMesh(torch.as_tensor(apart, dtype=dtype), ft))[0]
    atol = 1e-12 if dtype == torch.float64 else 1e-6
    np.testing.assert_allclose(apart_d.double().numpy(), plain_apart.double().numpy(), atol=atol)  # its own pose
    body.update(torch.as_tensor(crossed, dtype=dtype))
    d = hair_body_signed_distance(points, body)[0].double().numpy()
    # Signed as the union; inside it the pieces left in (not inside in the apart pose) are
    # nearer than the union's boundary, as in any body split over several poses.
    np.testing.assert_array_equal(np.sign(d), np.sign(UNION_DISTANCES))
    outside = UNION_DISTANCES > 0
    np.testing.assert_allclose(d[outside], UNION_DISTANCES[outside], atol=atol)
    assert bool((np.abs(d[~outside]) <= np.abs(UNION_DISTANCES[~outside]) + atol).all())
    _check_union_of_boxes(rng, body, crossed, ft, dtype, atol)
    with pytest.raises(ValueError, match="split_poses"):
        BodyMesh(torch.as_tensor(apart, dtype=dtype), ft, split_poses=torch.zeros(1, 5, 3, dtype=dtype))


def _check_union_of_boxes(rng, body, v, ft, dtype, atol):
    """Random points around `overlapping_boxes()`: the sign is the float64 winding number's
    wherever the point is off the surface, and outside the union the distance is the exact one
    (the nearer of the two boxes').
    """
    points = rng.uniform([-0.5, -0.3, -0.3], [3.5, 1.3, 1.3], size=(3000, 3))
    d = hair_body_signed_distance(torch.as_tensor(points, dtype=dtype)[None], body)[0].double()
    inside = winding_numbers(torch.as_tensor(points), torch.as_tensor(v), ft) > 0.5
    off = d.abs() > 1e-5
    assert int(off.sum()) > 2900 and int(inside.sum()) > 300
    assert bool(((d < 0) == inside)[off].all())
    outside = (~inside).numpy()
    exact = np.minimum(_box_distance(points[outside], [0, 0, 0], [2, 1, 1]),
                       _box_distance(points[outside], [1, 0.25, 0.25], [3, 0.75, 0.75]))
    np.testing.assert_allclose(d.numpy()[outside], exact, atol=atol)


def test_a_piece_budget_keeps_the_union_signed_exactly(rng, monkeypatch):
    """A body whose parts cross along long seams (primitives overlapping everywhere) stops
    cutting at `SELF_INTERSECTION_MAX_PIECES`: coarser pieces on the crossing, signed by the
    winding number where their side is not known. The sign stays the winding number's, and
    outside the union the distance stays exact (an outside point's closest point on the mesh
    lies on the union's boundary, whatever the pieces).
    """
    import hairwarp.ops.hair_body_contact as hb

    v, f = overlapping_boxes()
    vt, ft = torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f)
    fine = BodyMesh(vt, ft).self_intersections["pieces"]
    monkeypatch.setattr(hb, "SELF_INTERSECTION_MAX_PIECES", 16)
    body = BodyMesh(vt, ft)
    cut = body.self_intersections
    assert cut["crossing_faces"] == 10 and cut["inside_faces"] == 2
    assert 0 < cut["pieces"] <= 16 < fine
    _check_union_of_boxes(rng, body, v, ft, torch.float64, 1e-12)


def _box_distance(points, lo, hi):
    """Distance from points outside the box [lo, hi] to it."""
    return np.linalg.norm(np.maximum(np.maximum(np.asarray(lo) - points, points - np.asarray(hi)), 0.0), axis=1)


def test_contact_energy_on_a_self_intersecting_body_equals_the_unbounded_queries():
    """The two-pass energy kernel carries a capped query's side along a strand: on the cut
    surface it matches the barrier of every vertex's own unbounded signed distance."""
    from hairwarp.ops.barrier import barrier, barrier_variant_id
    from hairwarp.ops.hair_body_contact import _energy_forward

    v, f = overlapping_boxes()
    body = BodyMesh(torch.as_tensor(v), torch.as_tensor(f))
    # Strands from above the boxes down through A into the overlap and out through B's far end.
    t = np.linspace(0.0, 1.0, 40)[:, None]
    starts = np.array([[0.7, 1.2, 0.5], [1.6, 1.3, 0.4], [2.05, 1.2, 0.6]])
    ends = np.array([[2.6, 0.5, 0.5], [3.4, 0.45, 0.55], [2.2, 0.5, 0.5]])
    hair = torch.as_tensor(starts[:, None] + t[None] * (ends - starts)[:, None])[None]
    d = hair_body_signed_distance(hair, body)
    assert int((d < -0.05).sum()) > 30
    xi, dhat, bp = 1e-3, 1.5e-3, 0.01
    energy, _, _ = _energy_forward(hair, body, xi, dhat, bp, 1.0, barrier_variant_id("quadratic"), "vertex")
    expected = barrier(d[:, :, 2:], xi, dhat, bp).sum()
    np.testing.assert_allclose(float(energy.sum()), float(expected), rtol=1e-10)


def test_poses_share_the_cut_and_update_moves_the_pieces(rng):
    """Pose 0 overlaps, pose 1 has B moved clear of A: both signed as the winding number says;
    a piece inside in one pose only stays (the sign near it is the winding number's)."""
    v0, f = overlapping_boxes()
    v1, _ = overlapping_boxes(shift=1.5)
    ft = torch.as_tensor(f)
    body = BodyMesh(torch.as_tensor(np.stack([v0, v1])), ft)
    points = rng.uniform([-0.5, -0.3, -0.3], [5.0, 1.3, 1.3], size=(2000, 3))
    pt = torch.as_tensor(points)
    meshes = [m.id for m in body._winding_meshes]
    for poses in ((v0, v1), (v1, v0)):
        d = hair_body_signed_distance(torch.stack([pt, pt])[:, :, None].reshape(2, -1, 1, 3), body).reshape(2, -1)
        for b, vb in enumerate(poses):
            inside = winding_numbers(pt, torch.as_tensor(vb), ft) > 0.5
            off = d[b].abs() > 1e-6
            assert bool(((d[b] < 0) == inside)[off].all()), f"pose {b}"
        body.update(torch.as_tensor(np.stack(poses[::-1])))  # the uncut mesh's vertices
        # Refit in place: a CUDA graph captured before `update` keeps reading the same meshes.
        assert [m.id for m in body._winding_meshes] == meshes


def test_a_body_builds_at_its_first_query_once_and_a_crop_takes_its_winding_meshes(rng, monkeypatch):
    """A body builds its trees, winding meshes and pieces' sides at its first query, not before;
    a crop of a body not yet queried takes that body's winding meshes (the self-intersection
    search's) instead of building them again, and the body builds its own again if queried
    after; four threads querying a new body at once build it once. Every answer the same."""
    import threading

    import warp as wp

    v, f = overlapping_boxes()
    points = torch.as_tensor(rng.uniform([-0.5, -0.3, -0.3], [3.5, 1.3, 1.3], size=(500, 3)))[None, :, None]
    reference = hair_body_signed_distance(points, BodyMesh(torch.as_tensor(v), torch.as_tensor(f)))
    built = []

    class CountingMesh(wp.Mesh):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            built.append(self)

    monkeypatch.setattr(wp, "Mesh", CountingMesh)
    body = BodyMesh(torch.as_tensor(v), torch.as_tensor(f))
    assert len(built) == 1 and body._meshes is None  # the search's uncut mesh only
    crop = body.crop(torch.tensor([[1.5, 0.5, 0.5]]), torch.tensor([5.0]))
    assert len(built) == 1 and crop._winding_meshes is not None and body._winding_meshes is None
    assert torch.equal(hair_body_signed_distance(points, crop), reference)
    assert len(built) == 2  # the crop's tree; its winding meshes were handed over
    assert torch.equal(hair_body_signed_distance(points, body), reference)
    assert len(built) == 4  # the body's own tree and winding mesh, built when it was queried
    fresh = BodyMesh(torch.as_tensor(v), torch.as_tensor(f))
    del built[:]
    results = [None] * 4
    barrier = threading.Barrier(4)

    def query(k):
        barrier.wait()
        results[k] = hair_body_signed_distance(points, fresh)

    threads = [threading.Thread(target=query, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(built) == 1 and all(torch.equal(r, reference) for r in results)


def test_a_scenes_moving_body_moved_to_a_frame_signs_the_hair_as_that_frames_own_body(rng):
    """`Scene.moving_body`: one body built at the first frame, split over the motion's poses and
    moved by `update`, gives the hair near it the distances of the body built for the frame itself
    (`SceneFrames.body_mesh`, cropped), at the first frame and at the last; it is one mesh."""
    import hairwarp as hw

    scene = hw.default_scene("long_straight", "head_turn", duration=0.3, strand_stride=64, num_vertices=24)
    frames = scene.frames()
    moving = scene.moving_body()
    assert moving.batch_size == 1 and moving.num_vertices >= scene.body.num_vertices
    for t in (0, frames.num_frames - 1):
        moving.update(frames.posed.vertices[t:t + 1])
        own = frames.select([t]).body_mesh
        hair = frames.rigid.positions[t:t + 1]
        points = hair + torch.as_tensor(rng.normal(scale=0.01, size=tuple(hair.shape)), dtype=hair.dtype)
        expected = hair_body_signed_distance(points, own)
        got = hair_body_signed_distance(points, moving)
        near = expected.abs() < 0.05
        assert int(near.sum()) > 100 and bool((expected[near] < 0).any())  # the check sees the body, inside too
        torch.testing.assert_close(got[near], expected[near], rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="indices"):
        scene.moving_body([frames.num_frames + 5])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the one-ray-a-thread launches need a CUDA device")
def test_the_pieces_sides_on_cuda_are_the_cpus():
    """The pieces' sides (`seam_piece_crossings_kernel` and the rays after it): on a GPU one ray a
    thread and the third ray in a launch of its own, on the CPU a thread a sample; the same
    verdicts (which pieces the winding number signs) and the same corners' distances, on the
    default body moved through a motion's poses."""
    import hairwarp as hw

    scene = hw.default_scene("long_straight", "head_turn", duration=1.0, strand_stride=64, num_vertices=24)
    frames = scene.frames()
    bodies = {device: scene.moving_body(device=device) for device in ("cpu", "cuda")}
    assert bodies["cpu"].num_faces > bodies["cpu"]._first_piece  # the body has pieces to sign
    for t in (0, frames.num_frames // 2, frames.num_frames - 1):
        sides = {}
        for device, body in bodies.items():
            body.update(frames.posed.vertices[t:t + 1].to(device))
            body._query_ready()
            sides[device] = body._seam_sides.cpu()
        assert torch.equal(sides["cpu"][:, 3], sides["cuda"][:, 3])
        torch.testing.assert_close(sides["cuda"], sides["cpu"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("cut", [False, True])
def test_update_moves_what_queries_read_in_place(rng, cut):
    """After `update` every array a query reads (trees, vertices, pseudo-normals, winding
    meshes, pieces' sides) is where it was, as a CUDA graph captured before needs, and holds the
    moved body: distances equal those of a body built on the new vertices, in float32 and
    float64. Cut: the two-box poses swapped (the same cut either way); uncut: a capsule moved and
    stretched."""
    if cut:
        v0, f = overlapping_boxes()
        v1, _ = overlapping_boxes(shift=1.5)
        poses = torch.as_tensor(np.stack([v0, v1]))
        moved = poses.flip(0)
    else:
        v, f = capsule()
        poses = torch.as_tensor(v)
        moved = poses * torch.tensor([1.2, 0.9, 1.0], dtype=poses.dtype) + torch.tensor([0.1, 0.0, -0.05],
                                                                                          dtype=poses.dtype)
    ft = torch.as_tensor(f)
    body = BodyMesh(poses, ft)
    lo, hi = moved.reshape(-1, 3).amin(0) - 0.3, moved.reshape(-1, 3).amax(0) + 0.3
    points = lo + (hi - lo) * torch.as_tensor(rng.uniform(size=(len(poses) if cut else 1, 800, 1, 3)))

    def addresses():
        return [a.ptr if hasattr(a, "ptr") else a for dtype in (torch.float32, torch.float64)
                for a in body._kernel_arrays(dtype)]

    for dtype in (torch.float32, torch.float64):
        hair_body_signed_distance(points.to(dtype), body)
    before = addresses()
    body.update(moved)
    assert addresses() == before
    fresh = BodyMesh(moved, ft)
    for dtype, atol in ((torch.float32, 1e-6), (torch.float64, 1e-12)):
        d = hair_body_signed_distance(points.to(dtype), body)
        torch.testing.assert_close(d, hair_body_signed_distance(points.to(dtype), fresh), rtol=0, atol=atol)


# Hair vertices this close to the pieces [m] (the armpits) are checked against the winding number.
_ARMPIT_RADIUS = 0.06


@pytest.mark.slow
def test_default_body_armpits_are_signed_as_the_winding_number_says():
    """table1 (the default body, arms down): the rigid placement's vertices near the faces cut
    at the armpits, and random points around the crossing (2-60 mm away), are signed as the
    float64 winding number says, but within 2.5 pieces' size of the surface (the pieces follow
    the crossing to about their size). Before the faces touching a face inside were cut and the
    pieces' edges took their parent's pseudo-normals, 315 of 20 000 such points up to 44 mm
    deep were called outside."""
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.ops.hair_body_contact import SELF_INTERSECTION_PIECE_FRACTION

    frames = comparison_scene("table1").frames(device=torch.device("cpu"))
    v = frames.posed.vertices[0].double()
    f = frames.scene.body.faces.long()
    body = BodyMesh(v, f)
    plain = BodyMesh(v, f, split_self_intersections=False)
    cut = body.self_intersections
    assert cut["crossing_faces"] > 0 and 0 < cut["winding_pieces"] < cut["seam_pieces"] / 2
    pieces = body.faces[body.num_faces - cut["pieces"]:].long()
    centres = body.vertices[pieces].mean(dim=1)
    x = frames.rigid.positions[0].reshape(-1, 3).double()
    near = torch.zeros(len(x), dtype=torch.bool)
    for start in range(0, len(x), 4096):
        near[start:start + 4096] = torch.cdist(x[start:start + 4096], centres).amin(dim=1) < _ARMPIT_RADIUS
    generator = torch.Generator().manual_seed(0)
    seam = body.vertices[body.faces[body.num_faces - cut["seam_pieces"]:].long()].mean(dim=1)
    count = 2500
    scale = torch.tensor([0.002, 0.01, 0.03, 0.06], dtype=torch.float64)[torch.randint(4, (count,), generator=generator)]
    around = seam[torch.randint(len(seam), (count,), generator=generator)] + scale[:, None] * torch.randn(
        count, 3, generator=generator, dtype=torch.float64)
    for points, hair in ((x[near], True), (around, False)):
        inside = winding_numbers(points, v, f) > 0.5
        d = hair_body_signed_distance(points[None, :, None], body).reshape(-1)
        d_plain = hair_body_signed_distance(points[None, :, None], plain).reshape(-1)
        off = d.abs() > (1e-4 if hair else 2.5 * SELF_INTERSECTION_PIECE_FRACTION * float(
            torch.linalg.vector_norm(v.amax(0) - v.amin(0))))
        assert int((inside & off).sum()) > 100 and int((inside & (d_plain > 1e-3)).sum()) > 50  # the hard case
        assert bool(((d < 0) == inside)[off].all()), f"{int(((d < 0) != inside)[off].sum())} wrong signs"


@pytest.mark.slow
def test_scene_frames_cut_whole_motions():
    """`Scene.frames` cuts the body's self-intersections for a batch of any length (a whole
    motion: 40 frames of the head turn here): the long hair's rigid placement has vertices inside
    the chest that the uncut surface calls outside (its armpits' faces inside the other part);
    the cut body signs them as the float64 winding number says, but within 2.5 pieces' size of
    the surface. `split_self_intersections=False` keeps the uncut surface."""
    from hairwarp.ops.hair_body_contact import SELF_INTERSECTION_PIECE_FRACTION
    from hairwarp.scene.scene import default_scene

    scene = default_scene("long_straight", "head_turn", strand_stride=8, num_vertices=30)
    indices = torch.linspace(0, scene.num_frames - 1, 40).round().long()
    frames = scene.frames(indices)
    plain = scene.frames(indices, split_self_intersections=False)
    assert frames.body_mesh.self_intersections["crossing_faces"] > 0
    assert plain.body_mesh.self_intersections["pieces"] == 0
    x = frames.rigid.positions
    d = hair_body_signed_distance(x, frames.body_mesh).reshape(len(indices), -1)
    d_plain = hair_body_signed_distance(x, plain.body_mesh).reshape(len(indices), -1)
    disagree = (d < 0) != (d_plain < 0)
    assert int(disagree.sum()) > 50, int(disagree.sum())  # the uncut surface lies there
    f = scene.body.faces.long()
    wrong = 0
    for b in disagree.any(dim=1).nonzero().reshape(-1).tolist():
        v = frames.posed.vertices[b].double()
        points = x[b].reshape(-1, 3)[disagree[b]].double()
        inside = winding_numbers(points, v, f) > 0.5
        off = d[b, disagree[b]].abs() > 2.5 * SELF_INTERSECTION_PIECE_FRACTION * float(
            torch.linalg.vector_norm(v.amax(0) - v.amin(0)))
        assert bool((d_plain[b, disagree[b]] >= 0)[inside & off].all())  # the lie is "outside"
        wrong += int(((d[b, disagree[b]] < 0) != inside)[off].sum())
    assert wrong == 0, f"{wrong} wrong signs"


def test_triangles_within_reach_count_the_body_s_own_triangles():
    """A cut body queries pieces of its triangles: the count of triangles it covers is at most the
    mesh's own, where its face count is more (the scene line said "36637 of 6400")."""
    v, f = overlapping_boxes()
    body = BodyMesh(torch.as_tensor(v), torch.as_tensor(f))
    cut = body.self_intersections
    assert body.num_faces > len(f)  # 1 297 pieces and faces queried for 24 triangles
    # Every triangle but the ones left out inside the other box.
    assert body.source_triangle_count == len(f) - cut["inside_faces"]
    plain = BodyMesh(torch.as_tensor(v), torch.as_tensor(f), split_self_intersections=False)
    assert plain.source_triangle_count == plain.num_faces == len(f)
