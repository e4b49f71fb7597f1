"""Float64 references of the guide frames and the follower interpolation, one vertex at a time,
written from the formulas in `hairwarp.kernels.guide_interpolation` with rotation matrices
(the kernels use quaternions).
"""

import numpy as np


def rotation_between(a, b):
    """The minimal rotation matrix taking unit vector a to unit vector b (Rodrigues)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    v = np.cross(a, b)
    c = float(a @ b)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def unit(v):
    return v / np.linalg.norm(v)


def guide_frame_rotations(rest, now, head_rotation, window=4):
    """(K, N-1, 3, 3) R_i = F_i F0_i^T of one frame: rest (K, N, 3), now (K, N, 3), head (3, 3);
    segment i >= 1 read as the chord from vertex i - window to i + 1 + window (clamped)."""
    k, n = rest.shape[:2]
    out = np.zeros((k, n - 1, 3, 3))
    for g in range(k):
        t0 = unit(rest[g, 1] - rest[g, 0])
        t = unit(now[g, 1] - now[g, 0])
        r = rotation_between(head_rotation @ t0, t) @ head_rotation
        out[g, 0] = r
        for i in range(1, n - 1):
            lo, hi = max(i - window, 0), min(i + 1 + window, n - 1)
            t0n = unit(rest[g, hi] - rest[g, lo])
            tn = unit(now[g, hi] - now[g, lo])
            r = rotation_between(t, tn) @ r @ rotation_between(t0, t0n).T
            out[g, i] = r
            t0, t = t0n, tn
    return out


def interpolate_followers(rest, now, rotations, followers_rest, follower_guides, weights, ratios,
                          fixed_vertices=2):
    """(M, N, 3) followers of one frame, vertex by vertex."""
    m, n = followers_rest.shape[:2]
    out = np.zeros((m, n, 3))
    for f in range(m):
        for i in range(n):
            x = np.zeros(3)
            for j in range(follower_guides.shape[1]):
                w = weights[f, j]
                if w == 0:
                    continue
                g = follower_guides[f, j]
                u = i * ratios[f, j]
                i0 = 0 if i < fixed_vertices else min(max(int(np.floor(u)), 0), n - 2)
                a = u - i0
                p0 = rest[g, i0] + a * (rest[g, i0 + 1] - rest[g, i0])
                p = now[g, i0] + a * (now[g, i0 + 1] - now[g, i0])
                x += w * (p + rotations[g, i0] @ (followers_rest[f, i] - p0))
            out[f, i] = x
    return out
