"""Foreign grooms (tools/foreign_grooms.py) fitted to the scalp: the flat load path against a
per-strand reference, and the root part turned from the old scalp's normal to the new one.

The reference below is the load path as it was, one strand at a time (struct decoding, a
Python loop per strand for the transform, the length, the resampling, the snap and the turn,
and an ICP with brute-force nearest points); the library runs it on all strands at once.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import struct

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hairwarp.io.hair_data import load_hairstyle, read_hair_data, read_hair_data_flat
from hairwarp.io.usd import read_usd_curves
from hairwarp.scene.groom import (
    NORMAL_NEIGHBOURS,
    ROOT_TURN_FADE_END,
    ROOT_TURN_FULL,
    estimate_root_normals,
    fit_similarity_to_scalp,
    flat_strand_lengths,
    place_groom,
    resample_flat_strands,
    turn_strands_at_roots,
    umeyama,
)
from hairwarp.scene.hairstyles import resample_strands, sphere_cap_scalp
from references.hair_data import resample_polyline

_PATH = os.path.join(os.path.dirname(__file__), os.pardir, "tools", "foreign_grooms.py")
_spec = importlib.util.spec_from_file_location("foreign_grooms", _PATH)
fg = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fg)

# Output strands are float32 metres (~1e-7 relative of ~1.6 m coordinates); the reference runs
# in float64 with sums in another order.
_STRAND_TOL = 1e-6  # [m]
# Two ICPs with the same pairs and the same arithmetic, one with a k-d tree, one brute force.
_FIT_TOL = 1e-9
# Float64 arc-length resampling against the one-at-a-time reference.
_RESAMPLE_TOL = 1e-12


@pytest.fixture(scope="module")
def body_and_scalp():
    from hairwarp.builder import load_body

    body, scalp, _ = load_body("default")
    head = body.rest_vertices[body.head_vertex_indices].double().numpy()
    return body, scalp, head


# ------------------------------------------------------------------ per-strand reference


def _decode(path):
    """A `.data` file strand by strand with struct (as the reader did before)."""
    raw = open(path, "rb").read()
    (count,) = struct.unpack_from("<i", raw, 0)
    offset, strands = 4, []
    for _ in range(count):
        (n,) = struct.unpack_from("<i", raw, offset)
        offset += 4
        strands.append(np.array(struct.unpack_from(f"<{3 * n}f", raw, offset), dtype=np.float64).reshape(n, 3))
        offset += 12 * n
    return strands


def _nearest_brute(queries, points):
    return np.array([int(np.argmin(((points - q) ** 2).sum(1))) for q in queries])


def _reference_icp(roots, grid, head, iterations=100, tolerance=1e-6):
    """The two-stage ICP of `fit_similarity_to_scalp`, nearest points by brute force."""
    spread = np.sqrt(((grid - grid.mean(0)) ** 2).sum(1).mean())
    scale = spread / np.sqrt(((roots - roots.mean(0)) ** 2).sum(1).mean())
    rotation, translation = np.eye(3), grid.mean(0) - scale * roots.mean(0)
    moved = scale * roots + translation
    grid = grid[:: max(1, round(len(grid) / len(roots)))]
    weights = np.concatenate([np.full(len(roots), 0.5 / len(roots)), np.full(len(grid), 0.5 / len(grid))])
    for rotate in (False, True):
        for _ in range(iterations):
            forward = head[_nearest_brute(moved, head)]
            backward = _nearest_brute(grid, moved)
            scale, rotation, translation = umeyama(np.concatenate([roots, roots[backward]]),
                                                   np.concatenate([forward, grid]), weights, with_rotation=rotate)
            new = scale * roots @ rotation.T + translation
            step, moved = float(np.abs(new - moved).max()), new
            if step < tolerance:
                break
    return scale, rotation, translation


def _reference_normals(roots, k=NORMAL_NEIGHBOURS):
    """Per root: its k nearest roots, their PCA plane, a quadric height field over it by
    least squares (numpy's lstsq), the quadric's normal at the root, away from the centroid."""
    centroid = roots.mean(0)
    out = []
    for r in roots:
        patch = roots[np.argsort(((roots - r) ** 2).sum(1))[:k]]
        axes = np.linalg.eigh((patch - patch.mean(0)).T @ (patch - patch.mean(0)))[1]
        rel = patch - r
        x, y, h = rel @ axes[:, 2], rel @ axes[:, 1], rel @ axes[:, 0]
        coef = np.linalg.lstsq(np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], 1), h, rcond=None)[0]
        normal = axes[:, 0] - coef[3] * axes[:, 2] - coef[4] * axes[:, 1]
        normal /= np.linalg.norm(normal)
        out.append(normal if normal @ (r - centroid) >= 0 else -normal)
    return np.array(out)


def _reference_turn(strand, old, new):
    """One strand: segment j turned about old x new by the angle times its share (smoothstep)."""
    axis = np.cross(old, new)
    angle = np.arctan2(np.linalg.norm(axis), old @ new)
    axis = axis / np.linalg.norm(axis)
    n = len(strand)
    out = [strand[0]]
    for j in range(n - 1):
        u = (j + 0.5) / (n - 1)
        w = min(max((ROOT_TURN_FADE_END - u) / (ROOT_TURN_FADE_END - ROOT_TURN_FULL), 0.0), 1.0)
        turn = Rotation.from_rotvec(angle * w * w * (3 - 2 * w) * axis).as_matrix()
        out.append(out[-1] + turn @ (strand[j + 1] - strand[j]))
    return np.array(out)


def test_flat_load_matches_the_per_strand_reference(tmp_path, body_and_scalp):
    """A 300-strand foreign groom (z up, markers mixed in): every stage, one strand at a time."""
    _, scalp, head = body_and_scalp
    path = fg.write_data_groom(str(tmp_path / "g.data"), 300, seed=5, up="z")
    got = load_hairstyle(path, scalp, units="cm", up="z", align="similarity", head_points=head)

    strands = [s @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T * 0.01 for s in _decode(path)]
    assert sum(len(s) == 1 for s in strands) == 6  # the bald-root markers
    usable = [s for s in strands if len(s) >= 2]
    roots = np.array([s[0] for s in usable])
    grid, normals = scalp.positions.double().numpy(), scalp.normals.double().numpy()
    scale, rotation, translation = _reference_icp(roots, grid, head)
    fit = fit_similarity_to_scalp(roots, scalp, head)
    assert abs(fit.scale - scale) < _FIT_TOL and np.abs(fit.rotation - rotation).max() < _FIT_TOL
    assert np.abs(fit.translation - translation).max() < _FIT_TOL
    assert fit.iterations > 2  # the ICP ran

    moved = [scale * s @ rotation.T + translation for s in strands]
    lengths = [float(np.linalg.norm(np.diff(s, axis=0), axis=1).sum()) if len(s) > 1 else 0.0 for s in moved]
    keep = [i for i, L in enumerate(lengths) if L >= 0.02]
    assert got.filtered.tolist() == [i for i in range(len(strands)) if i not in keep]
    old_all = _reference_normals(scale * roots @ rotation.T + translation)
    old_of = dict(zip([i for i, s in enumerate(strands) if len(s) >= 2], old_all))
    expected, index = [], []
    for i in keep:
        res = resample_polyline(moved[i], 100)
        near = int(_nearest_brute(res[:1], grid)[0])
        res = res + (grid[near] - res[0])
        res[0] = grid[near]
        expected.append(_reference_turn(res, old_of[i], normals[near] / np.linalg.norm(normals[near])))
        index.append(near)
    assert got.root_index.tolist() == index
    np.testing.assert_allclose(got.strands.double().numpy(), np.array(expected), rtol=0, atol=_STRAND_TOL)
    assert got.info["root_rotation_deg_median"] > 2.0  # the turn did something to compare


def test_flat_pieces_match_per_strand_ones(rng):
    counts = np.array([5, 1, 0, 100, 37, 2, 1, 9])
    strands = [np.cumsum(rng.normal(size=(n, 3)), axis=0) for n in counts]
    points = np.concatenate([s for s in strands if len(s)])
    lengths = flat_strand_lengths(points, counts)
    expected = [float(np.linalg.norm(np.diff(s, axis=0), axis=1).sum()) if len(s) > 1 else 0.0 for s in strands]
    np.testing.assert_allclose(lengths, expected, rtol=1e-14, atol=0)
    assert lengths[[1, 2, 6]].tolist() == [0.0, 0.0, 0.0]
    long = np.nonzero(counts >= 2)[0]
    out = np.concatenate(list(resample_flat_strands(points, counts, 30, long, block=2)))
    for i, o in zip(long, out):
        np.testing.assert_allclose(o, resample_polyline(strands[i], 30), rtol=0, atol=_RESAMPLE_TOL)
        np.testing.assert_array_equal(o[[0, -1]], strands[i][[0, -1]])
    np.testing.assert_allclose(out, resample_strands([strands[i] for i in long], 30, dtype=torch.float64).numpy(),
                               rtol=0, atol=_RESAMPLE_TOL)


def test_flat_reader_matches_the_list_reader(tmp_path):
    path = fg.write_data_groom(str(tmp_path / "g.data"), 50, seed=1)
    points, counts = read_hair_data_flat(path)
    strands = read_hair_data(path)
    decoded = _decode(path)
    assert counts.tolist() == [len(s) for s in strands] == [len(s) for s in decoded]
    assert points.dtype == np.float32 and points.shape == (int(counts.sum()), 3)
    np.testing.assert_array_equal(np.concatenate(strands), points)
    np.testing.assert_array_equal(np.concatenate(decoded), points.astype(np.float64))


def test_icp_on_a_subset_lays_the_roots_as_the_fit_on_all(body_and_scalp):
    """Our scalp, sampled 9 times as densely as its grid, seen from another head's frame: the
    fit on 4096 of its 8836 roots lays them within 3 mm of the fit on all (1.5 mm measured; the
    fit itself is 2.7 mm from the truth: the head's vertices are its target)."""
    from hairwarp.scene.rotations import np_axis_angle_to_matrix

    _, scalp, head = body_and_scalp
    r = scalp.resolution
    grid = scalp.positions.double().numpy().reshape(r, r, 3)
    t = np.linspace(0.0, 1.0, 3 * (r - 1) + 1) * (r - 1)
    i = np.minimum(t.astype(int), r - 2)
    w = (t - i)[:, None, None]
    rows = grid[i] * (1 - w) + grid[i + 1] * w
    dense = (rows[:, i] * (1 - w[:, :, 0])[None, :, :] + rows[:, i + 1] * w[:, :, 0][None, :, :]).reshape(-1, 3)
    rot = np_axis_angle_to_matrix(np.array([0.1, 1.0, 0.2]) / np.linalg.norm([0.1, 1.0, 0.2]) * np.radians(5.0))
    foreign = (dense - np.array([0.02, 1.1, -0.04])) @ rot / 1.07
    full = fit_similarity_to_scalp(foreign, scalp, head, sample_size=len(foreign))
    subset = fit_similarity_to_scalp(foreign, scalp, head)
    assert len(foreign) == 8836 and full.iterations > 2 and subset.iterations > 2
    assert np.abs(full.apply(foreign) - dense).max() < 4e-3  # [m]
    assert np.abs(subset.apply(foreign) - full.apply(foreign)).max() < 3e-3
    again = fit_similarity_to_scalp(foreign, scalp, head)
    np.testing.assert_array_equal(again.rotation, subset.rotation)  # seeded


# ------------------------------------------------------------------ the turn at the roots


def _strands_on_normals(rng, roots, normals, n=40, length=0.3):
    """Strands whose first segments leave along `normals`, then droop (down, toward -z)."""
    m = len(roots)
    out = np.empty((m, n, 3))
    out[:, 0] = roots
    step = length / (n - 1)
    for j in range(1, n):
        a = np.exp(-((j - 1) / 4.0) ** 2)
        d = a * normals + (1 - a) * np.array([0.0, -1.0, -0.3])
        out[:, j] = out[:, j - 1] + step * d / np.linalg.norm(d, axis=1, keepdims=True)
    return out


def test_turn_takes_the_first_segment_to_the_new_normal_and_keeps_the_rest(rng):
    m, n = 64, 50
    old = rng.normal(size=(m, 3))
    old /= np.linalg.norm(old, axis=1, keepdims=True)
    new = old + 0.4 * rng.normal(size=(m, 3))
    new /= np.linalg.norm(new, axis=1, keepdims=True)
    new[0], new[1] = -old[0], old[1]  # opposite, and equal
    strands = _strands_on_normals(rng, rng.normal(size=(m, 3)), old, n=n)
    out = turn_strands_at_roots(strands, old, new)
    first = out[:, 1] - out[:, 0]
    np.testing.assert_allclose(first / np.linalg.norm(first, axis=1, keepdims=True), new, atol=1e-12)
    np.testing.assert_array_equal(out[:, 0], strands[:, 0])
    seg_in, seg_out = np.diff(strands, axis=1), np.diff(out, axis=1)
    np.testing.assert_allclose(np.linalg.norm(seg_out, axis=2), np.linalg.norm(seg_in, axis=2), rtol=1e-12)
    beyond = (np.arange(n - 1) + 0.5) / (n - 1) >= ROOT_TURN_FADE_END
    np.testing.assert_allclose(seg_out[:, beyond], seg_in[:, beyond], atol=1e-12)  # the hanging part keeps its direction
    np.testing.assert_allclose(out[1], strands[1], atol=1e-15)  # no turn where the normals agree


def test_a_strand_leaving_the_old_scalp_along_its_normal_leaves_the_new_one_along_its_normal(rng):
    """A groom grown along the normals of an ellipsoid cap (20 % wider, 15 % flatter than the
    sphere cap it is fitted to): after the similarity fit and the snap its first segments make
    12 degrees (median) with the new normals; after the turn, 0.3 (the old normals are
    estimated from the roots)."""
    scalp = sphere_cap_scalp(resolution=24, radius=0.1, centre=(0.0, 1.6, 0.0))
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    sphere = np.array([0.0, 1.6, 0.0]) + 0.1 * u
    radii = np.array([0.12, 0.085, 0.1])
    v = rng.normal(size=(3000, 3))
    v = v[v[:, 1] > 0.35 * np.linalg.norm(v, axis=1)][:500]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    roots = v * radii + np.array([0.3, 0.2, -0.1])  # another head, elsewhere
    normals = v / radii
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    strands = list(_strands_on_normals(rng, roots, normals))
    angles = {}
    for orient in (False, True):
        style, fit = place_groom(strands, scalp, sphere, fit="similarity", num_vertices=40, orient_roots=orient)
        x = style.strands.double()
        first = x[:, 1] - x[:, 0]
        cos = (first / first.norm(dim=1, keepdim=True) * style.root_normals.double()).sum(1)
        angles[orient] = np.degrees(np.arccos(cos.clamp(-1, 1).numpy()))
    assert fit.iterations > 2
    assert np.median(angles[False]) > 4.0  # the shapes differ: without the turn the angle stays (12)
    assert np.median(angles[True]) < 1.0 and np.percentile(angles[True], 90) < 1.5  # (0.3, 0.5)


def test_old_normals_are_estimated_from_the_roots(rng):
    g = fg.make_groom(2000, seed=3, bald_fraction=0.0)
    roots = g.points[g.offsets]
    est = estimate_root_normals(roots)
    err = np.degrees(np.arccos(np.clip((est * g.root_normals).sum(1), -1, 1)))
    assert np.median(err) < 1.5 and np.percentile(err, 99) < 10.0  # outward, not flipped
    with pytest.raises(ValueError, match="roots"):
        estimate_root_normals(roots[:2])


def _root_region(scene) -> dict:
    """Inside-the-body counts of a scene's rigid placement at frame 0 (root vertex left out)."""
    from hairwarp.ops import hair_body_signed_distance

    frames = scene.frames([0])
    inside = (hair_body_signed_distance(frames.rigid.positions, frames.body_mesh)[0] < 0)[:, 1:]
    tenth = inside.shape[1] + 1
    return {"inside_percent": float(inside.double().mean() * 100),
            "first_tenth_inside": int(inside[:, : tenth // 10].sum()),
            "strands_inside_percent": float(inside.any(dim=1).double().mean() * 100)}


def root_region_before_after(path: str) -> dict:
    """`_root_region` of a `.data` groom built by `build_scene` (after: the turn at the roots)
    and the same without the turn (before)."""
    from hairwarp.builder import build_scene

    scene = build_scene(hairstyle=path, pose="rest")
    head = scene.body.rest_vertices[scene.body.head_vertex_indices].double().numpy()
    before = load_hairstyle(path, scene.scalp, units="cm", align="auto", head_points=head, orient_roots=False)
    return {"before": _root_region(dataclasses.replace(scene, hairstyle=before)), "after": _root_region(scene),
            "info": scene.hairstyle.info}


def test_a_foreign_groom_enters_the_head_less_near_its_roots(tmp_path):
    """400 strands grown on a head 15 % wider and 10 % flatter than ours (the tool's default):
    the vertices inside the body in the first tenth of the strands, without and with the turn."""
    path = fg.write_data_groom(str(tmp_path / "g400.data"), 400, seed=0)
    result = root_region_before_after(path)
    before, after = result["before"], result["after"]
    assert "ICP" in result["info"]["fit"]
    assert before["first_tenth_inside"] >= 20  # the fault is there to fix (37 measured)
    assert after["first_tenth_inside"] <= before["first_tenth_inside"] / 3  # (9 measured)
    assert after["inside_percent"] < before["inside_percent"]  # and no more inside elsewhere


# ------------------------------------------------------------------ the tool's files


def test_tool_files_are_deterministic_and_agree(tmp_path):
    a = fg.write_data_groom(str(tmp_path / "a.data"), 200, seed=7)
    b = fg.write_data_groom(str(tmp_path / "b.data"), 200, seed=7)
    assert open(a, "rb").read() == open(b, "rb").read()
    points, counts = read_hair_data_flat(a)
    hair = counts >= 2
    assert len(counts) == 204 and (counts[~hair] == 1).all() and (~hair[:5]).sum() < 5
    assert 40 <= counts[hair].min() and counts[hair].max() <= 80 and len(set(counts[hair].tolist())) > 10
    lengths = flat_strand_lengths(points.astype(np.float64), counts)[hair]
    assert 20.0 < np.percentile(lengths, 5) and np.percentile(lengths, 95) < 46.0  # centimetres
    for up in ("y", "z"):
        usd = read_usd_curves(fg.write_usd_groom(str(tmp_path / f"g_{up}.usda"), 200, seed=7, up=up))
        assert usd["up_axis"] == up.upper() and usd["meters_per_unit"] == 0.01
        # The same hair (the markers left out), in metres, y up: float32 cm less the Xform's offset.
        expected = points[np.repeat(hair, counts)].astype(np.float64) * 0.01
        np.testing.assert_allclose(np.concatenate(usd["strands"]), expected, rtol=0, atol=1e-6)


def test_tool_cli(tmp_path, capsys):
    assert fg.main(["--out", str(tmp_path), "--strands", "30", "--seed", "1"]) == 0
    assert "groom_30.data" in capsys.readouterr().out
    assert len(read_hair_data(tmp_path / "groom_30.data")) == 31
    with pytest.raises(SystemExit):
        fg.main(["--out", str(tmp_path), "--strands", "0"])
