"""Grooms from elsewhere: fit their roots to this body's scalp, then attach them to the grid.

A groom made on another head (another scale, another place in its world, centimetres) puts
its roots off our scalp; projecting each root onto the scalp then drags the strands through
the head. `fit_similarity_to_scalp` first finds the similarity transform (scale, rotation,
translation) that lays the groom's roots onto the head, by ICP as the paper aligns PERM's
head with SMPL's: each iteration pairs every root with its nearest head-surface point and
every scalp grid root with its nearest groom root (both ways, so the roots cannot shrink onto
one spot), and solves the best similarity for those pairs in closed form (Umeyama, 1991).
`attach_strands` then resamples, filters and snaps each strand to its nearest scalp root.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hairwarp.scene.hairstyles import Hairstyle, resample_strands, scalp_arrays
from hairwarp.scene.scalp import Scalp

# A groom is fitted when the median distance of its roots to the nearest scalp root exceeds
# this [m] (a groom made on this body sits within the grid spacing, about 6 mm).
FIT_THRESHOLD = 0.01
# ICP stops when the transform moves the roots by less than this [m] in an iteration.
FIT_TOLERANCE = 1e-6
FIT_ITERATIONS = 100


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
        return self.scale * points @ self.rotation.T + self.translation

    def describe(self) -> str:
        if self.iterations == 0:
            return "translated by (" + ", ".join(f"{v:+.3f}" for v in self.translation) + ") m"
        angle = float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1) / 2, -1, 1))))
        t = ", ".join(f"{v:+.3f}" for v in self.translation)
        return (f"scale {self.scale:.4f}, rotation {angle:.2f} deg, offset ({t}) m, residual "
                f"{self.residual * 1e3:.2f} mm, {self.iterations} ICP iterations")


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
    """Index of the nearest of `points` to each query (chunked to bound memory)."""
    out = np.empty(len(queries), dtype=np.int64)
    for start in range(0, len(queries), 2048):
        q = torch.from_numpy(queries[start:start + 2048])
        out[start:start + 2048] = torch.cdist(q, torch.from_numpy(points)).argmin(1).numpy()
    return out


def fit_similarity_to_scalp(roots: np.ndarray, scalp: Scalp, head_points: np.ndarray,
                            iterations: int = FIT_ITERATIONS) -> SimilarityFit:
    """ICP with scale: the similarity that lays a groom's roots onto this head's scalp.

    Args:
        roots: (K, 3) the groom's root positions [m], y up, facing +z (after unit and axis
            conversion).
        scalp: the body's scalp grid (its roots are where hair grows on this head).
        head_points: (P, 3) points of the head surface [m] (the rest head region's vertices).
        iterations: most ICP iterations.

    Returns:
        SimilarityFit from the groom's frame to the body's.
    """
    roots = np.asarray(roots, dtype=np.float64)
    head = np.asarray(head_points, dtype=np.float64)
    grid = scalp_arrays(scalp)[0]
    if len(roots) < 3:
        raise ValueError(f"roots: a fit needs at least 3 strands, got {len(roots)}")
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
            forward = head[_nearest(moved, head)]  # each root to the nearest head point
            backward = _nearest(grid, moved)  # each (thinned) scalp root to the nearest groom root
            source = np.concatenate([roots, roots[backward]])
            target = np.concatenate([forward, grid])
            scale, rot, translation = umeyama(source, target, weights, with_rotation=rotate)
            rotation = rot
            new = scale * roots @ rotation.T + translation
            step = float(np.abs(new - moved).max())
            moved = new
            if step < FIT_TOLERANCE:
                break
    residual = float(np.sqrt(((moved - head[_nearest(moved, head)]) ** 2).sum(1).mean()))
    return SimilarityFit(scale=scale, rotation=rotation, translation=translation, residual=residual, iterations=it)


def attach_strands(strands: list[np.ndarray], scalp: Scalp, *, num_vertices: int = 100, min_length: float = 0.0,
                   snap_roots: bool = True, name: str = "", info: dict | None = None) -> Hairstyle:
    """Strands in the body's frame (metres, y up) attached to the scalp grid.

    Drops strands with fewer than 2 vertices or shorter than `min_length` [m] (Section 3.1),
    resamples the rest to `num_vertices` by arc length, and maps each root to the nearest
    scalp root (snapping the strand onto it when `snap_roots`).

    Returns:
        A `Hairstyle`; info adds "root_distance_mean/median/max" [m] (root to the nearest
        scalp root, before snapping) and "num_file_strands".

    Raises:
        ValueError: when no strand survives the filtering.
    """
    scalp_pos, scalp_nrm, scalp_uv = scalp_arrays(scalp)
    lengths = np.array([float(np.linalg.norm(np.diff(a, axis=0), axis=1).sum()) if len(a) >= 2 else 0.0
                        for a in strands])
    keep = np.nonzero((lengths >= float(min_length)) & (lengths > 0))[0]
    filtered = np.nonzero(~np.isin(np.arange(len(strands)), keep))[0]
    if len(keep) == 0:
        raise ValueError(f"strands: no strand is at least {min_length} m long (of {len(strands)} strands; "
                         "check the units)")
    res = resample_strands([strands[i] for i in keep], int(num_vertices), dtype=torch.float64).numpy()
    nearest = _nearest(res[:, 0], scalp_pos)
    dist = np.linalg.norm(res[:, 0] - scalp_pos[nearest], axis=1)
    if snap_roots:
        res = res + (scalp_pos[nearest] - res[:, 0])[:, None, :]
        res[:, 0] = scalp_pos[nearest]
    out_info = dict(info or {})
    out_info.update(root_distance_mean=float(dist.mean()), root_distance_median=float(np.median(dist)),
                    root_distance_max=float(dist.max()), num_file_strands=len(strands))
    return Hairstyle(
        strands=torch.tensor(res, dtype=torch.float32),
        root_uv=torch.tensor(scalp_uv[nearest], dtype=torch.float32),
        root_normals=torch.tensor(scalp_nrm[nearest], dtype=torch.float32),
        root_index=torch.tensor(nearest, dtype=torch.int64),
        filtered=torch.tensor(filtered, dtype=torch.int64),
        name=name,
        info=out_info,
    )


def place_groom(strands: list[np.ndarray], scalp: Scalp, head_points: np.ndarray, *, fit: str = "auto",
                num_vertices: int = 100, min_length: float = 0.0, name: str = "") -> tuple[Hairstyle, SimilarityFit | None]:
    """Fit (when asked or needed) and attach a groom given in metres, y up.

    Args:
        strands: list of (n_i, 3) arrays [m], y up, facing +z.
        scalp: the body's scalp grid.
        head_points: (P, 3) the rest head surface [m] (the fit's target).
        fit: "auto" (fit when the median root lies more than `FIT_THRESHOLD` from the scalp
            grid), "similarity" (always), "translate" (mean root onto the mean scalp root),
            or "none" (keep the file's placement).
        num_vertices, min_length, name: as in `attach_strands`.

    Returns:
        (Hairstyle, the SimilarityFit applied or None).
    """
    if fit not in ("auto", "similarity", "translate", "none"):
        raise ValueError(f"fit: expected 'auto', 'similarity', 'translate' or 'none', got {fit!r}")
    usable = [np.asarray(a, dtype=np.float64) for a in strands]
    roots = np.array([a[0] for a in usable if len(a) >= 2])
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
    if applied is not None:
        usable = [applied.apply(a) for a in usable]
    info = {"fit": None if applied is None else applied.describe()}
    style = attach_strands(usable, scalp, num_vertices=num_vertices, min_length=min_length, name=name, info=info)
    return style, applied
