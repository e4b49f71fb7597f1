"""Procedural hairstyles: roots, arc-length sampling, head clearance, presets, determinism."""

import math

import numpy as np
import pytest
import torch

from hairwarp.scene.hairstyles import (
    CURL_TYPES, HairstyleParams, Hairstyle, fit_head_ellipsoid, generate_hairstyle, hairstyle_preset,
    list_hairstyle_presets, resample_polylines, sample_hairstyle_params, sphere_cap_scalp,
)
from hairwarp.scene.scalp import Scalp
from references.hair_data import resample_polyline

# Segments of a resampled strand are chords of equal arcs of the fine centreline: equal to
# float32 rounding for straight hair, within a small fraction for curls.
_SEGMENT_REL_TOL = 1e-2
# Clearance over the head proxy: strands may not dip inside it (float32 positions).
_INSIDE_TOL = 1e-5  # [m]
# Least-squares ellipsoid fit on exact points.
_FIT_TOL = 1e-6  # [m]


@pytest.fixture(scope="module")
def scalp():
    return sphere_cap_scalp(resolution=16)


@pytest.fixture(scope="module")
def presets(scalp):
    return {name: generate_hairstyle(scalp, name) for name in list_hairstyle_presets()}


def _arc_lengths(s):
    return (s[:, 1:] - s[:, :-1]).norm(dim=-1).sum(dim=1)


def test_sphere_cap_scalp():
    sc = sphere_cap_scalp(resolution=32)
    assert sc.num_roots == 1024 and sc.resolution == 32
    r = (sc.positions.double() - torch.tensor([0.0, 1.6, 0.0], dtype=torch.float64)).norm(dim=1)
    torch.testing.assert_close(r, torch.full_like(r, 0.1), rtol=0, atol=1e-6)
    torch.testing.assert_close(sc.normals.norm(dim=1), torch.ones(1024), rtol=0, atol=1e-6)
    uv = sc.uv.reshape(32, 32, 2)
    assert float(uv[0, 1, 0] - uv[0, 0, 0]) > 0 and float(uv[1, 0, 1] - uv[0, 0, 1]) > 0
    # v runs front (+z) to back; u toward +x; the nape reaches lower than the forehead.
    pos = sc.positions.reshape(32, 32, 3)
    assert float(pos[0, 16, 2]) > 0.05 and float(pos[-1, 16, 2]) < -0.05
    assert float(pos[16, -1, 0]) > 0.05
    assert float(pos[-1, 16, 1]) < float(pos[0, 16, 1]) - 0.03


def test_fit_head_ellipsoid_recovers_an_ellipsoid():
    centre, radii = np.array([0.01, 1.55, -0.02]), np.array([0.075, 0.11, 0.095])
    sc = sphere_cap_scalp(resolution=12, radius=1.0, centre=(0.0, 0.0, 0.0))
    p = centre + sc.positions.double().numpy() * radii
    n = sc.positions.double().numpy() / radii
    n = n / np.linalg.norm(n, axis=1)[:, None]
    ell = Scalp(uv=sc.uv, positions=torch.tensor(p), normals=torch.tensor(n))
    head = fit_head_ellipsoid(ell)
    np.testing.assert_allclose(head.centre, centre, atol=_FIT_TOL)
    np.testing.assert_allclose(head.radii, radii, atol=_FIT_TOL)
    np.testing.assert_allclose(head.radial_distance(p), 0.0, atol=_FIT_TOL)


def test_fit_head_ellipsoid_falls_back_to_a_sphere():
    # A nearly flat patch: the axis-aligned quadric fit is ill-posed; a sphere is still found.
    sc = sphere_cap_scalp(resolution=6, radius=0.1, cap_angle_deg=8.0, tilt_back_deg=0.0)
    head = fit_head_ellipsoid(sc)
    assert np.all(np.isfinite(head.radii)) and np.all(head.radii > 0)
    np.testing.assert_allclose(head.radial_distance(sc.positions.double().numpy()), 0.0, atol=1e-4)


def test_resample_polylines_matches_reference(rng):
    pts = np.cumsum(rng.normal(size=(4, 9, 3)), axis=1)
    out = resample_polylines(pts, 25)
    for p, o in zip(pts, out):
        np.testing.assert_allclose(o, resample_polyline(p, 25), atol=1e-12)


def test_presets_basic_invariants(scalp, presets):
    assert len(presets) >= 6
    roots = scalp.positions
    for name, h in presets.items():
        assert isinstance(h, Hairstyle) and h.name == name
        m = h.num_strands
        assert m == scalp.num_roots - len(h.filtered) and m > 200, name
        assert h.strands.shape == (m, 100, 3) and h.strands.dtype == torch.float32
        assert torch.isfinite(h.strands).all()
        # Vertex 0 is the scalp root, bit for bit.
        assert torch.equal(h.strands[:, 0], roots[h.root_index])
        assert torch.equal(h.root_uv, scalp.uv[h.root_index])
        assert torch.equal(h.root_normals, scalp.normals[h.root_index])
        seg = (h.strands[:, 1:] - h.strands[:, :-1]).norm(dim=-1)
        assert float((seg.std(dim=1) / seg.mean(dim=1)).max()) < _SEGMENT_REL_TOL, name
        # No strand bends back sharply: successive segments turn less than 90 degrees.
        e = h.strands[:, 1:] - h.strands[:, :-1]
        cos = (e[:, 1:] * e[:, :-1]).sum(-1) / (e[:, 1:].norm(dim=-1) * e[:, :-1].norm(dim=-1))
        assert float(cos.min()) > 0.0, name


def test_presets_stay_outside_the_head_proxy(scalp, presets):
    head = fit_head_ellipsoid(scalp)
    for name, h in presets.items():
        d = head.radial_distance(h.strands.double().numpy())
        assert d[:, 1:].min() > -_INSIDE_TOL, name
        # Away from the root (beyond 1 cm of arc) the hair keeps the minimum clearance.
        s = np.cumsum(np.r_[0, np.ones(99)])[None, :] * (_arc_lengths(h.strands).numpy() / 99)[:, None]
        assert d[s > 0.01].min() > 0.003 - _INSIDE_TOL, name


def test_lengths_and_gravity(scalp):
    head = fit_head_ellipsoid(scalp)
    tips = {}
    for length in (0.1, 0.3, 0.6):
        h = generate_hairstyle(scalp, HairstyleParams(length=length, length_jitter=0.0, seed=1))
        # Straight hair: the strand is its centreline, so its arc length is the length.
        torch.testing.assert_close(_arc_lengths(h.strands), torch.full((h.num_strands,), length),
                                   rtol=2e-3, atol=0)
        tips[length] = h.strands[:, -1, 1].double().numpy()
    # Longer hair hangs lower; long hair falls well below the head.
    assert np.median(tips[0.3]) < np.median(tips[0.1]) < head.centre[1] + head.radii[1]
    assert np.median(tips[0.6]) < head.centre[1] - head.radii[1] - 0.1


def test_parting_splits_left_and_right(scalp):
    for parting in (0.0, 0.4):
        h = generate_hairstyle(scalp, HairstyleParams(length=0.3, parting=parting, seed=2))
        head = fit_head_ellipsoid(scalp)
        rel = h.strands[:, 0].double().numpy() - head.centre
        top = rel[:, 1] > 0.6 * head.radii[1]  # roots on the crown
        part_x = parting * head.radii[0]
        left = top & (rel[:, 0] < part_x - 0.01)
        right = top & (rel[:, 0] > part_x + 0.01)
        assert left.sum() > 5 and right.sum() > 5
        tip_x = h.strands[:, -1, 0].double().numpy() - head.centre[0]
        assert (tip_x[left] < 0).mean() > 0.95 and (tip_x[right] > 0).mean() > 0.95


def test_bangs_fall_over_the_forehead(scalp, presets):
    h = presets["bangs"]
    head = fit_head_ellipsoid(scalp)
    nb = h.info["num_bangs"]
    assert nb > 10
    bang = _arc_lengths(h.strands) < 0.2  # bangs are the short strands of this preset
    assert int(bang.sum()) == nb
    s = h.strands[bang].double().numpy()
    # Tips in front of the face and below the roots, within the face's width.
    assert (s[:, -1, 2] > head.centre[2] + 0.8 * head.radii[2]).all()
    assert (s[:, -1, 1] < s[:, 0, 1] - 0.03).all()
    assert (np.abs(s[:, -1, 0] - head.centre[0]) < head.radii[0]).all()
    # Without bangs no strand ends in front of the forehead.
    plain = presets["long_straight"].strands.double().numpy()
    front = (plain[:, -1, 2] > head.centre[2] + 0.8 * head.radii[2]) & (np.abs(plain[:, -1, 0]) < 0.05)
    assert front.sum() == 0


def test_bob_is_cut_blunt(scalp, presets):
    h = presets["bob"]
    head = fit_head_ellipsoid(scalp)
    cut = head.centre[1] - hairstyle_preset("bob").cut_below
    assert float(h.strands[..., 1].min()) > cut - 0.01
    # Most strands reach the cut line.
    assert (h.strands[:, -1, 1].double().numpy() < cut + 0.01).mean() > 0.5


def test_curls_add_arc_length(scalp, presets):
    for name, longer in (("long_curly", 1.2), ("medium_wavy", 1.04)):
        h = presets[name]
        p = hairstyle_preset(name)
        ratio = float(_arc_lengths(h.strands).median()) / p.length
        # A curl of amplitude A at f turns/m lengthens the hair by about sqrt(1 + (2 pi f A)^2),
        # a wave by about 1 + (2 pi f A)^2 / 4.
        assert ratio > longer, name
        # The curl stays within its amplitude of a smooth centreline: vertices 0 and 1 fixed
        # near the root normal (the ramp), so the first segment leaves the scalp outward.
        first = h.strands[:, 1] - h.strands[:, 0]
        assert float(((first * h.root_normals).sum(-1)).min()) > 0


def test_filtering_reports_short_strands(scalp):
    p = HairstyleParams(length=0.05, length_jitter=0.4, min_length=0.05, seed=4)
    h = generate_hairstyle(scalp, p)
    assert 0 < len(h.filtered) < scalp.num_roots
    assert sorted(h.filtered.tolist() + h.root_index.tolist()) == list(range(scalp.num_roots))
    assert float(_arc_lengths(h.strands).min()) >= 0.05 * (1 - 1e-3)


def test_deterministic_per_seed(scalp):
    p = sample_hairstyle_params(np.random.default_rng(3))
    a, b = generate_hairstyle(scalp, p), generate_hairstyle(scalp, p)
    assert torch.equal(a.strands, b.strands)
    c = generate_hairstyle(scalp, p.replace(seed=p.seed + 1))
    assert not torch.equal(a.strands, c.strands)


def test_sample_params_cover_the_family(scalp):
    rng = np.random.default_rng(11)
    ps = [sample_hairstyle_params(rng) for _ in range(200)]
    for p in ps:
        p.validate()
    lengths = np.array([p.length for p in ps])
    assert lengths.min() < 0.08 and lengths.max() > 0.45
    assert {p.curl for p in ps} == set(CURL_TYPES)
    assert any(p.bangs for p in ps) and any(p.parting is None for p in ps)
    assert any(p.cut_below is not None for p in ps)
    for p in ps[:3]:
        h = generate_hairstyle(scalp, p)
        assert torch.isfinite(h.strands).all() and h.num_strands > 0


def test_num_vertices(scalp):
    h = generate_hairstyle(scalp, HairstyleParams(length=0.2), num_vertices=17)
    assert h.strands.shape[1] == 17


@pytest.mark.parametrize("field, value", [
    ("length", 0.0), ("curl", "frizzy"), ("curl_amplitude", -0.01), ("parting", 1.5),
    ("droop", 2.0), ("volume", -1.0), ("cut_below", float("nan")), ("seed", 1.5),
])
def test_bad_params_raise(scalp, field, value):
    with pytest.raises(ValueError, match=field):
        generate_hairstyle(scalp, HairstyleParams(**{field: value}))


def test_bad_scalp_and_args_raise(scalp):
    with pytest.raises(ValueError, match="scalp"):
        generate_hairstyle("head", "bob")
    bad = Scalp(uv=scalp.uv, positions=scalp.positions.clone(), normals=scalp.normals)
    bad.positions[3, 1] = float("nan")
    with pytest.raises(ValueError, match="scalp.positions"):
        generate_hairstyle(bad, "bob")
    with pytest.raises(ValueError, match="name"):
        generate_hairstyle(scalp, "mohawk")
    with pytest.raises(ValueError, match="num_vertices"):
        generate_hairstyle(scalp, "bob", num_vertices=2)
    assert math.isfinite(hairstyle_preset("bob", seed=3).length)


def test_body_keeps_long_hair_out_of_the_torso():
    """With a body surface given, strands drape over it instead of through it."""
    import trimesh

    sc = sphere_cap_scalp(resolution=10)
    centre, half = np.array([0.0, 1.27, -0.02]), np.array([0.2, 0.18, 0.12])  # shoulders at 1.45 m
    box = trimesh.creation.box(extents=2 * half)
    box.apply_translation(centre)
    body = (torch.tensor(box.vertices, dtype=torch.float32), torch.tensor(box.faces, dtype=torch.int32))

    def inside(h):
        p = h.strands.double().numpy()
        return int((np.abs(p - centre) < half).all(axis=-1).sum())

    p = HairstyleParams(length=0.55, parting=0.0, seed=7)
    free = generate_hairstyle(sc, p)
    draped = generate_hairstyle(sc, p, body=body)
    assert inside(free) > 100  # hanging straight down, the hair goes through the torso
    assert inside(draped) == 0
    assert torch.equal(draped.strands[:, 0], free.strands[:, 0])
    seg = (draped.strands[:, 1:] - draped.strands[:, :-1]).norm(dim=-1)
    assert float((seg.std(dim=1) / seg.mean(dim=1)).max()) < _SEGMENT_REL_TOL
    with pytest.raises(ValueError, match="body"):
        generate_hairstyle(sc, p, body="torso")
