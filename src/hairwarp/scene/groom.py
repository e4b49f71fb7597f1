"""Grooms from elsewhere: fit their roots to this body's scalp, then attach them to the grid.

A groom made on another head (another scale, another place in its world, centimetres) puts
its roots off our scalp; projecting each root onto the scalp then drags the strands through
the head. `fit_similarity_to_scalp` first finds the similarity transform (scale, rotation,
translation) that lays the groom's roots onto the head, by ICP as the paper aligns PERM's
head with SMPL's: each iteration pairs every root with its nearest head-surface point and
every scalp grid root with its nearest groom root (both ways, so the roots cannot shrink onto
one spot), and solves the best similarity for those pairs in closed form (Umeyama, 1991).
`attach_strands` then resamples, filters and snaps each strand to its nearest scalp root.

A similarity cannot make another head's shape ours: after the fit, a strand that left the old
scalp along its normal leaves the new one at an angle (into the head where the new scalp
curves away from the old). So after a fit the root part of each snapped strand is turned by the
smallest rotation taking the old scalp's normal at its root (`estimate_root_normals`, from
the groom's own roots) to the new scalp's normal (`turn_strands_at_roots`): it leaves the new
scalp at the angle it left the old one, as the root alignment term expects, and its hanging
length keeps its direction.

The work runs on the groom's concatenated vertices (V, 3) with a vertex count per strand, in
numpy operations over all strands (no Python loop per strand): 100 000 strands load in
seconds (benchmarks/bm_groom_load.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from hairwarp.scene.hairstyles import Hairstyle, scalp_arrays
from hairwarp.scene.scalp import Scalp

# A groom is fitted when the median distance of its roots to the nearest scalp root exceeds
# this [m] (a groom made on this body sits within the grid spacing, about 6 mm).
FIT_THRESHOLD = 0.01
# ICP stops when the transform moves the roots by less than this [m] in an iteration.
FIT_TOLERANCE = 1e-6
FIT_ITERATIONS = 100
# The ICP pairs at most this many roots, a seeded random subset of a larger groom (four times
# the scalp grid's 1024 roots). On a 20 000-strand groom from another head, subsets of 4096
# (three seeds) laid every root within 1.9 mm of the fit on all roots (whose residual is
# 8.8 mm: the shapes differ), in 0.4-0.6 s against 2.9 s; subsets of 1024 strayed by 6 mm.
FIT_SAMPLE_SIZE = 4096
FIT_SAMPLE_SEED = 0
# The old scalp's normal at a root: a quadric fitted to this many nearest roots of a seeded
# subset of this many (a patch some 4 cm across whatever the groom's density). On the tool's
# grooms of 400-100 000 strands: a median error of 0.04-0.1 degrees, 1.3-1.8 with 1 mm of
# noise on the roots; the PCA plane of each root's 12 nearest among 4096 roots erred by
# 0.5-2.2 degrees (10 at the 99th percentile on 400 strands), and by 7 with the noise.
NORMAL_NEIGHBOURS = 32
NORMAL_SAMPLE_SIZE = 1024
# After a fit, the root part of each strand turns from the old scalp's normal to the new one:
# in full over the first tenth of its length, fading out (smoothstep) by 30 %. Chosen on
# bm_groom_load's 400-strand groom from a head 15 % wider and 10 % flatter than ours: turning
# whole strands rigidly about their roots swings their hanging lengths (a 9 degree median turn
# moves a 40 cm tip by 6 cm) into the neck and shoulders, and put more vertices inside the body
# than no turn at all; the root part alone fixes the first tenth as well and not the rest.
ROOT_TURN_FULL = 0.1
ROOT_TURN_FADE_END = 0.3
# Strands resampled per block: bounds the temporary arrays (blocks of 8192 x 100 vertices).
_RESAMPLE_BLOCK = 8192


@dataclass
class SimilarityFit:
    """x -> scale * rotation @ x + translation, and how well it fits.

    Attributes:
        scale: uniform scale (dimensionless).
        rotation: (3, 3) rotation matrix.
        translation: (3,) [m].
        residual: RMS distance [m] of the fitted roots to the head surface.
        iterations: ICP iterations run.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float
    iterations: int

    def apply(self, points: np.ndarray) -> np.ndarray:
        """The transform applied to points (..., 3)."""
        return transform_points(points, self.scale * self.rotation) + self.translation

    def describe(self) -> str:
        if self.iterations == 0:
            return "translated by (" + ", ".join(f"{v:+.3f}" for v in self.translation) + ") m"
        angle = float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1) / 2, -1, 1))))
        t = ", ".join(f"{v:+.3f}" for v in self.translation)
        return (f"scale {self.scale:.4f}, rotation {angle:.2f} deg, offset ({t}) m, residual "
                f"{self.residual * 1e3:.2f} mm, {self.iterations} ICP iterations")


def transform_points(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """The product `matrix @ p` for each point p of `points` (..., 3), float64.

    By einsum's own loop, not BLAS: a (V, 3) x (3, 3) product through OpenBLAS took 2.2 s for
    6 million points on a 2-core CPU with the other core busy (its threads wait on each
    other), einsum 0.15-0.3 s.
    """
    return np.einsum("...j,ij->...i", np.asarray(points, dtype=np.float64), np.asarray(matrix, dtype=np.float64))


def umeyama(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
            with_scale: bool = True, with_rotation: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) minimising sum w |s R source + t - target|^2 (Umeyama 1991).

    Args:
        source: (K, 3) points.
        target: (K, 3) points paired with them.
        weights: (K,) non-negative weights (None: equal).
        with_scale: solve for the scale (else 1).
        with_rotation: solve for the rotation (else the identity).

    Returns:
        (scale, rotation (3, 3) with det +1, translation (3,)).
    """
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_t = w @ source, w @ target
    a, b = source - mu_s, target - mu_t
    var_s = float(w @ (a * a).sum(1))
    if not with_rotation:
        scale = float(w @ (a * b).sum(1) / var_s) if with_scale and var_s > 0 else 1.0
        return scale, np.eye(3), mu_t - scale * mu_s
    cov = (b * w[:, None]).T @ a
    u, sigma, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[-1] = -1.0
    rotation = u @ np.diag(d) @ vt
    scale = float((sigma * d).sum() / var_s) if with_scale and var_s > 0 else 1.0
    return scale, rotation, mu_t - scale * rotation @ mu_s


def _nearest(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index (int64) of the nearest of `points` (P, 3) to each query (Q, 3): exact, by a k-d tree."""
    return cKDTree(points).query(queries)[1].astype(np.int64)


def fit_similarity_to_scalp(roots: np.ndarray, scalp: Scalp, head_points: np.ndarray,
                            iterations: int = FIT_ITERATIONS, sample_size: int = FIT_SAMPLE_SIZE,
                            seed: int = FIT_SAMPLE_SEED) -> SimilarityFit:
    """ICP with scale: the similarity that lays a groom's roots onto this head's scalp.

    Args:
        roots: (K, 3) the groom's root positions [m], y up, facing +z (after unit and axis
            conversion).
        scalp: the body's scalp grid (its roots are where hair grows on this head).
        head_points: (P, 3) points of the head surface [m] (the rest head region's vertices).
        iterations: most ICP iterations per stage.
        sample_size: the ICP pairs a seeded random subset of this many roots when K is larger
            (the transform is then applied to every root); all roots when K <= sample_size.
        seed: the subset's seed.

    Returns:
        SimilarityFit from the groom's frame to the body's; its residual is over all K roots.

    Raises:
        ValueError: fewer than 3 roots.
    """
    all_roots = np.asarray(roots, dtype=np.float64)
    head = np.asarray(head_points, dtype=np.float64)
    grid = scalp_arrays(scalp)[0]
    if len(all_roots) < 3:
        raise ValueError(f"roots: a fit needs at least 3 strands, got {len(all_roots)}")
    roots = all_roots
    if len(roots) > int(sample_size):
        pick = np.random.default_rng(seed).choice(len(roots), size=int(sample_size), replace=False)
        roots = roots[np.sort(pick)]
    head_tree = cKDTree(head)
    # Start: centroids together, spreads equal (no rotation: both are y up, facing +z).
    spread = np.sqrt(((grid - grid.mean(0)) ** 2).sum(1).mean())
    spread_roots = np.sqrt(((roots - roots.mean(0)) ** 2).sum(1).mean())
    scale = spread / max(spread_roots, 1e-12)
    rotation = np.eye(3)
    translation = grid.mean(0) - scale * roots.mean(0)
    moved = scale * roots + translation
    # The backward pairs use the scalp grid thinned to the groom's density: a sparse groom
    # paired with every grid root is pulled toward wherever the grid has no strand.
    grid = grid[:: max(1, round(len(grid) / len(roots)))]
    weights = np.concatenate([np.full(len(roots), 0.5 / len(roots)), np.full(len(grid), 0.5 / len(grid))])
    it = 0
    # Two stages: scale and offset alone first (both heads are y up, facing +z), then the full
    # similarity from there. A head is nearly round, so a rotation left free from the start can
    # slide into a wrong minimum tens of degrees away.
    for rotate in (False, True):
        for _ in range(iterations):
            it += 1
            forward = head[head_tree.query(moved)[1]]  # each root to the nearest head point
            backward = cKDTree(moved).query(grid)[1]  # each (thinned) scalp root to the nearest groom root
            source = np.concatenate([roots, roots[backward]])
            target = np.concatenate([forward, grid])
            scale, rot, translation = umeyama(source, target, weights, with_rotation=rotate)
            rotation = rot
            new = scale * transform_points(roots, rotation) + translation
            step = float(np.abs(new - moved).max())
            moved = new
            if step < FIT_TOLERANCE:
                break
    fitted = scale * transform_points(all_roots, rotation) + translation
    residual = float(np.sqrt(((fitted - head[head_tree.query(fitted)[1]]) ** 2).sum(1).mean()))
    return SimilarityFit(scale=scale, rotation=rotation, translation=translation, residual=residual, iterations=it)


def estimate_root_normals(roots: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS,
                          sample_size: int = NORMAL_SAMPLE_SIZE, seed: int = FIT_SAMPLE_SEED) -> np.ndarray:
    """The outward unit normal of the scalp a groom was made on, at each of its roots.

    On a seeded random subset of `sample_size` roots (all roots when there are fewer; the patch
    then has the same size whatever the groom's density), each subset root's patch: its
    `neighbours` nearest subset roots, a plane through them (PCA), and a quadric height field
    over that plane, fitted by least squares. Each root takes the normal at its position of the
    quadric of its nearest subset root. The quadric takes out the bias of a plane where the
    patch is one-sided (at the hairline) or curved. The normal points away from
    the roots' centroid: a scalp is convex, so the centroid of its roots lies under every
    tangent plane; a strand's first segment cannot decide the side, as combed hair leaves the
    scalp nearly along it.

    Args:
        roots: (K, 3) root positions [m], K >= 3 (on the old scalp, in any frame).
        neighbours: roots per patch (a plane alone below 10, when the groom has fewer roots).
        sample_size: the subset's size.
        seed: the subset's seed.

    Returns:
        (K, 3) float64 unit normals.

    Raises:
        ValueError: fewer than 3 roots.
    """
    roots = np.asarray(roots, dtype=np.float64)
    if roots.ndim != 2 or roots.shape[1] != 3 or len(roots) < 3:
        raise ValueError(f"roots: expected (K, 3) with K >= 3, got shape {roots.shape}")
    sample = roots
    if len(roots) > int(sample_size):
        sample = roots[np.sort(np.random.default_rng(seed).choice(len(roots), size=int(sample_size), replace=False))]
    k = max(3, min(int(neighbours), len(sample)))
    tree = cKDTree(sample)
    # One patch per subset root: its k nearest subset roots, their PCA frame (e1, e2, normal).
    patch = sample[tree.query(sample, k=k)[1]]  # (S, k, 3)
    centred = patch - patch.mean(1, keepdims=True)
    axes = np.linalg.eigh(np.einsum("ski,skj->sij", centred, centred))[1]  # ascending variance
    normal, e1, e2 = axes[:, :, 0], axes[:, :, 2], axes[:, :, 1]
    # Each root takes the patch of its nearest subset root (itself when every root is in it).
    owner = tree.query(roots)[1] if len(sample) < len(roots) else np.arange(len(roots))
    if k >= 10:
        # h = a x^2 + b x y + c y^2 + d x + e y + f about the subset root, x and y scaled to the
        # patch's size; its slope at the root tilts the plane's normal.
        rel = patch - sample[:, None]
        x = np.einsum("ski,si->sk", rel, e1)
        y = np.einsum("ski,si->sk", rel, e2)
        h = np.einsum("ski,si->sk", rel, normal)
        size = np.sqrt((x * x + y * y).mean(1))
        x, y = x / size[:, None], y / size[:, None]
        design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)
        gram = np.einsum("ski,skj->sij", design, design) + 1e-10 * np.eye(6)
        a, b, c, d, e, _ = np.moveaxis(np.linalg.solve(gram, np.einsum("ski,sk->si", design, h)[..., None])[..., 0], -1, 0)
        rel = roots - sample[owner]
        s = size[owner]
        x = np.einsum("ki,ki->k", rel, e1[owner]) / s
        y = np.einsum("ki,ki->k", rel, e2[owner]) / s
        o = owner
        slope_x = (2 * a[o] * x + b[o] * y + d[o]) / s
        slope_y = (b[o] * x + 2 * c[o] * y + e[o]) / s
        normals = normal[o] - slope_x[:, None] * e1[o] - slope_y[:, None] * e2[o]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    else:
        normals = normal[owner].copy()
    flip = np.einsum("ki,ki->k", normals, roots - sample.mean(0)) < 0
    normals[flip] *= -1.0
    return normals


def turn_strands_at_roots(strands: np.ndarray, from_normals: np.ndarray, to_normals: np.ndarray,
                          full: float = ROOT_TURN_FULL, fade_end: float = ROOT_TURN_FADE_END) -> np.ndarray:
    """Each strand's root part turned by the smallest rotation taking `from` to `to`.

    Each segment turns about the axis from x to: by the whole angle over the first `full` of
    the strand's length, by a share falling smoothly (smoothstep) to zero at `fade_end`, not at
    all beyond. So the strand leaves along `to` as it left along `from`, and the rest keeps its
    direction (hanging hair stays hanging) and moves with the root part. Segment lengths are
    kept exactly; the root does not move. Opposite vectors turn about an axis perpendicular to
    `from`.

    Args:
        strands: (M, N, 3) [m], vertices evenly spaced in arc length, vertex 0 the root.
        from_normals, to_normals: (M, 3) unit vectors.
        full: share of the segments turned by the whole angle (0 < full <= fade_end).
        fade_end: share of the segments past which nothing turns (<= 1).

    Returns:
        (M, N, 3) float64.
    """
    x = np.asarray(strands, dtype=np.float64)
    a = np.asarray(from_normals, dtype=np.float64)
    b = np.asarray(to_normals, dtype=np.float64)
    axis = np.cross(a, b)
    sine = np.linalg.norm(axis, axis=1)
    cosine = np.einsum("ki,ki->k", a, b)
    angle = np.arctan2(sine, cosine)
    parallel = sine < 1e-12
    if parallel.any():
        # No axis from the cross product: any axis perpendicular to `from` (used only when the
        # vectors are opposite; parallel ones have angle 0).
        basis = np.eye(3)[np.argmin(np.abs(a[parallel]), axis=1)]
        axis[parallel] = np.cross(a[parallel], basis)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    n = x.shape[1]
    u = (np.arange(n - 1) + 0.5) / (n - 1)  # each segment's midpoint, as a share of the strand
    w = np.clip((fade_end - u) / max(fade_end - full, 1e-12), 0.0, 1.0)
    share = w * w * (3.0 - 2.0 * w)
    turning = int(np.count_nonzero(share))  # the first segments; the rest only move
    phi = angle[:, None] * share[None, :turning]  # (M, T)
    seg = x[:, 1:turning + 1] - x[:, :turning]
    k0, k1, k2 = (axis[:, i, None] for i in range(3))
    s0, s1, s2 = seg[..., 0], seg[..., 1], seg[..., 2]
    cos_phi, sin_phi = np.cos(phi), np.sin(phi)
    along = (k0 * s0 + k1 * s1 + k2 * s2) * (1.0 - cos_phi)
    # Rodrigues on each segment: v cos + (k x v) sin + k (k . v)(1 - cos).
    turned = np.stack([s0 * cos_phi + (k1 * s2 - k2 * s1) * sin_phi + k0 * along,
                       s1 * cos_phi + (k2 * s0 - k0 * s2) * sin_phi + k1 * along,
                       s2 * cos_phi + (k0 * s1 - k1 * s0) * sin_phi + k2 * along], axis=-1)
    out = np.empty_like(x)
    out[:, 0] = x[:, 0]
    out[:, 1:turning + 1] = x[:, :1] + np.cumsum(turned, axis=1)
    out[:, turning + 1:] = x[:, turning + 1:] + (out[:, turning] - x[:, turning])[:, None]
    return out


def flatten_strands(strands) -> tuple[np.ndarray, np.ndarray]:
    """A list of (n_i, 3) strands as (concatenated points (V, 3) float64, counts (S,) int64)."""
    counts = np.fromiter((len(a) for a in strands), dtype=np.int64, count=len(strands))
    if len(strands) == 0:
        return np.zeros((0, 3)), counts
    points = np.concatenate([np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in strands])
    return points, counts


def flat_strand_lengths(points: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Arc length of each strand of a flat groom [points' unit], (S,) float64 (0 below 2 vertices)."""
    counts = np.asarray(counts, dtype=np.int64)
    lengths = np.zeros(len(counts))
    if len(points) < 2:
        return lengths
    ends = np.cumsum(counts)
    seg = np.sqrt((np.diff(points, axis=0) ** 2).sum(1))
    # The segment from a strand's last vertex to the next strand's first is not hair.
    seg[ends[(counts > 0) & (ends < len(points))] - 1] = 0.0
    long = np.nonzero(counts >= 2)[0]
    if long.size:
        # Each sum runs from a strand's first segment to the next such strand's: past its own
        # segments only zeros (the segments between strands, 1-vertex strands).
        lengths[long] = np.add.reduceat(seg, (ends - counts)[long])
    return lengths


def resample_flat_strands(points: np.ndarray, counts: np.ndarray, num_vertices: int,
                          keep: np.ndarray | None = None, block: int = _RESAMPLE_BLOCK):
    """Strands of any vertex counts resampled to `num_vertices` evenly spaced in arc length.

    The arithmetic of `hairwarp.scene.hairstyles.resample_polylines` (vertex 0 and the tip kept
    exactly, linear interpolation between), on all strands at once: one cumulative arc length
    over the whole groom, restarted at each root, and one sorted search for every target.

    Args:
        points: (V, 3) float64 concatenated vertices.
        counts: (S,) vertex count of each strand.
        num_vertices: vertices per output strand (>= 2).
        keep: (M,) the strands to resample (each >= 2 vertices, non-zero length); None: all.
        block: strands per yielded block.

    Yields:
        (M_b, num_vertices, 3) float64 blocks of the kept strands, in order.
    """
    counts = np.asarray(counts, dtype=np.int64)
    keep = np.arange(len(counts)) if keep is None else np.asarray(keep, dtype=np.int64)
    n = int(num_vertices)
    starts = np.cumsum(counts) - counts
    seg = np.sqrt((np.diff(points, axis=0) ** 2).sum(1))
    ends = starts + counts
    seg[ends[(counts > 0) & (ends < len(points))] - 1] = 0.0  # between strands: no arc length
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    # Arc length from each strand's root (less the cumulative sum at the root, as a per-strand
    # cumulative sum up to round-off), and a search key that also orders the strands: the
    # strand index times more than any strand's length, so one searchsorted serves all.
    owner = np.repeat(np.arange(len(counts)), counts)
    local = cum - cum[starts[owner]]
    total = local[np.maximum(ends - 1, 0)]
    stride = float(total.max(initial=0.0)) + 1.0
    keys = local + owner * stride
    t_unit = np.linspace(0.0, 1.0, n)
    for lo in range(0, len(keep), block):
        k = keep[lo:lo + block]
        first, last, length = starts[k], ends[k] - 1, total[k]
        t = t_unit[None, :] * length[:, None]
        idx = np.searchsorted(keys, (t + (k * stride)[:, None]).reshape(-1), side="right").reshape(len(k), n) - 1
        idx = np.clip(idx, first[:, None], (last - 1)[:, None])
        c0, c1 = local[idx], local[idx + 1]
        w = np.where(c1 > c0, (t - c0) / np.maximum(c1 - c0, 1e-300), 0.0)
        w = np.clip(w, 0.0, 1.0)[..., None]
        res = points[idx] * (1 - w) + points[idx + 1] * w
        res[:, 0] = points[first]
        res[:, -1] = np.where((length > 0)[:, None], points[last], points[first])
        yield res


def attach_strands(strands: list[np.ndarray], scalp: Scalp, *, num_vertices: int = 100, min_length: float = 0.0,
                   snap_roots: bool = True, name: str = "", info: dict | None = None,
                   old_normals: np.ndarray | None = None) -> Hairstyle:
    """Strands in the body's frame (metres, y up) attached to the scalp grid.

    Drops strands with fewer than 2 vertices or shorter than `min_length` [m] (Section 3.1),
    resamples the rest to `num_vertices` by arc length, and maps each root to the nearest
    scalp root (snapping the strand onto it when `snap_roots`).

    Args:
        strands: list of (n_i, 3) arrays [m] (`attach_flat_strands` takes them concatenated).
        scalp: the body's scalp grid.
        num_vertices: vertices per output strand (>= 2).
        min_length: shorter strands are dropped [m].
        snap_roots: translate each strand so its root sits exactly on its scalp root.
        name: the hairstyle's label.
        info: facts to keep in the hairstyle's info.
        old_normals: (S, 3) unit normals of the scalp the strands were made on, at their roots
            (rows of dropped strands are ignored); with `snap_roots`, each strand is turned about
            its root from that normal to the scalp normal of its scalp root.

    Returns:
        A `Hairstyle`; info adds "root_distance_mean/median/max" [m] (root to the nearest
        scalp root, before snapping), "num_file_strands", and with `old_normals`
        "root_rotation_deg_median/max" (the turns about the roots [deg]).

    Raises:
        ValueError: when no strand survives the filtering.
    """
    points, counts = flatten_strands(strands)
    return attach_flat_strands(points, counts, scalp, num_vertices=num_vertices, min_length=min_length,
                               snap_roots=snap_roots, name=name, info=info, old_normals=old_normals)


def attach_flat_strands(points: np.ndarray, counts: np.ndarray, scalp: Scalp, *, num_vertices: int = 100,
                        min_length: float = 0.0, snap_roots: bool = True, name: str = "", info: dict | None = None,
                        old_normals: np.ndarray | None = None) -> Hairstyle:
    """`attach_strands` of a flat groom: points (V, 3) [m] concatenated, counts (S,) per strand."""
    scalp_pos, scalp_nrm, scalp_uv = scalp_arrays(scalp)
    points = np.asarray(points, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    lengths = flat_strand_lengths(points, counts)
    kept = (lengths >= float(min_length)) & (lengths > 0)
    keep, filtered = np.nonzero(kept)[0], np.nonzero(~kept)[0]
    if len(keep) == 0:
        raise ValueError(f"strands: no strand is at least {min_length} m long (of {len(counts)} strands; "
                         "check the units)")
    roots = points[starts[keep]]  # the resampled strands keep their roots exactly
    nearest = _nearest(roots, scalp_pos)
    dist = np.linalg.norm(roots - scalp_pos[nearest], axis=1)
    orient = snap_roots and old_normals is not None
    if orient:
        old = np.asarray(old_normals, dtype=np.float64)[keep]
        turn = np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", old, scalp_nrm[nearest]), -1.0, 1.0)))
    out = np.empty((len(keep), int(num_vertices), 3), dtype=np.float32)
    lo = 0
    for res in resample_flat_strands(points, counts, int(num_vertices), keep):
        block = slice(lo, lo + len(res))
        lo += len(res)
        target = scalp_pos[nearest[block]]
        if snap_roots:
            res = res + (target - res[:, 0])[:, None, :]
            res[:, 0] = target
        if orient:
            res = turn_strands_at_roots(res, old[block], scalp_nrm[nearest[block]])
        out[block] = res
    out_info = dict(info or {})
    out_info.update(root_distance_mean=float(dist.mean()), root_distance_median=float(np.median(dist)),
                    root_distance_max=float(dist.max()), num_file_strands=len(counts))
    if orient:
        out_info.update(root_rotation_deg_median=float(np.median(turn)), root_rotation_deg_max=float(turn.max()))
    return Hairstyle(
        strands=torch.from_numpy(out),
        root_uv=torch.tensor(scalp_uv[nearest], dtype=torch.float32),
        root_normals=torch.tensor(scalp_nrm[nearest], dtype=torch.float32),
        root_index=torch.tensor(nearest, dtype=torch.int64),
        filtered=torch.tensor(filtered, dtype=torch.int64),
        name=name,
        info=out_info,
    )


def place_groom(strands: list[np.ndarray], scalp: Scalp, head_points: np.ndarray, *, fit: str = "auto",
                num_vertices: int = 100, min_length: float = 0.0, name: str = "",
                orient_roots: bool = True) -> tuple[Hairstyle, SimilarityFit | None]:
    """Fit (when asked or needed) and attach a groom given in metres, y up.

    Args:
        strands: list of (n_i, 3) arrays [m], y up, facing +z (`place_flat_groom` takes them
            concatenated).
        scalp: the body's scalp grid.
        head_points: (P, 3) the rest head surface [m] (the fit's target).
        fit: "auto" (fit when the median root lies more than `FIT_THRESHOLD` from the scalp
            grid), "similarity" (always), "translate" (mean root onto the mean scalp root),
            or "none" (keep the file's placement).
        num_vertices, min_length, name: as in `attach_strands`.
        orient_roots: after a similarity fit, turn each snapped strand about its root from the
            old scalp's normal (`estimate_root_normals`) to the new one, so it leaves the new
            scalp as it left the old (the module docstring).

    Returns:
        (Hairstyle, the SimilarityFit applied or None).
    """
    points, counts = flatten_strands(strands)
    return place_flat_groom(points, counts, scalp, head_points, fit=fit, num_vertices=num_vertices,
                            min_length=min_length, name=name, orient_roots=orient_roots)


def place_flat_groom(points: np.ndarray, counts: np.ndarray, scalp: Scalp, head_points: np.ndarray, *,
                     fit: str = "auto", num_vertices: int = 100, min_length: float = 0.0, name: str = "",
                     orient_roots: bool = True) -> tuple[Hairstyle, SimilarityFit | None]:
    """`place_groom` of a flat groom: points (V, 3) [m] concatenated, counts (S,) per strand."""
    if fit not in ("auto", "similarity", "translate", "none"):
        raise ValueError(f"fit: expected 'auto', 'similarity', 'translate' or 'none', got {fit!r}")
    points = np.asarray(points, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.int64)
    usable = counts >= 2
    roots = points[(np.cumsum(counts) - counts)[usable]]
    if len(roots) == 0:
        raise ValueError("strands: no strand with at least 2 vertices")
    grid = scalp_arrays(scalp)[0]
    applied = None
    if fit == "translate":
        offset = grid.mean(0) - roots.mean(0)
        applied = SimilarityFit(1.0, np.eye(3), offset, 0.0, 0)
    elif fit == "similarity" or (fit == "auto" and
                                 float(np.median(np.linalg.norm(roots - grid[_nearest(roots, grid)], axis=1)))
                                 > FIT_THRESHOLD):
        applied = fit_similarity_to_scalp(roots, scalp, head_points)
    old_normals = None
    if applied is not None:
        points = applied.apply(points)
        if orient_roots and applied.iterations > 0 and len(roots) >= 3:
            old_normals = np.zeros((len(counts), 3))
            old_normals[usable] = estimate_root_normals(applied.apply(roots))
    info = {"fit": None if applied is None else applied.describe()}
    style = attach_flat_strands(points, counts, scalp, num_vertices=num_vertices, min_length=min_length, name=name,
                                info=info, old_normals=old_normals)
    return style, applied
