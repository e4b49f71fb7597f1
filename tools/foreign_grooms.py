"""Grooms of any size "made outside the project": grown on another head, written with numpy/struct/pxr.

Question it answers: does a large groom from another tool load fast, and do its strands leave
our scalp as they left theirs (issue 32, item 4)? `benchmarks/bm_groom_load.py` and
`tests/test_groom_fit.py` use these files; nothing here imports hairwarp.

The head is an ellipsoid that is not ours (default semi-axes 8.6 x 8.9 x 9.0 cm: 15 % wider
and 10 % flatter front to back than the default body's fitted head, 7.5 x 8.9 x 10.0 cm),
its centre at (3, 158, -2) cm in its own world, facing +z, y up (or z up: (x, y, z) ->
(x, -z, y)), in centimetres. Roots cover a scalp-like cap of it (down to the nape at the back,
above the ears at the sides, a hairline above the forehead), drawn uniformly over the cap's
area. Each strand leaves the head along its normal (its first segment exactly), then bends
within a centimetre or so into a droop (down and a little outward), lying a millimetre or two
over the head where the droop would enter it (a radial push-out). Strands are 30-45 cm long
(the push-out shortens a few), with 40-80 vertices each; a part of them is wavy or curly (a
helix or a sideways wave about the centreline, faded in from the root so the first segments
stay on the normal). The `.data` file also holds 1-vertex bald-root markers mixed in among the
strands, as USC-HairSalon files do; the USD file holds one linear BasisCurves under an Xform
that carries the head's offset.

    python tools/foreign_grooms.py --out /tmp/grooms --strands 100000                 # groom_100000.data
    python tools/foreign_grooms.py --out /tmp/grooms --strands 10000 --format usdc --up z

Deterministic by --seed; 100 000 strands take a few seconds (all numpy, no loop per strand).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

# The default body's head, fitted by an axis-aligned ellipsoid to its scalp [cm] (x, y, z).
OUR_HEAD_RADII_CM = (7.48, 8.93, 9.95)
# "Another head": 15 % wider, 10 % flatter front to back, as tall; elsewhere in its world.
HEAD_RADII_CM = (8.6, 8.93, 8.96)
HEAD_CENTRE_CM = (3.0, 158.0, -2.0)
# The cap that carries hair, in elevation [deg] above the head's equator: its lowest edge as a
# function of the azimuth a (0 = front): front 39, sides 8, nape -48 (the default body's scalp).
_EDGE_COEFFS = (8.0, 43.5, -12.5)  # edge(a) = c0 + c1 cos a + c2 cos^2 a
# Arc length [cm] over which a strand turns from the normal into its droop (short: the hair
# lies on the head soon after its root, as combed hair does).
TURN_LENGTH_CM = (0.5, 1.5)
# How far outward (per unit down) the droop leans, so strands fall beside the head.
_DROOP_LEAN = (0.25, 0.55)
# Clearance [cm] kept from the head by the push-out: base + slope * arc length (a few
# millimetres over the scalp, a centimetre or so at the shoulders).
CLEARANCE_CM = (0.1, 0.01)
# Curls and waves fade in over this arc length [cm], after this much straight hair [cm].
_CURL_FADE_CM = (1.5, 6.0)


@dataclass
class ForeignGroom:
    """A groom on the foreign head, flat: strand i is points[offsets[i]:offsets[i] + counts[i]].

    Attributes:
        points: (V, 3) float64 vertices [cm], y up, the file's world.
        counts: (S,) int64 vertex count per strand (1 for a bald-root marker).
        root_normals: (S, 3) the head's outward unit normal at each strand's root.
        head_centre: (3,) [cm]; head_radii: (3,) semi-axes [cm].
    """

    points: np.ndarray
    counts: np.ndarray
    root_normals: np.ndarray
    head_centre: np.ndarray
    head_radii: np.ndarray

    @property
    def offsets(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(np.int64)

    def strands(self) -> list[np.ndarray]:
        return np.split(self.points, np.cumsum(self.counts)[:-1])


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _sample_roots(rng: np.random.Generator, count: int, centre: np.ndarray, radii: np.ndarray):
    """(count, 3) roots on the cap of the ellipsoid, uniform in area, and their unit normals."""
    c0, c1, c2 = _EDGE_COEFFS
    chosen = []
    total = 0
    while total < count:
        u = _normalize(rng.normal(size=(4 * count + 64, 3)))
        p = u * radii
        n = _normalize(p / radii**2)
        # Uniform directions mapped to the ellipsoid are denser where it is flat: accept with the
        # area ratio (|grad| * prod(radii) / max) so the roots are uniform over the surface.
        area = np.linalg.norm(p / radii**2, axis=1) * np.prod(radii)
        accept = rng.uniform(size=len(u)) * area.max() < area
        azimuth = np.arctan2(u[:, 0], u[:, 2])
        elevation = np.degrees(np.arcsin(np.clip(u[:, 1], -1, 1)))
        edge = c0 + c1 * np.cos(azimuth) + c2 * np.cos(azimuth) ** 2
        keep = accept & (elevation > edge)
        chosen.append((p[keep], n[keep]))
        total += int(keep.sum())
    p = np.concatenate([c[0] for c in chosen])[:count]
    n = np.concatenate([c[1] for c in chosen])[:count]
    return p + centre, n


def make_groom(num_strands: int, seed: int = 0, *, head_radii_cm=HEAD_RADII_CM, head_centre_cm=HEAD_CENTRE_CM,
               length_cm=(30.0, 45.0), vertex_range=(40, 80), curl_fraction: float = 0.3,
               bald_fraction: float = 0.02) -> ForeignGroom:
    """A groom of `num_strands` hair strands (plus bald-root markers) on the foreign head.

    Args:
        num_strands: hair strands (>= 1); `bald_fraction` of that many 1-vertex markers are added.
        seed: the generator's seed (the same seed, the same groom).
        head_radii_cm: (3,) the head ellipsoid's semi-axes [cm] along x, y (up), z (front).
        head_centre_cm: (3,) its centre [cm].
        length_cm: (lo, hi) strand arc lengths [cm], uniform.
        vertex_range: (lo, hi) vertices per strand, uniform integers, both included.
        curl_fraction: share of strands with waves or curls (half each).
        bald_fraction: 1-vertex markers per hair strand, mixed in at random places of the
            strand order (as USC-HairSalon files have them).

    Returns:
        A `ForeignGroom` in centimetres, y up.
    """
    if int(num_strands) < 1:
        raise ValueError(f"num_strands: expected an int >= 1, got {num_strands}")
    rng = np.random.default_rng(seed)
    s_count = int(num_strands)
    centre = np.asarray(head_centre_cm, dtype=np.float64)
    radii = np.asarray(head_radii_cm, dtype=np.float64)
    roots, normals = _sample_roots(rng, s_count, centre, radii)
    counts = rng.integers(vertex_range[0], vertex_range[1] + 1, size=s_count)
    lengths = rng.uniform(length_cm[0], length_cm[1], size=s_count)
    turn = rng.uniform(*TURN_LENGTH_CM, size=s_count)
    lean = rng.uniform(*_DROOP_LEAN, size=s_count)
    # Droop: down, leaning outward from the head's vertical axis (horizontal direction of the root).
    outward = roots - centre
    outward[:, 1] = 0.0
    flat = np.linalg.norm(outward, axis=1) < 1e-6
    outward[flat] = [0.0, 0.0, -1.0]  # a root exactly on the crown leans back
    outward = _normalize(outward)
    droop = _normalize(np.array([0.0, -1.0, 0.0]) + lean[:, None] * outward + 0.05 * rng.normal(size=(s_count, 3)))

    # Waves (sideways) and curls (a helix about the centreline) add arc length: the centreline is
    # shortened by their length factor so each strand's own arc length stays `lengths`.
    kind = rng.uniform(size=s_count)
    curly = kind < curl_fraction / 2
    wavy = (kind >= curl_fraction / 2) & (kind < curl_fraction)
    amplitude = np.where(curly, rng.uniform(0.6, 1.2, s_count), rng.uniform(0.8, 2.0, s_count))
    period = np.where(curly, rng.uniform(3.0, 5.0, s_count), rng.uniform(6.0, 10.0, s_count))
    phase = rng.uniform(0, 2 * np.pi, s_count)
    slope = 2 * np.pi * amplitude / period
    cosine = np.cos(np.linspace(0, np.pi, 33))
    stretch = np.where(curly, np.sqrt(1 + slope**2),
                       np.where(wavy, np.sqrt(1 + (slope[:, None] * cosine) ** 2).mean(1), 1.0))
    centreline = lengths / stretch

    # Flat per-vertex arrays: strand index, arc length s of each vertex along the centreline.
    total = int(counts.sum())
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    strand = np.repeat(np.arange(s_count), counts)
    j = np.arange(total) - offsets[strand]
    step = centreline / (counts - 1)
    s = j * step[strand]
    # Each segment points along the direction at its midpoint, which depends on s alone: the
    # normal for the first segment, then a turn into the droop with weight exp(-(s'/turn)^2)
    # (s' the arc length past the first segment's midpoint).
    mid = np.maximum(s - 1.5 * step[strand], 0.0) / turn[strand]
    a = np.exp(-mid * mid)[:, None]
    direction = _normalize(a * normals[strand] + (1 - a) * droop[strand])
    seg = direction * step[strand][:, None]
    seg[offsets] = 0.0  # the root is the strand's start
    cum = np.cumsum(seg, axis=0)
    points = cum - np.repeat(cum[offsets] - roots, counts, axis=0)

    rows = np.nonzero(np.repeat(curly | wavy, counts))[0]
    if rows.size:
        st, d, sr = strand[rows], direction[rows], s[rows]
        side = _normalize(np.cross(np.array([0.0, 1.0, 0.0]), outward))
        e1 = _normalize(np.cross(d, side[st]))
        e2 = np.cross(d, e1)
        fade = np.clip((sr - _CURL_FADE_CM[0]) / _CURL_FADE_CM[1], 0.0, 1.0)
        amp = amplitude[st] * fade * fade * (3 - 2 * fade)
        angle = 2 * np.pi * sr / period[st] + phase[st]
        across = np.where(curly[st], np.cos(angle) * amp, 0.0)
        points[rows] += across[:, None] * e1 + (np.sin(angle) * amp)[:, None] * e2

    # Push out of the head (radially in the ellipsoid's unit coordinates), never the root.
    q = (points - centre) / radii
    rho = np.sqrt(np.einsum("ij,ij->i", q, q))
    floor = 1.0 + (CLEARANCE_CM[0] + CLEARANCE_CM[1] * s) / radii.mean()
    inside = np.nonzero((rho < floor) & (j > 0))[0]
    points[inside] = centre + q[inside] * ((floor[inside] / np.maximum(rho[inside], 1e-12))[:, None] * radii)

    # Bald-root markers (1 vertex) mixed in at random places of the strand order.
    bald = int(round(bald_fraction * s_count))
    if bald:
        marker_roots, marker_normals = _sample_roots(rng, bald, centre, radii)
        slots = np.sort(rng.choice(s_count + bald, size=bald, replace=False))
        before = slots - np.arange(bald)  # hair strands that come before each marker
        rows_at = np.append(offsets, total)[before]
        points = np.insert(points, rows_at, marker_roots, axis=0)
        counts = np.insert(counts, before, 1)
        normals = np.insert(normals, before, marker_normals, axis=0)
    return ForeignGroom(points=points, counts=counts.astype(np.int64), root_normals=normals,
                        head_centre=centre, head_radii=radii)


def to_file_axes(points_cm: np.ndarray, up: str = "y") -> np.ndarray:
    """Centimetres, y up -> the file's axes (z up: (x, y, z) -> (x, -z, y))."""
    if up == "y":
        return points_cm
    if up == "z":
        return np.stack([points_cm[:, 0], -points_cm[:, 2], points_cm[:, 1]], axis=1)
    raise ValueError(f"up: expected 'y' or 'z', got {up!r}")


def encode_data(points: np.ndarray, counts: np.ndarray) -> bytes:
    """USC-HairSalon `.data` bytes: int32 S, then per strand int32 n and n x 3 float32 (little-endian)."""
    counts = np.asarray(counts, dtype=np.int64)
    # One int32 word per header, 3 float32 words per vertex: interleave them in one array.
    words = np.empty(1 + len(counts) + 3 * int(counts.sum()), dtype="<u4")
    words[0] = len(counts)
    headers = 1 + np.arange(len(counts)) + 3 * np.concatenate([[0], np.cumsum(counts)[:-1]])
    words[headers] = counts.astype("<u4")
    is_coord = np.ones(len(words), dtype=bool)
    is_coord[0] = False
    is_coord[headers] = False
    words[is_coord] = np.ascontiguousarray(points, dtype="<f4").reshape(-1).view("<u4")
    return words.tobytes()


def write_data_groom(path: str, num_strands: int, seed: int = 0, *, up: str = "y", **kwargs) -> str:
    """Write a `.data` groom (centimetres, y or z up) of `num_strands` strands; returns the path.

    Keyword arguments go to `make_groom`.
    """
    groom = make_groom(num_strands, seed, **kwargs)
    data = encode_data(to_file_axes(groom.points, up), groom.counts)
    with open(path, "wb") as f:
        f.write(data)
    return path


def write_usd_groom(path: str, num_strands: int, seed: int = 0, *, up: str = "y", **kwargs) -> str:
    """Write a USD groom: /Groom (an Xform holding the head's offset) / Hair (linear BasisCurves).

    The stage is in centimetres (metersPerUnit 0.01) with its upAxis `up`; bald-root markers
    are left out (a curve needs two vertices). Keyword arguments go to `make_groom`.
    """
    from pxr import Gf, Usd, UsdGeom, Vt

    kwargs.setdefault("bald_fraction", 0.0)
    groom = make_groom(num_strands, seed, **kwargs)
    hair = groom.counts >= 2
    keep_rows = np.repeat(hair, groom.counts)
    offset = to_file_axes(groom.head_centre[None], up)[0]
    local = to_file_axes(groom.points[keep_rows], up) - offset
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    xform = UsdGeom.Xform.Define(stage, "/Groom")
    xform.AddTranslateOp().Set(Gf.Vec3d(*[float(v) for v in offset]))
    stage.SetDefaultPrim(xform.GetPrim())
    curves = UsdGeom.BasisCurves.Define(stage, "/Groom/Hair")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(groom.counts[hair].astype(np.int32)))
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local.astype(np.float32)))
    curves.CreateWidthsAttr(Vt.FloatArray([0.008]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    if not stage.GetRootLayer().Export(os.fspath(path)):
        raise OSError(f"path: USD could not write {path!r}")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--strands", type=int, default=10000, help="hair strands (default: 10000)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: 0)")
    p.add_argument("--format", choices=("data", "usdc", "usda"), default="data", help="file format (default: data)")
    p.add_argument("--up", choices=("y", "z"), default="y", help="the file's up axis (default: y)")
    p.add_argument("--curl-fraction", type=float, default=0.3, help="share of wavy or curly strands (default: 0.3)")
    args = p.parse_args(argv)
    if args.strands < 1:
        p.error(f"--strands: expected a positive count, got {args.strands}")
    os.makedirs(args.out, exist_ok=True)
    suffix = "" if args.up == "y" else "_zup"
    path = os.path.join(args.out, f"groom_{args.strands}{suffix}.{args.format}")
    t0 = time.perf_counter()
    if args.format == "data":
        write_data_groom(path, args.strands, args.seed, up=args.up, curl_fraction=args.curl_fraction)
    else:
        write_usd_groom(path, args.strands, args.seed, up=args.up, curl_fraction=args.curl_fraction)
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.1f} MB, {time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
