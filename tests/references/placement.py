"""numpy float64 references of the rigid hair placement (HairFormer Section 3.1.1, Eq. 1).

    p_rigid[s, v] = M_head p_init[s, v] + dt_align + dt[s, 0]
    dt_align = mean_{i in head} (V_body[i] - M_head V0_head[i])
    dt[s, 0] = closest point of the posed body surface to (M_head p_init[s, 0] + dt_align)
               minus that point

and an exact point-triangle distance written differently from the library's (projection
onto the plane when it falls inside, else the nearest of the three edges), brute force over
every triangle.
"""

from __future__ import annotations

import numpy as np


def _point_segment(p, a, b):
    """Closest points (..., 3) of segments a-b to points p."""
    e = b - a
    t = np.clip(np.sum((p - a) * e, -1) / np.maximum(np.sum(e * e, -1), 1e-300), 0.0, 1.0)
    return a + t[..., None] * e


def closest_points_on_triangles(p, a, b, c):
    """Closest points (..., 3) of triangles (a, b, c) to points p, broadcast together."""
    n = np.cross(b - a, c - a)
    nn = np.sum(n * n, -1)
    q_plane = p - (np.sum((p - a) * n, -1) / nn)[..., None] * n
    # Inside test by signed areas of the sub-triangles (all agree with the normal).
    inside = (
        (np.sum(np.cross(b - a, q_plane - a) * n, -1) >= 0)
        & (np.sum(np.cross(c - b, q_plane - b) * n, -1) >= 0)
        & (np.sum(np.cross(a - c, q_plane - c) * n, -1) >= 0)
    )
    edges = np.stack([_point_segment(p, a, b), _point_segment(p, b, c), _point_segment(p, c, a)], 0)
    d_edges = np.linalg.norm(edges - p[None], axis=-1)
    best_edge = np.take_along_axis(edges, np.argmin(d_edges, 0)[None, ..., None], 0)[0]
    return np.where(inside[..., None], q_plane, best_edge)


def closest_point_on_mesh(points, vertices, faces):
    """Closest points (P, 3) on a triangle mesh and the distances (P,), brute force."""
    tri = vertices[faces]
    out = np.empty_like(points)
    dist = np.empty(points.shape[0])
    for i, p in enumerate(points):
        q = closest_points_on_triangles(p[None], tri[:, 0], tri[:, 1], tri[:, 2])
        d = np.linalg.norm(q - p, axis=-1)
        k = int(np.argmin(d))
        out[i], dist[i] = q[k], d[k]
    return out, dist


def rigid_placement(strands, posed_vertices, head_transform, rest_vertices, head_ids, faces):
    """Eq. 1 for one frame.

    Args:
        strands: (M, N, 3) rest-pose strands.
        posed_vertices: (V, 3) posed body.
        head_transform: (4, 4) M_head.
        rest_vertices: (V, 3) rest body.
        head_ids: (H,) head-region vertices.
        faces: (F, 3) triangles searched for the root projection.

    Returns:
        (positions (M, N, 3), dt_align (3,), root offsets (M, 3)).
    """
    r, t = head_transform[:3, :3], head_transform[:3, 3]
    align = np.mean(posed_vertices[head_ids] - (rest_vertices[head_ids] @ r.T + t), axis=0)
    moved = strands @ r.T + t + align
    surface, _ = closest_point_on_mesh(moved[:, 0], posed_vertices, faces)
    offsets = surface - moved[:, 0]
    return moved + offsets[:, None], align, offsets
