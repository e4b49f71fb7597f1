"""numpy float64 reference of SMPL's forward pass (Loper et al. 2015; HairFormer Section 3.1).

Written loop by loop from the model's definition, independently of `hairwarp.scene.smpl`:

    v_shaped = T + S beta,     J = J_regressor v_shaped
    v_posed  = v_shaped + P (vec(R_1 .. R_{J-1}) - vec(I))
    G_0 = [R_0 | J_0],         G_k = G_parent(k) [R_k | J_k - J_parent(k)]
    A_k = G_k [I | -J_k],      v_i = sum_k w_ik A_k [v_posed_i; 1] + trans
"""

from __future__ import annotations

import numpy as np


def rodrigues(axis_angle):
    """Rotation matrix (3, 3) of one axis-angle vector: cos t I + sin t [k] + (1 - cos t) k k^T."""
    axis_angle = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(axis_angle)
    if angle == 0.0:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.cos(angle) * np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * np.outer(k, k)


def homogeneous(rotation, translation):
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def smpl_forward(arrays: dict, betas, pose, trans=None):
    """One frame of SMPL.

    Args:
        arrays: the model's arrays (v_template, shapedirs, posedirs optional, J_regressor,
            kintree_table, weights), J joints.
        betas: (K',) shape coefficients, K' <= K.
        pose: (22, 3) axis-angle rotations of the first 22 joints; the others identity.
        trans: (3,) translation or None.

    Returns:
        (vertices (V, 3), joint world transforms G (J, 4, 4), skinning transforms A (J, 4, 4)).
    """
    t = np.asarray(arrays["v_template"], dtype=np.float64)
    s = np.asarray(arrays["shapedirs"], dtype=np.float64)[:, :, : len(betas)]
    regressor = np.asarray(arrays["J_regressor"], dtype=np.float64)
    weights = np.asarray(arrays["weights"], dtype=np.float64)
    parents = [int(p) for p in np.asarray(arrays["kintree_table"])[0]]
    num_joints = len(parents)
    v_shaped = t + s @ np.asarray(betas, dtype=np.float64)
    joints = regressor @ v_shaped
    rotations = [rodrigues(pose[k]) if k < 22 else np.eye(3) for k in range(num_joints)]
    v_posed = v_shaped.copy()
    if arrays.get("posedirs") is not None:
        feature = np.concatenate([(rotations[k] - np.eye(3)).ravel() for k in range(1, num_joints)])
        v_posed = v_posed + np.asarray(arrays["posedirs"], dtype=np.float64) @ feature
    world = []
    for k in range(num_joints):
        if k == 0:
            world.append(homogeneous(rotations[0], joints[0]))
        else:
            p = parents[k]
            world.append(world[p] @ homogeneous(rotations[k], joints[k] - joints[p]))
    skin = [g @ homogeneous(np.eye(3), -joints[k]) for k, g in enumerate(world)]
    vertices = np.zeros_like(v_posed)
    for i in range(v_posed.shape[0]):
        blended = sum(weights[i, k] * skin[k] for k in range(num_joints))
        vertices[i] = (blended @ np.append(v_posed[i], 1.0))[:3]
    world = np.stack(world)
    skin = np.stack(skin)
    if trans is not None:
        vertices = vertices + trans
        world[:, :3, 3] += trans
        skin[:, :3, 3] += trans
    return vertices, world, skin
