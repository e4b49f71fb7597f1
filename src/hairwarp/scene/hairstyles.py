"""Procedural hairstyles on the scalp grid: the hair generator G_hair of Section 3.1.

The paper samples PERM's StyleGAN; we grow strands procedurally instead, so the library needs
no third-party weights. Each strand starts at its scalp root, leaves along the scalp normal,
bends toward a combing direction (away from the parting, backward or, for bangs, forward over
the forehead), slides over a head proxy (an ellipsoid fitted to the scalp roots) and falls
under gravity once past the widest part of the head. Curls are added around that centreline,
and the result is resampled to N vertices of equal arc length (N = 100 in the paper). Strands
shorter than a threshold are filtered, as Section 3.1 filters overly short strands.

Everything is deterministic per `HairstyleParams.seed`; the geometry is built in numpy float64
and returned as float32 torch tensors (rest pose, world frame, metres, y up, face toward +z).
Below the head only gravity acts unless a body surface is passed (`generate_hairstyle(...,
body=...)`): then long hair drapes over the shoulders and back instead of through them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from hairwarp._validate import check_positive, check_tensor
from hairwarp.scene.scalp import Scalp

CURL_TYPES = ("straight", "wavy", "curly")

# Sub-steps of the centreline growth per strand, before the arc-length resampling: enough
# that a 0.6 m strand turns in ~4 mm steps, few enough that 1024 strands take ~30 ms.
_GROWTH_STEPS = 160
# Smallest clearance [m] that a strand keeps over the head proxy away from its root, so the
# rest pose does not start inside the contact barrier's hard band (xi = 1 mm, Section 3.4.4).
_MIN_CLEARANCE = 0.003
# Arc length [m] over which the curl amplitude ramps up from zero, so vertices 0 and 1 (which
# the paper keeps fixed) stay on the scalp normal.
_CURL_RAMP = 0.04
# Width [m] of the smooth push out of the head proxy applied to curls.
_SOFT_WIDTH = 0.002
# Correlation length [m] of the per-strand jitter over the scalp.
_JITTER_CORRELATION = 0.03


@dataclass
class HairstyleParams:
    """Parameters of one procedural hairstyle.

    Attributes:
        length: strand centreline length [m], from 0.05 (short) to 0.6 (past the shoulders).
            Curls add arc length on top of it.
        curl: "straight", "wavy" (planar wave) or "curly" (helix).
        curl_amplitude: wave amplitude or helix radius [m].
        curl_frequency: waves or turns per metre of centreline [1/m].
        parting: lateral position of the parting as a fraction of the head's half width in
            [-1, 1] (0 = centre parting, + toward +x); None combs everything backward.
        bangs: whether the front strands fall forward over the forehead.
        bangs_length: centreline length of the bangs [m].
        volume: clearance of the hair over the head proxy [m] (more = fuller hair).
        droop: 0 (stiff, strands keep the scalp normal) to 1 (strands bend over at once).
        length_jitter: standard deviation of log(per-strand length) (0 = all equal); the
            jitter is spatially smooth over the scalp (clumps) plus a little per-strand noise.
        cut_below: if set, strands are cut where they pass this distance [m] below the head
            proxy's centre (a blunt cut: "bob").
        min_length: strands shorter than this [m] are filtered (Section 3.1).
        seed: random seed; the same parameters and seed give the same strands.
    """

    length: float = 0.25
    curl: str = "straight"
    curl_amplitude: float = 0.0
    curl_frequency: float = 0.0
    parting: float | None = 0.0
    bangs: bool = False
    bangs_length: float = 0.1
    volume: float = 0.01
    droop: float = 0.6
    length_jitter: float = 0.05
    cut_below: float | None = None
    min_length: float = 0.02
    seed: int = 0

    def validate(self) -> HairstyleParams:
        """Check every field; raise ValueError naming the first bad one. Returns self."""
        check_positive("length", self.length)
        if self.curl not in CURL_TYPES:
            raise ValueError(f"curl: expected one of {CURL_TYPES}, got {self.curl!r}")
        check_positive("curl_amplitude", self.curl_amplitude, allow_zero=True)
        check_positive("curl_frequency", self.curl_frequency, allow_zero=True)
        if self.parting is not None:
            p = float(self.parting)
            if not -1.0 <= p <= 1.0:
                raise ValueError(f"parting: expected None or a value in [-1, 1], got {self.parting}")
        check_positive("bangs_length", self.bangs_length)
        check_positive("volume", self.volume, allow_zero=True)
        d = float(self.droop)
        if not 0.0 <= d <= 1.0:
            raise ValueError(f"droop: expected a value in [0, 1], got {self.droop}")
        check_positive("length_jitter", self.length_jitter, allow_zero=True)
        if self.cut_below is not None:
            check_positive("cut_below", self.cut_below)
        check_positive("min_length", self.min_length, allow_zero=True)
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool):
            raise ValueError(f"seed: expected an int, got {type(self.seed).__name__}")
        return self

    def replace(self, **changes) -> HairstyleParams:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


_PRESETS: dict[str, HairstyleParams] = {
    "short_straight": HairstyleParams(
        length=0.06, droop=0.7, volume=0.004, parting=None, length_jitter=0.08
    ),
    "medium_wavy": HairstyleParams(
        length=0.3, curl="wavy", curl_amplitude=0.012, curl_frequency=7.0, parting=0.0, volume=0.01
    ),
    "long_straight": HairstyleParams(length=0.55, parting=0.35, droop=0.8, volume=0.008),
    "long_curly": HairstyleParams(
        length=0.5, curl="curly", curl_amplitude=0.015, curl_frequency=12.0, parting=0.0,
        volume=0.02, droop=0.7,
    ),
    "bob": HairstyleParams(length=0.35, cut_below=0.09, parting=-0.3, volume=0.012, droop=0.7,
                           length_jitter=0.02),
    "bangs": HairstyleParams(length=0.35, bangs=True, bangs_length=0.12, parting=None, volume=0.01),
}


def list_hairstyle_presets() -> list[str]:
    """Names of the preset hairstyles."""
    return sorted(_PRESETS)


def hairstyle_preset(name: str, seed: int = 0) -> HairstyleParams:
    """The parameters of a named preset (see `list_hairstyle_presets`), with `seed` set."""
    if name not in _PRESETS:
        raise ValueError(f"name: expected one of {list_hairstyle_presets()}, got {name!r}")
    return _PRESETS[name].replace(seed=int(seed))


def sample_hairstyle_params(rng: np.random.Generator) -> HairstyleParams:
    """Draw parameters from a broad family (short to long, straight to curly, partings, bangs).

    Args:
        rng: numpy random generator; the draw and the style's seed both come from it.
    """
    length = float(np.exp(rng.uniform(np.log(0.05), np.log(0.6))))
    curl = str(rng.choice(CURL_TYPES, p=[0.5, 0.25, 0.25]))
    if curl == "straight":
        amplitude, frequency = 0.0, 0.0
    elif curl == "wavy":
        amplitude, frequency = float(rng.uniform(0.004, 0.02)), float(rng.uniform(3.0, 10.0))
    else:
        amplitude, frequency = float(rng.uniform(0.005, 0.02)), float(rng.uniform(8.0, 20.0))
    parting = None if rng.uniform() < 0.3 else float(rng.uniform(-0.6, 0.6))
    bangs = bool(rng.uniform() < 0.25)
    cut_below = float(rng.uniform(0.05, 0.2)) if rng.uniform() < 0.2 else None
    return HairstyleParams(
        length=length,
        curl=curl,
        curl_amplitude=amplitude,
        curl_frequency=frequency,
        parting=parting,
        bangs=bangs,
        bangs_length=float(rng.uniform(0.06, 0.15)),
        volume=float(rng.uniform(0.003, 0.03)),
        droop=float(rng.uniform(0.3, 1.0)),
        length_jitter=float(rng.uniform(0.0, 0.15)),
        cut_below=cut_below,
        seed=int(rng.integers(0, 2**31 - 1)),
    )


@dataclass
class HeadEllipsoid:
    """Axis-aligned ellipsoid head proxy (y up, face +z).

    Attributes:
        centre: (3,) centre [m].
        radii: (3,) semi-axes along x, y, z [m].
    """

    centre: np.ndarray
    radii: np.ndarray

    def radial_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of `points` (..., 3) to the surface along the ray from the centre.

        Exact for a sphere; for an ellipsoid it slightly over-estimates the Euclidean distance
        (never flips its sign), which is what a clearance test needs.
        """
        d = points - self.centre
        r = np.linalg.norm(d, axis=-1)
        rho = np.linalg.norm(d / self.radii, axis=-1)
        return r - r / np.maximum(rho, 1e-12)

    def push_out(self, points: np.ndarray, clearance: np.ndarray) -> np.ndarray:
        """Move points closer than `clearance` [m] out along the ray from the centre."""
        d = points - self.centre
        r = np.linalg.norm(d, axis=-1, keepdims=True)
        rho = np.linalg.norm(d / self.radii, axis=-1, keepdims=True)
        surface = r / np.maximum(rho, 1e-12)
        target = surface + clearance[..., None]
        scale = np.where(r < target, target / np.maximum(r, 1e-12), 1.0)
        return self.centre + d * scale

    def soft_push_out(self, points: np.ndarray, clearance: np.ndarray, width) -> np.ndarray:
        """Like `push_out`, but smooth: the radial distance d becomes c + w softplus((d - c) / w).

        Points well outside barely move, points at or inside the clearance end up about
        w log 2 outside it, and the map has no corner, so it cannot fold a strand.
        """
        d = points - self.centre
        r = np.linalg.norm(d, axis=-1, keepdims=True)
        rho = np.linalg.norm(d / self.radii, axis=-1, keepdims=True)
        surface = r / np.maximum(rho, 1e-12)
        gap = r - surface - clearance[..., None]
        width = np.asarray(width)[..., None] if np.ndim(width) else width
        new_gap = width * np.logaddexp(0.0, gap / width)
        return self.centre + d * ((surface + clearance[..., None] + new_gap) / np.maximum(r, 1e-12))

    def normal(self, points: np.ndarray) -> np.ndarray:
        """Outward unit normal of the level set through `points` (..., 3)."""
        g = (points - self.centre) / self.radii**2
        return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)


def fit_head_ellipsoid(scalp: Scalp) -> HeadEllipsoid:
    """Fit the head proxy to the scalp root positions.

    An axis-aligned ellipsoid `a x^2 + b y^2 + c z^2 + d x + e y + f z = 1` by linear least
    squares; if the roots cover too little of the head for that to be well posed (a coefficient
    comes out non-positive or a semi-axis absurd), a sphere fit is used instead.

    Args:
        scalp: the scalp (positions (M, 3) [m], M >= 6).

    Returns:
        The fitted `HeadEllipsoid`.
    """
    p = scalp_arrays(scalp)[0]
    if p.shape[0] < 6:
        raise ValueError(f"scalp: need at least 6 roots to fit a head proxy, got {p.shape[0]}")
    mean = p.mean(axis=0)
    scale = float(np.abs(p - mean).max()) or 1.0
    q = (p - mean) / scale  # conditioning: the fit is done in a unit box
    A = np.concatenate([q**2, q], axis=1)
    coef, *_ = np.linalg.lstsq(A, np.ones(len(q)), rcond=None)
    quad, lin = coef[:3], coef[3:]
    ellipsoid = None
    if np.all(quad > 1e-9):
        c = -lin / (2 * quad)
        k = 1.0 + float(np.sum(lin**2 / (4 * quad)))
        if k > 0:
            radii = np.sqrt(k / quad)
            if np.all(radii < 4.0) and radii.max() / radii.min() < 3.0:
                ellipsoid = HeadEllipsoid(centre=mean + c * scale, radii=radii * scale)
    if ellipsoid is None:
        # Sphere: |q|^2 = 2 c.q + k, linear in (c, k).
        A = np.concatenate([2 * q, np.ones((len(q), 1))], axis=1)
        sol, *_ = np.linalg.lstsq(A, np.sum(q**2, axis=1), rcond=None)
        c, k = sol[:3], sol[3]
        radius = math.sqrt(max(k + float(c @ c), 1e-12))
        ellipsoid = HeadEllipsoid(centre=mean + c * scale, radii=np.full(3, radius * scale))
    return ellipsoid


@dataclass(eq=False)
class Hairstyle:
    """A set of rest-pose strands attached to the scalp.

    Attributes:
        strands: (M, N, 3) float32 vertex positions [m], rest pose, world frame; vertex 0 is
            the root.
        root_uv: (M, 2) float32 root UV coordinates on the scalp grid.
        root_normals: (M, 3) float32 outward unit scalp normals at the roots.
        root_index: (M,) int64 index of each strand's scalp root.
        filtered: (K,) int64 indices of the source strands that were dropped as too short
            (scalp roots for generated styles, file strands for loaded ones).
        name: a label (preset name or file name).
        info: extra facts (e.g. root-distance statistics of a loaded file).
    """

    strands: torch.Tensor
    root_uv: torch.Tensor
    root_normals: torch.Tensor
    root_index: torch.Tensor
    filtered: torch.Tensor
    name: str = ""
    info: dict = field(default_factory=dict)

    @property
    def num_strands(self) -> int:
        return int(self.strands.shape[0])

    def subset(self, keep: torch.Tensor | None = None, num_vertices: int | None = None) -> Hairstyle:
        """The strands `keep` (indices; None: all), resampled by arc length to `num_vertices`.

        Args:
            keep: (K,) int64 strand indices, or None for every strand.
            num_vertices: vertices per strand of the result (None: unchanged), >= 3.

        Returns:
            A new Hairstyle (same name, filtered and info).
        """
        strands = self.strands if keep is None else self.strands[keep]
        if num_vertices is not None and num_vertices != strands.shape[1]:
            strands = torch.as_tensor(resample_polylines(strands.double().numpy(), num_vertices), dtype=torch.float32)
        pick = (lambda t: t) if keep is None else (lambda t: t[keep])
        return Hairstyle(strands=strands.contiguous(), root_uv=pick(self.root_uv),
                         root_normals=pick(self.root_normals), root_index=pick(self.root_index),
                         filtered=self.filtered, name=self.name, info=dict(self.info))


def sphere_cap_scalp(
    resolution: int = 32,
    radius: float = 0.1,
    centre: tuple[float, float, float] = (0.0, 1.6, 0.0),
    cap_angle_deg: float = 80.0,
    tilt_back_deg: float = 20.0,
) -> Scalp:
    """A synthetic scalp: a `resolution` x `resolution` grid over a spherical cap.

    Stands in for the body's scalp in tests and tools. The cap's axis is +y tilted backward
    (toward -z) by `tilt_back_deg`, so it reaches lower at the nape than at the forehead, like
    a real hairline. Grid cell (i, j) is root `i * resolution + j` with uv = ((j + 0.5) / res,
    (i + 0.5) / res): u grows toward +x, v from the front (+z) to the back (-z).

    Args:
        resolution: roots per side.
        radius: sphere radius [m].
        centre: sphere centre [m].
        cap_angle_deg: angular radius of the cap [deg].
        tilt_back_deg: backward tilt of the cap axis [deg].

    Returns:
        A `Scalp` with float32 uv (R*R, 2), positions (R*R, 3) and normals (R*R, 3).
    """
    if int(resolution) < 2:
        raise ValueError(f"resolution: expected an int >= 2, got {resolution}")
    check_positive("radius", radius)
    res = int(resolution)
    g = (np.arange(res) + 0.5) / res
    u, v = np.meshgrid(g, g)  # v varies along rows (i), u along columns (j)
    a, b = 2 * u - 1, 2 * v - 1
    # Square -> disc (elliptical grid mapping), so the cap edge is round and cells stay even.
    dx = a * np.sqrt(1 - b**2 / 2)
    dz = -b * np.sqrt(1 - a**2 / 2)
    rho = np.sqrt(dx**2 + dz**2)
    theta = np.radians(cap_angle_deg) * rho
    phi = np.arctan2(dz, dx)
    n = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], axis=-1)
    t = np.radians(tilt_back_deg)
    # Rotation about x by -t: takes +y toward -z (backward).
    rot = np.array([[1, 0, 0], [0, np.cos(t), np.sin(t)], [0, -np.sin(t), np.cos(t)]])
    n = (n.reshape(-1, 3) @ rot.T)
    pos = np.asarray(centre, dtype=np.float64) + radius * n
    uv = np.stack([u.reshape(-1), v.reshape(-1)], axis=-1)
    return Scalp(
        uv=torch.tensor(uv, dtype=torch.float32),
        positions=torch.tensor(pos, dtype=torch.float32),
        normals=torch.tensor(n, dtype=torch.float32),
        resolution=res,
    )


def scalp_arrays(scalp: Scalp) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions, unit normals, uv) of a checked scalp as float64 numpy arrays."""
    if not isinstance(scalp, Scalp):
        raise ValueError(f"scalp: expected a hairwarp.scene.scalp.Scalp, got {type(scalp).__name__}")
    check_tensor("scalp.positions", scalp.positions, shape=(None, 3), allow_empty=False)
    m = scalp.positions.shape[0]
    check_tensor("scalp.normals", scalp.normals, shape=(m, 3))
    check_tensor("scalp.uv", scalp.uv, shape=(m, 2))
    p = scalp.positions.detach().cpu().double().numpy()
    n = scalp.normals.detach().cpu().double().numpy()
    norm = np.linalg.norm(n, axis=1)
    if np.any(norm < 1e-6):
        raise ValueError("scalp.normals: contains a zero normal")
    return p, n / norm[:, None], scalp.uv.detach().cpu().double().numpy()


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def as_strand_list(arg: str, strands) -> list[np.ndarray]:
    """Strands as a list of (n_i, 3) numpy arrays, checked (shape, numeric, finite), errors naming `arg`."""
    if isinstance(strands, (torch.Tensor, np.ndarray)):
        if strands.ndim != 3 or strands.shape[-1] != 3:
            raise ValueError(
                f"{arg}: expected (S, N, 3) or a list of (n_i, 3), got shape {tuple(strands.shape)}"
            )
        strands = list(strands)
    if not isinstance(strands, (list, tuple)):
        raise ValueError(f"{arg}: expected a list of (n_i, 3) arrays, got {type(strands).__name__}")
    out = []
    for i, s in enumerate(strands):
        if isinstance(s, torch.Tensor):
            s = s.detach().cpu().numpy()
        a = np.asarray(s)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{arg}[{i}]: expected shape (n, 3), got {a.shape}")
        if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{arg}[{i}]: expected a numeric array, got dtype {a.dtype}")
        if not np.isfinite(a).all():
            raise ValueError(f"{arg}[{i}]: contains NaN or Inf")
        out.append(a)
    return out


def resample_strands(strands, n: int = 100, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Resample each strand to `n` vertices evenly spaced in arc length.

    Vertex 0 (the root) and the tip are kept exactly; in between, points are linearly
    interpolated along the polyline.

    Args:
        strands: a sequence of (n_i, 3) arrays/tensors (n_i >= 2, non-zero length), or one
            (S, N, 3) array/tensor.
        n: vertices per output strand (>= 2; 100 in the paper).
        dtype: torch float dtype of the result.

    Returns:
        (S, n, 3) tensor (CPU for array input, the input's device for tensor input).
    """
    if int(n) < 2:
        raise ValueError(f"n: expected an int >= 2, got {n}")
    device = strands.device if isinstance(strands, torch.Tensor) else torch.device("cpu")
    items = as_strand_list("strands", strands)
    out = np.empty((len(items), int(n), 3))
    # Group strands by vertex count so the vectorised resampler runs once per group.
    groups: dict[int, list[int]] = {}
    for i, a in enumerate(items):
        if a.shape[0] < 2:
            raise ValueError(f"strands[{i}]: needs at least 2 vertices to resample, got {a.shape[0]}")
        groups.setdefault(a.shape[0], []).append(i)
    for count, idx in groups.items():
        pts = np.stack([np.asarray(items[i], dtype=np.float64) for i in idx])
        lengths = np.linalg.norm(np.diff(pts, axis=1), axis=-1).sum(axis=1)
        if np.any(lengths <= 0):
            raise ValueError(f"strands[{idx[int(np.argmin(lengths))]}]: has zero length, cannot resample")
        out[idx] = resample_polylines(pts, int(n))
    return torch.tensor(out, dtype=dtype, device=device)


def resample_polylines(points: np.ndarray, num_vertices: int) -> np.ndarray:
    """Resample polylines (M, K, 3) to (M, n, 3) vertices evenly spaced in arc length.

    Vertex 0 and the last vertex are kept exactly. Polylines of zero length collapse to their
    first point.
    """
    m, k, _ = points.shape
    seg = np.linalg.norm(np.diff(points, axis=1), axis=-1)
    cum = np.concatenate([np.zeros((m, 1)), np.cumsum(seg, axis=1)], axis=1)
    total = cum[:, -1:]
    t = np.linspace(0.0, 1.0, num_vertices)[None, :] * total
    # Row-wise searchsorted: offset each row so one flat search serves all strands.
    offset = (np.arange(m) * (total.max() + 1.0))[:, None]
    idx = np.searchsorted((cum + offset).reshape(-1), (t + offset).reshape(-1), side="right")
    idx = idx.reshape(m, num_vertices) - np.arange(m)[:, None] * k - 1
    idx = np.clip(idx, 0, k - 2)
    rows = np.arange(m)[:, None]
    c0, c1 = cum[rows, idx], cum[rows, idx + 1]
    w = np.where(c1 > c0, (t - c0) / np.maximum(c1 - c0, 1e-300), 0.0)
    w = np.clip(w, 0.0, 1.0)[..., None]
    out = points[rows, idx] * (1 - w) + points[rows, idx + 1] * w
    out[:, 0] = points[:, 0]
    out[:, -1] = np.where(total > 0, points[:, -1], points[:, 0])
    return out


def generate_hairstyle(
    scalp: Scalp, params: HairstyleParams | str | None = None, num_vertices: int = 100, body=None
) -> Hairstyle:
    """Grow a procedural hairstyle on `scalp` (the generator G_hair of Section 3.1).

    Args:
        scalp: roots (positions (M, 3) [m], outward normals (M, 3), uv (M, 2)).
        params: a `HairstyleParams`, a preset name, or None for the defaults.
        num_vertices: vertices per strand N (100 in the paper), >= 3.
        body: optional rest body surface to keep the hair out of below the head too (long
            hair then drapes over the shoulders and back instead of through them): a
            `hairwarp.ops.hair_body_contact.BodyMesh` or a (vertices (V, 3) [m], faces (F, 3))
            pair of a watertight mesh. Each growth step then queries the signed distance
            (about 2-3 s per 1024-strand style on the CPU instead of ~0.2 s).

    Returns:
        A `Hairstyle` with strands (M', N, 3) float32 [m], M' = M minus the strands shorter
        than `params.min_length` (listed in `filtered`). Vertex 0 of every strand equals its
        scalp root position exactly; the strands stay outside the fitted head ellipsoid (by
        at least a few millimetres away from the root).
    """
    name = ""
    if params is None:
        params = HairstyleParams()
    elif isinstance(params, str):
        name, params = params, hairstyle_preset(params)
    if not isinstance(params, HairstyleParams):
        raise ValueError(f"params: expected HairstyleParams or a preset name, got {type(params).__name__}")
    params.validate()
    if int(num_vertices) < 3:
        raise ValueError(f"num_vertices: expected an int >= 3, got {num_vertices}")
    roots, normals, uv = scalp_arrays(scalp)
    head = fit_head_ellipsoid(scalp)
    rng = np.random.default_rng(int(params.seed))
    m = roots.shape[0]

    rel = roots - head.centre
    radial = _normalize(rel)
    # Bangs: the front band of roots (facing +z, within the central 70 % of the head's width).
    is_bang = np.zeros(m, dtype=bool)
    if params.bangs:
        front = radial[:, 2]
        is_bang = (front > 0.45) & (np.abs(rel[:, 0]) < 0.7 * head.radii[0])
        # Only the frontmost rows: strands within ~3 cm of the hairline.
        if is_bang.any():
            cutoff = np.quantile(rel[is_bang, 2], 0.35)
            is_bang &= rel[:, 2] >= cutoff

    lengths = np.full(m, float(params.length))
    lengths[is_bang] = float(params.bangs_length)
    lengths = lengths * np.exp(params.length_jitter * _jitter_field(rng, roots))

    # Combing direction: gravity, away from the parting, backward for the front (so the hair
    # clears the face) or forward for bangs.
    ex, ey, ez = np.eye(3)
    comb = np.tile(-ey, (m, 1))
    front_weight = np.clip(radial[:, 2], 0.0, None)[:, None]
    if params.parting is None:
        comb += 1.2 * front_weight * (-ez)
        side = np.sign(rel[:, 0])
        comb += 0.15 * side[:, None] * ex
    else:
        part_x = float(params.parting) * head.radii[0]
        offset = rel[:, 0] - part_x
        side = np.where(offset >= 0, 1.0, -1.0)
        # Strong push near the parting line, fading toward the sides (where gravity wins).
        comb += (1.5 * side * np.exp(-np.abs(offset) / (0.5 * head.radii[0])))[:, None] * ex
        comb += 0.3 * front_weight * (-ez)
    comb[is_bang] = -ey + 0.9 * ez + 0.1 * np.sign(rel[is_bang, 0])[:, None] * ex

    # Turning rate [1/m]: how quickly a strand bends from the scalp normal to the comb.
    kappa = np.full(m, 4.0 + 70.0 * float(params.droop))
    # Lift of the strand's first direction over the scalp (1 = 45 degrees from the normal).
    lift = np.full(m, 0.25 + 1.5 * (1.0 - float(params.droop)))
    # Bangs lie close over the forehead: they leave the scalp flat and bend down quickly.
    kappa[is_bang] = 120.0
    lift[is_bang] = 0.15
    # Every strand but the bangs steers around the face, toward its side of the parting.
    face_side = np.where(side >= 0, 1.0, -1.0)
    face_side[is_bang] = 0.0
    d0 = head.radial_distance(roots)
    body_fn = None if body is None else _body_distance(body)
    centreline = _grow(
        roots, normals, comb, lengths, kappa, lift, face_side, head, d0, params.volume, body_fn
    )

    # Blunt cut: the centreline ends where it first drops below the cut height.
    if params.cut_below is not None:
        cut_y = head.centre[1] - float(params.cut_below)
        below = centreline[..., 1] < cut_y
        below[:, 0] = False
        first = np.where(below.any(axis=1), below.argmax(axis=1), _GROWTH_STEPS - 1)
        seg = np.linalg.norm(np.diff(centreline, axis=1), axis=-1)
        cum = np.concatenate([np.zeros((m, 1)), np.cumsum(seg, axis=1)], axis=1)
        lengths = np.minimum(lengths, cum[np.arange(m), first])
        centreline = _trim(centreline, lengths)

    strands = centreline
    if params.curl != "straight" and params.curl_amplitude > 0 and params.curl_frequency > 0:
        strands = _add_curls(centreline, normals, lengths, params, rng, roots, head, d0, body_fn)

    strands = resample_polylines(strands, int(num_vertices))
    strands[:, 0] = roots
    keep = lengths >= float(params.min_length)
    filtered = np.nonzero(~keep)[0]
    index = np.nonzero(keep)[0]
    index_t = torch.as_tensor(index, dtype=torch.int64)
    return Hairstyle(
        strands=torch.tensor(strands[index], dtype=torch.float32),
        root_uv=scalp.uv.detach().cpu().to(torch.float32)[index_t],
        root_normals=scalp.normals.detach().cpu().to(torch.float32)[index_t],
        root_index=index_t,
        filtered=torch.tensor(filtered, dtype=torch.int64),
        name=name,
        info={"params": params, "head_centre": head.centre.copy(), "head_radii": head.radii.copy(),
              "num_bangs": int(is_bang[index].sum())},
    )


def _body_distance(body):
    """A function points (..., 3) -> (signed distance (...), outward unit direction (..., 3))."""
    from hairwarp.ops.hair_body_contact import BodyMesh, hair_body_signed_distance  # noqa: PLC0415

    if not isinstance(body, BodyMesh):
        if not isinstance(body, (tuple, list)) or len(body) != 2:
            raise ValueError("body: expected a BodyMesh or a (vertices, faces) pair")
        vertices, faces = (torch.as_tensor(a) for a in body)
        body = BodyMesh(vertices.to(torch.float32), faces)

    def query(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = torch.tensor(points.reshape(-1, 1, 3), dtype=torch.float64, requires_grad=True)
        d = hair_body_signed_distance(x, body)
        (grad,) = torch.autograd.grad(d.sum(), x)
        return d.detach().numpy().reshape(points.shape[:-1]), grad.numpy().reshape(points.shape)

    return query


def _smooth_along(x: np.ndarray, width: int) -> np.ndarray:
    """Moving average of width `width` (odd) along axis 1, edges padded by repetition."""
    half = width // 2
    pad = [(0, 0), (half, half)] + [(0, 0)] * (x.ndim - 2)
    c = np.cumsum(np.pad(x, pad, mode="edge"), axis=1)
    c = np.concatenate([np.zeros_like(c[:, :1]), c], axis=1)
    return (c[:, width:] - c[:, :-width]) / width


def _slope_limited(x: np.ndarray, ds: np.ndarray, slope: float) -> np.ndarray:
    """The largest values <= x (M, K) whose steps along axis 1 are at most slope * ds (M, 1)."""
    out = x.copy()
    step = slope * ds[:, 0]
    for i in range(1, out.shape[1]):
        out[:, i] = np.minimum(out[:, i], out[:, i - 1] + step)
    for i in range(out.shape[1] - 2, -1, -1):
        out[:, i] = np.minimum(out[:, i], out[:, i + 1] + step)
    return out


def _jitter_field(rng: np.random.Generator, points: np.ndarray, white: float = 0.3) -> np.ndarray:
    """Unit-variance random values at `points` (M, 3): mostly a smooth field, a little noise.

    Neighbouring strands vary together (clumps, layered cuts), as neighbouring guide strands
    do in PERM's texture-space representation; the smooth part is a sum of random Fourier
    features with a correlation length of ~3 cm.
    """
    features = 24
    w = rng.standard_normal((features, 3)) / _JITTER_CORRELATION
    b = rng.uniform(0.0, 2 * np.pi, features)
    smooth = np.sqrt(2.0 / features) * np.cos(points @ w.T + b).sum(axis=1)
    return np.sqrt(1 - white**2) * smooth + white * rng.standard_normal(points.shape[0])


def _clearance(d0: np.ndarray, s: np.ndarray, volume: float) -> np.ndarray:
    """Clearance [m] a strand keeps over the head proxy at arc length s from its root.

    At the root it is the root's own distance d0 (the scalp is not exactly an ellipsoid), it
    rises at most as fast as the arc length (a strand leaving along the normal), up to the
    style's volume offset.
    """
    return np.minimum(d0 + s, np.maximum(d0, _MIN_CLEARANCE + volume))


def _grow(
    roots, normals, comb, lengths, kappa, lift, face_side, head, d0, volume, body_fn=None
) -> np.ndarray:
    """Integrate the centrelines: (M, _GROWTH_STEPS, 3), equal steps, arc length `lengths`."""
    m = roots.shape[0]
    # Pushing points out of the head proxy lengthens steps; grow a little more, then trim.
    h = 1.1 * lengths / (_GROWTH_STEPS - 1)
    p = roots.copy()
    # Hair leaves the scalp at a slant (follicles are angled), already leaning toward the comb:
    # stiff styles (low droop) lift more.
    tangent = comb - np.sum(comb * normals, axis=1, keepdims=True) * normals
    d = _normalize(lift[:, None] * normals + _normalize(tangent))
    out = np.empty((m, _GROWTH_STEPS, 3))
    out[:, 0] = p
    ex, ey = np.eye(3)[0], np.eye(3)[1]
    c, r = head.centre, head.radii
    for k in range(1, _GROWTH_STEPS):
        s = k * h
        n_e = head.normal(p)
        dist = head.radial_distance(p)
        # Near the head the comb slides along the surface (its inward part removed); away from
        # the head (past the widest part, or after sticking out) only gravity pulls.
        near = np.clip(1.0 - (dist - d0) / 0.04, 0.0, 1.0)[:, None]
        target = near * comb + (1.0 - near) * (-ey)
        # The face (in front of the head, below the hairline, between the temples) is kept
        # clear: strands entering that zone are steered sideways.
        rel = p - c
        face = (np.clip((0.7 * r[0] - np.abs(rel[:, 0])) / (0.25 * r[0]), 0.0, 1.0)
                * np.clip((0.6 * r[1] - rel[:, 1]) / (0.15 * r[1]), 0.0, 1.0)
                * np.clip((rel[:, 2] - 0.3 * r[2]) / (0.15 * r[2]), 0.0, 1.0)) * np.abs(face_side)
        # Sideways, with gravity held off, until the strand has cleared the temple.
        target = target + face[:, None] * (4.0 * face_side[:, None] * ex + 0.8 * near * ey)
        inward = np.minimum(np.sum(target * n_e, axis=1, keepdims=True), 0.0)
        target = _normalize(target - inward * n_e)
        turn = np.minimum(kappa * h, 1.0)[:, None]
        d = _normalize(d + turn * (target - np.sum(target * d, axis=1, keepdims=True) * d))
        q = p + h[:, None] * d
        q = head.push_out(q, _clearance(d0, s, volume))
        if body_fn is not None:
            if k == 1:
                d0_body = body_fn(roots)[0]
            dist_b, n_b = body_fn(q)
            need = _clearance(d0_body, s, volume) - dist_b
            q = q + np.maximum(need, 0.0)[:, None] * n_b
        step = q - p
        d = np.where(np.linalg.norm(step, axis=1, keepdims=True) > 0, _normalize(step), d)
        p = q
        out[:, k] = p
    return _trim(out, lengths)


def _trim(polylines: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Cut each polyline at arc length `lengths` (if longer) and resample it to equal steps."""
    m, k, _ = polylines.shape
    seg = np.linalg.norm(np.diff(polylines, axis=1), axis=-1)
    cum = np.concatenate([np.zeros((m, 1)), np.cumsum(seg, axis=1)], axis=1)
    target = np.minimum(lengths, cum[:, -1])
    # Index of the segment holding the cut, and the cut point on it.
    j = np.clip((cum < target[:, None]).sum(axis=1) - 1, 0, k - 2)
    rows = np.arange(m)
    w = np.clip((target - cum[rows, j]) / np.maximum(seg[rows, j], 1e-300), 0.0, 1.0)[:, None]
    end = polylines[rows, j] * (1 - w) + polylines[rows, j + 1] * w
    after = np.arange(k)[None, :] > j[:, None]
    cut = np.where(after[..., None], end[:, None, :], polylines)
    return resample_polylines(cut, k)


def _add_curls(centreline, normals, lengths, params, rng, roots, head, d0, body_fn=None) -> np.ndarray:
    """Waves (planar) or curls (helix) around the centreline, ramped in from the root."""
    m, k, _ = centreline.shape
    s = np.linspace(0.0, 1.0, k)[None, :] * lengths[:, None]
    ramp = np.clip(s / _CURL_RAMP, 0.0, 1.0)
    ramp = ramp * ramp * (3 - 2 * ramp)
    # Neighbouring strands curl in phase (clumps), as real locks do; a little noise per strand.
    direction = _normalize(rng.standard_normal(3))
    phase = 2 * np.pi * (roots - head.centre) @ direction / 0.05 + 0.5 * _jitter_field(rng, roots)
    amp = float(params.curl_amplitude) * np.exp(0.15 * _jitter_field(rng, roots))
    angle = 2 * np.pi * float(params.curl_frequency) * s + phase[:, None]
    a = amp[:, None] * ramp  # (M, K) curl amplitude along the strand

    # Curls need room: where the centreline lies closer to the head than the amplitude, lift
    # it off the head (smoothly, a softplus of the shortfall) so the curl fits, as curly hair
    # stands off the scalp. Squashing the curl instead would fold it into tight corners.
    clearance = _clearance(d0[:, None], s, params.volume)
    room = head.radial_distance(centreline) - clearance
    w = np.maximum(0.25 * a, 1e-7)
    lift = _smooth_along(w * np.logaddexp(0.0, (a - room) / w), 15)
    lift[:, 0] = 0.0
    lift = _slope_limited(lift, s[:, 1:2] - s[:, :1], 0.3)
    centreline = centreline + lift[..., None] * head.normal(centreline)
    if body_fn is not None:
        # The same lift off the body, along its (smoothed) outward directions.
        d0_body = body_fn(roots)[0]
        dist_b, n_b = body_fn(centreline)
        room_b = dist_b - _clearance(d0_body[:, None], s, params.volume)
        lift_b = _smooth_along(w * np.logaddexp(0.0, (a - room_b) / w), 15)
        lift_b[:, 0] = 0.0
        lift_b = _slope_limited(lift_b, s[:, 1:2] - s[:, :1], 0.3)
        centreline = centreline + lift_b[..., None] * _normalize(_smooth_along(n_b, 15))

    # Where the centreline bends tighter than the curl is wide, the curve offset from it
    # would form cusps: keep amplitude x curvature <= ~1/2. The curvature and the frame come
    # from a smoothed copy of the centreline (its growth steps carry small corners).
    smooth = _smooth_along(centreline, 9)
    tangent = _normalize(np.gradient(smooth, axis=1))
    seg = np.linalg.norm(np.gradient(smooth, axis=1), axis=-1)
    curvature = np.linalg.norm(np.gradient(tangent, axis=1), axis=-1) / np.maximum(seg, 1e-12)
    curvature = _smooth_along(curvature, 15)
    a = a / np.sqrt(1.0 + (2.0 * a * curvature) ** 2)
    # A fast-changing amplitude moves the curve sideways faster than it advances: cap the
    # slope |da/ds| (the largest such envelope below a).
    a = _slope_limited(a, s[:, 1:2] - s[:, :1], 0.3)

    # Parallel-transported frame along the (lifted) centreline, started perpendicular to the
    # root normal.
    ref = np.where(np.abs(normals[:, 1:2]) < 0.9, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    nrm = _normalize(np.cross(normals, ref))
    frames_n = np.empty_like(centreline)
    for i in range(k):
        t = tangent[:, i]
        nrm = _normalize(nrm - np.sum(nrm * t, axis=1, keepdims=True) * t)
        frames_n[:, i] = nrm
    frames_b = np.cross(tangent, frames_n)
    a = a[..., None]
    if params.curl == "wavy":
        offset = a * np.sin(angle)[..., None] * frames_n
    else:
        offset = a * (np.cos(angle)[..., None] * frames_n + np.sin(angle)[..., None] * frames_b)
    # The smooth push's width shrinks to zero at the root, which must stay where it is.
    width = _SOFT_WIDTH * np.clip(s / 0.02, 1e-6, 1.0)
    curled = head.soft_push_out(centreline + offset, clearance, width)
    if body_fn is not None:
        # The same smooth push against the body: distance d -> c + w softplus((d - c) / w).
        dist_b, n_b = body_fn(curled)
        c = _clearance(d0_body[:, None], s, params.volume)
        new = c + width * np.logaddexp(0.0, (dist_b - c) / width)
        curled = curled + (new - dist_b)[..., None] * n_b
        curled[:, 0] = centreline[:, 0]
    return curled
