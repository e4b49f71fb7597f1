"""`.data` strand files: exact round trip, a malformed-file battery, resampling, loading."""

import struct

import numpy as np
import pytest
import torch

from hairwarp.io.hair_data import load_hairstyle, read_hair_data, write_hair_data
from hairwarp.scene.hairstyles import resample_strands
from hairwarp.scene.hairstyles import HairstyleParams, generate_hairstyle, sphere_cap_scalp
from references.hair_data import encode_hair_data, resample_polyline

# float32 storage of centimetre coordinates converted to metres: ~1e-7 relative of ~160 cm.
_POSITION_TOL = 2e-6  # [m]
# Re-resampling a generated strand by arc length moves its vertices a little: the generator's
# vertices are equally spaced along its fine centreline, so their chords are not exactly equal.
_RERESAMPLE_TOL = 5e-5  # [m]
# Arc-length resampling in float64 against the one-at-a-time reference.
_RESAMPLE_TOL = 1e-12


@pytest.fixture(scope="module")
def scalp():
    return sphere_cap_scalp(resolution=12)


def _strands(rng):
    counts = [5, 1, 0, 100, 37, 2]
    return [rng.normal(size=(n, 3)).astype(np.float32) for n in counts]


def test_round_trip_bytes_identical(tmp_path, rng):
    strands = _strands(rng)
    path = tmp_path / "a.data"
    write_hair_data(path, strands)
    original = path.read_bytes()
    assert original == encode_hair_data(strands)  # the format, written independently
    back = read_hair_data(path)
    assert len(back) == len(strands) == 6
    for a, b in zip(back, strands):
        assert a.dtype == np.float32 and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    write_hair_data(tmp_path / "b.data", back)
    assert (tmp_path / "b.data").read_bytes() == original


def test_round_trip_of_foreign_bytes(tmp_path, rng):
    """A file written by someone else (including odd float bit patterns) survives unchanged."""
    raw = encode_hair_data([rng.normal(size=(7, 3)), np.array([[1e-40, -0.0, 3.4e38]])])
    (tmp_path / "x.data").write_bytes(raw)
    write_hair_data(tmp_path / "y.data", read_hair_data(tmp_path / "x.data"))
    assert (tmp_path / "y.data").read_bytes() == raw


def test_write_accepts_tensor_batch(tmp_path):
    s = torch.arange(2 * 4 * 3, dtype=torch.float32).reshape(2, 4, 3)
    write_hair_data(tmp_path / "t.data", s)
    back = read_hair_data(tmp_path / "t.data")
    assert len(back) == 2
    np.testing.assert_array_equal(np.stack(back), s.numpy())


def test_zero_strands(tmp_path):
    write_hair_data(tmp_path / "z.data", [])
    assert (tmp_path / "z.data").read_bytes() == struct.pack("<i", 0)
    assert read_hair_data(tmp_path / "z.data") == []


def _i(*v):
    return struct.pack(f"<{len(v)}i", *v)


def _f(*v):
    return struct.pack(f"<{len(v)}f", *v)


MALFORMED = {
    "empty": (b"", "empty"),
    "short_header": (b"\x01\x00", "truncated"),
    "negative_count": (_i(-3), "negative strand count"),
    "absurd_count": (_i(10**9) + _i(1) + _f(0, 0, 0), "absurd"),
    "missing_vertex_count": (_i(2) + _i(1) + _f(0, 0, 0), "truncated"),
    "negative_vertex_count": (_i(1) + _i(-1), "negative vertex count"),
    "truncated_coordinates": (_i(1) + _i(3) + _f(0, 0, 0, 1, 1), "truncated"),
    "absurd_vertex_count": (_i(1) + _i(2**30) + _f(0, 0, 0), "truncated"),
    "nan_coordinate": (_i(1) + _i(2) + _f(0, 0, 0, 1, float("nan"), 1), "NaN"),
    "inf_coordinate": (_i(1) + _i(1) + _f(float("inf"), 0, 0), "NaN or Inf"),
    "trailing_bytes": (_i(1) + _i(1) + _f(0, 0, 0) + b"\x00\x01", "trailing"),
    # The first fault in file order is the one named, whatever its kind.
    "nan_in_a_later_strand": (_i(3) + _i(1) + _f(0, 0, 0) + _i(2) + _f(0, 0, 0, 1, float("inf"), 1) + _i(0),
                              "strand 1 vertex 1 has a NaN or Inf"),
    "nan_before_truncation": (_i(2) + _i(1) + _f(float("nan"), 0, 0) + _i(5) + _f(0, 0, 0), "strand 0 vertex 0"),
    "truncation_before_nan": (_i(2) + _i(1) + _f(0, 0, 0) + _i(2) + _f(float("nan"), 0, 0), "truncated: strand 1"),
    "nan_before_trailing": (_i(1) + _i(1) + _f(0, float("nan"), 0) + b"\x00", "strand 0 vertex 0 has a NaN"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_raise(tmp_path, case):
    raw, reason = MALFORMED[case]
    path = tmp_path / f"{case}.data"
    path.write_bytes(raw)
    with pytest.raises(ValueError) as info:
        read_hair_data(path)
    message = str(info.value)
    assert str(path) in message and reason in message


def test_missing_file_raises(tmp_path):
    with pytest.raises(ValueError, match="nope.data"):
        read_hair_data(tmp_path / "nope.data")


@pytest.mark.parametrize("bad, match", [
    ([np.zeros((3, 2))], r"strands\[0\]"),
    ([np.zeros((2, 3)), np.array([[0.0, np.nan, 0.0]])], r"strands\[1\].*NaN"),
    ("abc", "strands"),
])
def test_write_rejects_bad_strands(tmp_path, bad, match):
    with pytest.raises(ValueError, match=match):
        write_hair_data(tmp_path / "w.data", bad)


def test_resample_matches_reference(rng):
    strands = [np.cumsum(rng.normal(size=(n, 3)), axis=0) for n in (2, 5, 5, 17, 130)]
    out = resample_strands(strands, n=100, dtype=torch.float64)
    assert out.shape == (5, 100, 3) and out.dtype == torch.float64
    for s, o in zip(strands, out.numpy()):
        np.testing.assert_allclose(o, resample_polyline(s, 100), rtol=0, atol=_RESAMPLE_TOL)
        np.testing.assert_array_equal(o[0], s[0])
        np.testing.assert_array_equal(o[-1], s[-1])


def test_resample_even_spacing_on_a_line():
    line = np.array([[0.0, 0, 0], [0.1, 0, 0], [1.0, 0, 0]])  # uneven input segments
    out = resample_strands([line], n=11, dtype=torch.float64)[0].numpy()
    np.testing.assert_allclose(out[:, 0], np.linspace(0, 1, 11), atol=_RESAMPLE_TOL)
    assert out.shape == (11, 3)


def test_resample_rejects_degenerate():
    with pytest.raises(ValueError, match=r"strands\[1\].*2 vertices"):
        resample_strands([np.zeros((3, 3)) + np.arange(3)[:, None], np.zeros((1, 3))])
    with pytest.raises(ValueError, match=r"strands\[0\].*zero length"):
        resample_strands([np.zeros((4, 3))])
    with pytest.raises(ValueError, match="n:"):
        resample_strands([np.eye(3)], n=1)


def _perm_file(tmp_path, style, name="perm.data", extra=(), up="y"):
    """The style written as PERM writes: centimetres (and optionally z up)."""
    strands = [s * 100.0 for s in style.strands.double().numpy()] + [np.asarray(e) for e in extra]
    if up == "z":  # y-up -> z-up: (x, y, z) -> (x, -z, y)
        strands = [np.stack([s[:, 0], -s[:, 2], s[:, 1]], axis=1) for s in strands]
    path = tmp_path / name
    write_hair_data(path, [s.astype(np.float32) for s in strands])
    return path


@pytest.mark.parametrize("up", ["y", "z"])
def test_load_perm_style_file(tmp_path, scalp, up):
    style = generate_hairstyle(scalp, HairstyleParams(length=0.2, seed=3))
    # One strand too short to keep (1 cm) and one bald-root marker (a single vertex).
    root = style.strands[0, 0].double().numpy() * 100
    extra = [np.stack([root, root + [0, -1.0, 0]]), root[None]]
    path = _perm_file(tmp_path, style, extra=extra, up=up)
    loaded = load_hairstyle(path, scalp, units="cm", up=up)
    m = style.num_strands
    assert m == scalp.num_roots == 144
    assert loaded.strands.shape == (m, 100, 3) and loaded.strands.dtype == torch.float32
    assert loaded.filtered.tolist() == [m, m + 1]
    assert loaded.info["num_file_strands"] == m + 2
    torch.testing.assert_close(loaded.root_index, style.root_index)
    torch.testing.assert_close(loaded.root_uv, style.root_uv)
    assert loaded.info["root_distance_max"] < _POSITION_TOL
    torch.testing.assert_close(loaded.strands, style.strands, rtol=0, atol=_RERESAMPLE_TOL)
    seg = (loaded.strands[:, 1:] - loaded.strands[:, :-1]).norm(dim=-1)
    assert float((seg.std(dim=1) / seg.mean(dim=1)).max()) < 1e-4  # equal arc-length steps
    # Snapped roots sit exactly on the scalp.
    torch.testing.assert_close(loaded.strands[:, 0], scalp.positions[loaded.root_index], rtol=0, atol=0)


def test_load_reports_root_distances_and_aligns(tmp_path, scalp):
    style = generate_hairstyle(scalp, HairstyleParams(length=0.1, seed=1))
    shifted = style.strands + torch.tensor([0.0, 0.5, 0.0])  # a head half a metre higher
    path = tmp_path / "m.data"
    write_hair_data(path, shifted)
    far = load_hairstyle(path, scalp, units="m", snap_roots=False)
    assert far.info["root_distance_mean"] > 0.3
    near = load_hairstyle(path, scalp, units="m", align="roots")
    np.testing.assert_allclose(near.info["translation"], [0.0, -0.5, 0.0], atol=1e-6)
    assert near.info["root_distance_max"] < 1e-5
    torch.testing.assert_close(near.root_index, style.root_index)


def test_load_rejects_wrong_units(tmp_path, scalp):
    style = generate_hairstyle(scalp, HairstyleParams(length=0.1, seed=1))
    path = _perm_file(tmp_path, style)
    with pytest.raises(ValueError, match="perm.data.*no strand"):
        load_hairstyle(path, scalp, units="mm")  # centimetre file read as millimetres: 1 cm hair
    with pytest.raises(ValueError, match="units"):
        load_hairstyle(path, scalp, units="inch")
    with pytest.raises(ValueError, match="up"):
        load_hairstyle(path, scalp, up="x")
    with pytest.raises(ValueError, match="scalp"):
        load_hairstyle(path, "not a scalp")
