"""Independent float64 references for rotations, forward kinematics and the motion descriptors
of Section 3.3.1, written frame by frame and joint by joint."""

import math

import numpy as np

PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)


def rodrigues(aa):
    aa = np.asarray(aa, dtype=np.float64)
    th = float(np.linalg.norm(aa))
    if th < 1e-15:
        return np.eye(3)
    k = aa / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def log_rotation(R):
    """Rotation vector of R (angle < pi)."""
    c = (np.trace(R) - 1) / 2
    th = math.acos(min(1.0, max(-1.0, c)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    if th < 1e-12:
        return v
    return v * th / math.sin(th)


def quat_from_aa(aa):
    th = float(np.linalg.norm(aa))
    if th < 1e-15:
        return np.array([1.0, 0, 0, 0])
    return np.concatenate([[math.cos(th / 2)], math.sin(th / 2) * np.asarray(aa) / th])


def slerp_aa(a0, a1, w):
    """Axis-angle of the rotation a fraction w of the way from R(a0) to R(a1)."""
    R0, R1 = rodrigues(a0), rodrigues(a1)
    step = log_rotation(R0.T @ R1)
    return log_rotation(R0 @ rodrigues(w * step))


def local_joint_positions(pose66, rest):
    """Joint positions in the root frame (root rotation left out), one joint at a time."""
    R = [rodrigues(pose66[3 * j:3 * j + 3]) for j in range(22)]
    G = [np.eye(3)] + [None] * 21
    x = [np.zeros(3)] + [None] * 21
    for j in range(1, 22):
        p = PARENTS[j]
        x[j] = x[p] + G[p] @ (rest[j] - rest[p])
        G[j] = G[p] @ R[j]
    return np.array(x)


def world_joint_positions(pose66, rest):
    R0 = rodrigues(pose66[:3])
    return (local_joint_positions(pose66, rest) @ R0.T)


def frame_descriptor(poses, t, betas, dt, rest):
    """m^(t): joint angular velocities, gravity-direction velocity, joint accelerations, beta."""
    T = len(poses)
    i1, i2 = max(t - 1, 0), max(t - 2, 0)
    omega = []
    for j in range(22):
        Ra = rodrigues(poses[i1][3 * j:3 * j + 3])
        Rb = rodrigues(poses[t][3 * j:3 * j + 3])
        omega.append(log_rotation(Ra.T @ Rb) / dt)
    g = lambda k: rodrigues(poses[k][:3]).T @ np.array([0.0, -1.0, 0.0])  # noqa: E731
    gvel = (g(t) - g(i1)) / dt
    x0 = local_joint_positions(poses[t], rest)
    x1 = local_joint_positions(poses[i1], rest)
    x2 = local_joint_positions(poses[i2], rest)
    acc = (x0 - 2 * x1 + x2)[1:] / dt**2
    assert T > t
    return np.concatenate([np.concatenate(omega), gvel, acc.reshape(-1), betas])
