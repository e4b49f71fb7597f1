"""The scalp: a 32x32 UV grid of hair roots over the head of the rest body (Section 3.1)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from hairwarp.scene import _geometry


@dataclass
class Scalp:
    """Hair roots on the rest body's head.

    Attributes:
        uv: (M, 2) float32 root UV coordinates in [0, 1]^2 on the scalp grid.
        positions: (M, 3) float32 rest root positions on the head surface [m], y up.
        normals: (M, 3) float32 outward unit scalp normals at the roots.
        resolution: grid size per side (32 in the paper, so M <= 1024).
    """

    uv: torch.Tensor
    positions: torch.Tensor
    normals: torch.Tensor
    resolution: int = 32

    @property
    def num_roots(self) -> int:
        return int(self.uv.shape[0])

    def every(self, stride: int) -> Scalp:
        """One root in `stride` (1: this scalp), spread over the whole scalp, for quick runs.

        A full grid keeps `grid_subset`'s lattice (so 16 keeps 64 roots over the whole head,
        not two columns of it); any other root set keeps every `stride`-th root.
        """
        if not isinstance(stride, int) or isinstance(stride, bool) or stride < 1:
            raise ValueError(f"stride: expected a positive int, got {stride!r}")
        if stride == 1:
            return self
        keep = root_subset(self.num_roots, self.resolution, stride, self.uv.device)
        return Scalp(uv=self.uv[keep], positions=self.positions[keep], normals=self.normals[keep],
                     resolution=self.resolution)


def root_subset(num_roots: int, resolution: int, stride: int, device=None) -> torch.Tensor:
    """(about num_roots / stride,) int64 indices of one root (or strand grown on it) in `stride`.

    Roots (or one strand per root, in the scalp's order) that fill a resolution x resolution
    grid keep `grid_subset`'s lattice, spread over the whole scalp; any other set keeps every
    `stride`-th (its order is its own).
    """
    if num_roots == resolution * resolution:
        return grid_subset(resolution, stride, device)
    return torch.arange(0, num_roots, stride, device=device)


@functools.lru_cache(maxsize=64)
def _grid_subset_cached(resolution: int, stride: int) -> tuple[int, ...]:
    row, col = torch.meshgrid(torch.arange(resolution), torch.arange(resolution), indexing="ij")
    row, col = row.reshape(-1), col.reshape(-1)
    cells = torch.stack([row, col], 1).to(torch.float64)

    def spacing(keep: torch.Tensor) -> float:
        if keep.numel() < 2:
            return math.inf
        d = torch.cdist(cells[keep], cells[keep])
        d.fill_diagonal_(math.inf)
        return float(d.min())

    # The rank-1 lattice (col + k row) = o (mod stride): k sets its shape (k = 0 keeps columns,
    # a row-major slice's pattern when stride divides the row), o its place. Among the shapes
    # that keep resolution^2 / stride cells (rounded), the one with the largest spacing
    # between kept cells; then the place whose centroid is nearest the grid's centre.
    n = resolution * resolution
    centre = (resolution - 1) / 2.0
    best, best_key = None, None
    for k in range(min(stride, n)):
        residue = (col + k * row) % stride
        counts = torch.bincount(residue, minlength=stride)
        fits = (counts > 0) & ((counts.double() - n / stride).abs() < 1.0)
        if not bool(fits.any()):
            continue
        centroid = torch.zeros(stride, 2, dtype=torch.float64).index_add_(0, residue, cells)
        offset = (centroid / counts.clamp_min(1)[:, None].double() - centre).abs().sum(1)
        offset[~fits] = math.inf
        o = int(offset.argmin())
        keep = torch.nonzero(residue == o).flatten()
        key = (-round(spacing(keep), 9), round(float(offset[o]), 9))
        if best_key is None or key < best_key:
            best, best_key = keep, key
    if best is None:
        return tuple(range(0, n, stride))
    return tuple(int(i) for i in best)


def grid_subset(resolution: int, stride: int, device=None) -> torch.Tensor:
    """(about resolution^2 / stride,) int64 row-major indices of grid cells spread over the grid.

    The cells where (col + k row) = o (mod stride), a rank-1 lattice: one cell in `stride` of
    every row (of every few rows for a stride past the row's length), rows shifted against each
    other so that the kept cells lie as far apart as such a pattern allows, centred on the
    grid: one root in 16 of the 32 x 32 scalp is 64 roots over the whole head. Exactly
    resolution^2 / stride cells when `stride` divides `resolution`. Deterministic.

    Args:
        resolution: cells per side of a row-major grid.
        stride: keep one cell in this many (1: all).
    """
    for name, value in (("resolution", resolution), ("stride", stride)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name}: expected a positive int, got {value!r}")
    if stride == 1:
        return torch.arange(resolution * resolution, device=device)
    return torch.tensor(_grid_subset_cached(resolution, stride), dtype=torch.long, device=device)


# The scalp cap: directions from the cranium's centre whose angle from vertical (y) is at
# most the rim angle, which blends smoothly with the azimuth from FRONT_DEG at the forehead
# (the hairline) through SIDE_DEG at the sides (above the ears) to BACK_DEG at the back (the
# nape) [deg].
SCALP_FRONT_DEG = 55.0
SCALP_SIDE_DEG = 88.0
SCALP_BACK_DEG = 140.0
# The sphere fitted to the cranium uses the upper part of the head region: vertices above
# this fraction of its height (the face and jaw below it are not round).
_CRANIUM_FRACTION = 0.55
# Triangles whose centroid lies within this many cranium radii of its centre are searched.
_NEAR_HEAD = 2.0
# Triangles each scalp ray tests: those whose centroid direction is closest to the ray's.
_RAY_CANDIDATES = 128


def fit_cranium_sphere(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares sphere through the top part of a head: (centre (3,), radius ()) [m].

    Args:
        points: (H, 3) head-region vertices [m], y up.
    """
    y = points[:, 1]
    cut = y.min() + _CRANIUM_FRACTION * (y.max() - y.min())
    p = points[y >= cut]
    # |p|^2 = 2 p.c + (r^2 - |c|^2): linear in (c, r^2 - |c|^2).
    a = torch.cat([2 * p, torch.ones_like(p[:, :1])], 1)
    b = (p * p).sum(1, keepdim=True)
    sol = torch.linalg.lstsq(a, b).solution[:, 0]
    centre = sol[:3]
    radius = torch.sqrt(sol[3] + (centre * centre).sum())
    return centre, radius


def scalp_directions(
    uv: torch.Tensor,
    front_deg: float = SCALP_FRONT_DEG,
    side_deg: float = SCALP_SIDE_DEG,
    back_deg: float = SCALP_BACK_DEG,
) -> torch.Tensor:
    """Unit directions (M, 3) from the cranium's centre for scalp UVs (M, 2) in [0, 1]^2.

    The UV square maps onto the unit disk (elliptical square-to-disk map, so the grid's
    corners reach the rim too); a disk point at radius r and azimuth psi gives the direction
    at angle r * rim(psi) from vertical, azimuth psi, where rim(psi) = side cos^2 psi +
    (front or back) sin^2 psi (continuous, with a continuous slope). u runs from the body's
    right to its left (+x), v from the forehead (v = 0, +z) to the nape (v = 1, -z).
    """
    a = 2 * uv[:, 0] - 1
    b = 2 * uv[:, 1] - 1
    x = a * torch.sqrt(1 - b * b / 2)  # towards the body's left
    z = b * torch.sqrt(1 - a * a / 2)  # towards the back
    r = torch.sqrt(x * x + z * z)
    safe = r.clamp_min(1e-12)
    cos_psi2 = torch.where(r > 1e-12, (x / safe) ** 2, torch.ones_like(r))
    back, front = math.radians(back_deg), math.radians(front_deg)
    end = torch.where(z > 0, torch.full_like(r, back), torch.full_like(r, front))
    rim = math.radians(side_deg) * cos_psi2 + end * (1 - cos_psi2)
    theta = rim * r
    s = torch.where(r > 1e-12, torch.sin(theta) / safe, rim)  # sin(theta) / r, its limit at the pole
    return torch.stack([s * x, torch.cos(theta), -s * z], -1)


def grid_uv(resolution: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(resolution^2, 2) cell-centre UVs, row-major: root m = row * resolution + col has
    u = (col + 0.5) / resolution, v = (row + 0.5) / resolution.
    """
    t = (torch.arange(resolution, dtype=torch.float64, device=device) + 0.5) / resolution
    v, u = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], 1).to(dtype)


def build_scalp(
    body,
    resolution: int = 32,
    front_deg: float = SCALP_FRONT_DEG,
    side_deg: float = SCALP_SIDE_DEG,
    back_deg: float = SCALP_BACK_DEG,
) -> Scalp:
    """The scalp grid of a body's rest head: `resolution`^2 roots on the surface.

    Each root is where the ray from the cranium's centre (a sphere fitted to the top of the
    head region) in its UV's direction (`scalp_directions`) first leaves the body; its normal is
    the mesh's area-weighted vertex normal interpolated at that point. Deterministic.

    Args:
        body: a `hairwarp.scene.body.Body` (its rest vertices, faces, head region).
        resolution: grid cells per side (32 in the paper: 1024 roots).
        front_deg, side_deg, back_deg: the scalp's rim, as angles from vertical seen from
            the cranium's centre at the forehead, the sides and the back [deg].

    Returns:
        `Scalp` (float32, on the body's device), root m at row m // resolution, column
        m % resolution.

    Raises:
        ValueError: on a bad resolution, or when a ray misses the head region (the cap is
            too large for this head).
    """
    if not isinstance(resolution, int) or isinstance(resolution, bool) or resolution < 1:
        raise ValueError(f"resolution: expected a positive int, got {resolution!r}")
    for name, value in (("front_deg", front_deg), ("side_deg", side_deg), ("back_deg", back_deg)):
        if not 0.0 < float(value) < 180.0:
            raise ValueError(f"{name}: expected an angle in (0, 180) degrees, got {value}")
    vertices = body.rest_vertices.to(torch.float64)
    faces = body.faces.long().to(vertices.device)
    head = body.head_vertex_indices.to(vertices.device)
    centre, radius = fit_cranium_sphere(vertices[head])
    # Each ray tests the triangles near the head (the nape lies outside the head region, so
    # the region itself is not enough) seen from the centre closest to its direction; the
    # triangle it leaves through is among them (a cone of a few degrees holds it).
    near = (vertices[faces].mean(1) - centre).norm(dim=-1) < _NEAR_HEAD * radius
    near_faces = faces[near]
    seen = vertices[near_faces].mean(1) - centre
    seen = seen / seen.norm(dim=-1, keepdim=True)

    uv = grid_uv(resolution, torch.float64, vertices.device)
    directions = scalp_directions(uv, front_deg, side_deg, back_deg)
    origins = centre.expand_as(directions)
    cone = (directions @ seen.T).topk(min(_RAY_CANDIDATES, near_faces.shape[0]), dim=1).indices
    t, face, bary = _geometry.ray_mesh_first_exit(origins, directions, vertices, near_faces, cone)
    if bool((face < 0).any()):
        raise ValueError(
            f"body: {int((face < 0).sum())} scalp rays find no head surface; shrink the rim angles"
        )
    positions = origins + t[:, None] * directions
    normals_v = _geometry.vertex_normals(vertices, faces)
    corners = near_faces[face]  # (M, 3)
    normals = (bary[:, :, None] * normals_v[corners]).sum(1)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    return Scalp(
        uv=uv.to(torch.float32),
        positions=positions.to(torch.float32),
        normals=normals.to(torch.float32),
        resolution=resolution,
    )
