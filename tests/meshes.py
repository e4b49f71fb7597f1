"""Test mesh builders (numpy float64, outward normals, watertight), shared by the test suite.

`icosphere(frequency)` is a geodesic sphere: every face of an icosahedron split into
frequency^2 triangles, vertices pushed onto the sphere. It has 10 f^2 + 2 vertices and
20 f^2 faces (f = 8: 642 / 1280; f = 37: 13 692 / 27 380, the size of a human body mesh).
`body_like(frequency)` stretches it into a body-sized ellipsoid, y up, standing on y = 0.
"""

from __future__ import annotations

import numpy as np

_PHI = (1.0 + 5.0**0.5) / 2.0

# `body_like`: an ellipsoid standing on y = 0, 1.7 m tall [m].
BODY_LIKE_CENTER = (0.0, 0.85, 0.0)
BODY_LIKE_SEMI_AXES = (0.2, 0.85, 0.13)

_ICOSAHEDRON_VERTICES = np.array(
    [
        [-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
        [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
        [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1],
    ],
    dtype=np.float64,
)  # fmt: skip

_ICOSAHEDRON_FACES = np.array(
    [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ],
    dtype=np.int64,
)  # fmt: skip


def icosphere(frequency: int = 8, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """Geodesic sphere, outward (counter-clockwise seen from outside) triangles.

    Args:
        frequency: edge subdivisions of each icosahedron face (>= 1).
        radius: sphere radius [m]; every vertex lies exactly on the sphere.
        center: sphere centre [m].

    Returns:
        (vertices (10 f^2 + 2, 3) float64, faces (20 f^2, 3) int64).
    """
    f = int(frequency)
    if f < 1:
        raise ValueError(f"frequency: expected >= 1, got {frequency}")
    corners = _ICOSAHEDRON_VERTICES / np.linalg.norm(_ICOSAHEDRON_VERTICES, axis=1, keepdims=True)
    points = []
    faces = []
    offset = 0
    # Per face a triangular grid (i, j), i + j <= f: point = a + (b - a) i/f + (c - a) j/f.
    grid = [(i, j) for j in range(f + 1) for i in range(f + 1 - j)]
    index = {ij: k for k, ij in enumerate(grid)}
    local = []
    for j in range(f):
        for i in range(f - j):
            local.append((index[(i, j)], index[(i + 1, j)], index[(i, j + 1)]))
            if i + j + 1 < f:
                local.append((index[(i + 1, j)], index[(i + 1, j + 1)], index[(i, j + 1)]))
    local = np.array(local, dtype=np.int64)
    ij = np.array(grid, dtype=np.float64)
    for a, b, c in _ICOSAHEDRON_FACES:
        pa, pb, pc = corners[a], corners[b], corners[c]
        pts = pa + np.outer(ij[:, 0] / f, pb - pa) + np.outer(ij[:, 1] / f, pc - pa)
        points.append(pts)
        faces.append(local + offset)
        offset += len(pts)
    points = np.concatenate(points)
    faces = np.concatenate(faces)
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    # Shared edge/corner points are generated once per face: merge them (they are equal up to
    # rounding, and distinct points are at least ~1/(2 f) apart).
    keys = np.round(points * 1e9).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    vertices = points[first]
    faces = inverse[faces]
    vertices = vertices * float(radius) + np.asarray(center, dtype=np.float64)
    return vertices, faces


def body_like(frequency: int = 37):
    """A body-sized watertight mesh: an icosphere stretched to semi-axes (0.2, 0.85, 0.13) m,
    centred at (0, 0.85, 0), so it stands on y = 0 and its "scalp" is the cap around y = 1.7.

    Returns:
        (vertices (10 f^2 + 2, 3) float64, faces (20 f^2, 3) int64).
    """
    vertices, faces = icosphere(frequency)
    vertices = vertices * np.array(BODY_LIKE_SEMI_AXES) + np.array(BODY_LIKE_CENTER)
    return vertices, faces


def open_cap(vertices, faces, axis: int = 1, above: float = 0.0):
    """The faces whose every vertex has coordinate `axis` > `above`: an open (non-watertight)
    mesh for bad-input tests. Vertices are kept as they are (unused ones included)."""
    keep = (vertices[faces][:, :, axis] > above).all(axis=1)
    return vertices, faces[keep]


def hair_on_cap(
    vertices, center, num_strands: int, num_vertices: int, length: float, rng, jitter: float = 0.002
):
    """Hair-like polylines rooted on mesh vertices near the top, growing outward then falling
    with gravity. Each strand leaves along a randomly tilted direction and carries a small
    per-vertex jitter, so some vertices graze or enter the surface.

    Args:
        vertices: (V, 3) mesh vertices [m]; roots are picked among those with the largest y.
        center: a point inside the mesh [m]: strands leave roughly along root - center.
        num_strands: M.
        num_vertices: N per strand.
        length: strand arc length before jitter [m].
        rng: numpy Generator.
        jitter: standard deviation of the per-vertex jitter [m] (vertices 0 and 1 excepted).

    Returns:
        (hair (M, N, 3) float64, roots (M, 3) float64, arc lengths (M,) float64 [m]).
    """
    order = np.argsort(-vertices[:, 1])
    candidates = order[: max(num_strands * 2, 8)]
    roots = vertices[rng.choice(candidates, size=num_strands, replace=len(candidates) < num_strands)]
    out = roots - np.asarray(center, dtype=np.float64)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out += rng.normal(scale=0.5, size=out.shape)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    seg = length / max(num_vertices - 1, 1)
    hair = np.empty((num_strands, num_vertices, 3))
    hair[:, 0] = roots
    down = np.array([0.0, -1.0, 0.0])
    for v in range(1, num_vertices):
        t = min(1.0, 3.0 * v / max(num_vertices - 1, 1))
        d = (1.0 - t) * out + t * down
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hair[:, v] = hair[:, v - 1] + seg * d
    hair[:, 2:] += rng.normal(scale=jitter, size=hair[:, 2:].shape)
    arc = np.linalg.norm(np.diff(hair, axis=1), axis=2).sum(axis=1)
    return hair, roots, arc


def push_outside_ellipsoid(points, center=BODY_LIKE_CENTER, semi_axes=BODY_LIKE_SEMI_AXES, clearance=1.02):
    """Move points that lie inside the ellipsoid scaled by `clearance` radially onto it
    (in the ellipsoid's normalised coordinates), so draped hair rests outside `body_like`.
    Returns a new array; points outside are unchanged."""
    center = np.asarray(center, dtype=np.float64)
    axes = np.asarray(semi_axes, dtype=np.float64)
    q = (np.asarray(points, dtype=np.float64) - center) / axes
    r = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(r < clearance, q / np.maximum(r, 1e-12) * clearance, q)
    return q * axes + center
