"""Rotations, in one module: axis-angle (SMPL's pose convention), matrices, interpolation.

The torch side (`axis_angle_to_matrix`, `matrix_to_axis_angle`, `rigid_transform`, ...) is
batched and differentiable and runs where the body and the networks run. The numpy side
(`np_*`, `compose_axis_angles`, `slerp_axis_angles`, `euler_to_axis_angle`) is float64 on the
CPU for building motions and poses, and is scipy's `Rotation` underneath.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

# Below this angle [rad] the Rodrigues coefficients switch to their Taylor series: sin(t)/t
# and (1 - cos t)/t^2 lose digits to cancellation near 0 and their autograd gives NaN at 0.
_SMALL_ANGLE = 1e-4


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from axis-angle vectors (Rodrigues' formula).

    Args:
        axis_angle: (..., 3) rotation vectors: unit axis times angle [rad].

    Returns:
        (..., 3, 3) rotation matrices of the same dtype and device; finite gradients
        everywhere, the zero vector included.
    """
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)
    small = theta2 < _SMALL_ANGLE**2
    # Keep the sqrt argument away from 0 on the branch that is not used (its NaN gradient
    # would leak through torch.where otherwise).
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)  # sin(t)/t
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta * theta))  # (1-cos t)/t^2
    k = skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) cross-product matrices [v]_x of vectors v (..., 3)."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors (..., 3) of rotation matrices (..., 3, 3), angles in [0, pi].

    Not differentiated anywhere in hairwarp (used to read poses back). Within 1e-4 of angle
    pi the axis comes from the symmetric part (the rotation is then exact up to the sign
    ambiguity at pi itself, where both signs are the same rotation).
    """
    trace = matrix[..., 0, 0] + matrix[..., 1, 1] + matrix[..., 2, 2]
    cos = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0)
    vee = torch.stack(
        [
            matrix[..., 2, 1] - matrix[..., 1, 2],
            matrix[..., 0, 2] - matrix[..., 2, 0],
            matrix[..., 1, 0] - matrix[..., 0, 1],
        ],
        -1,
    )
    # atan2(sin, cos) rather than acos(cos): acos loses half the digits at small angles (the
    # frame-to-frame steps of the motion descriptors are such angles).
    sin = 0.5 * torch.linalg.vector_norm(vee, dim=-1)
    angle = torch.atan2(sin, cos)
    scale = torch.where(sin > 1e-12, angle / (2.0 * sin.clamp_min(1e-12)), torch.full_like(sin, 0.5))
    out = vee * scale[..., None]
    # Near pi the antisymmetric part vanishes: the axis a comes from the symmetric part,
    # (R + R^T) / 2 - cos(t) I = (1 - cos t) a a^T, as its column of largest norm.
    # Computed for every matrix, no test read back: the function runs inside CUDA graphs (the
    # networks' heading, `hairwarp.models.heading`).
    near_pi = (sin < 1e-4) & (cos < 0)
    eye = torch.eye(3, dtype=matrix.dtype, device=matrix.device)
    sym = (matrix + matrix.transpose(-1, -2)) / 2 - cos[..., None, None] * eye
    col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)
    axis = torch.gather(sym, -1, col[..., None, None].expand(*col.shape, 3, 1))[..., 0]
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # Sign: agree with the antisymmetric part where it is not exactly zero.
    sign = torch.where((axis * vee).sum(-1) < 0, -1.0, 1.0).to(matrix.dtype)
    return torch.where(near_pi[..., None], axis * (sign * angle)[..., None], out)


def rigid_transform(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) homogeneous transforms from rotations (..., 3, 3) and translations (..., 3)."""
    top = torch.cat([rotation, translation[..., None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (..., 4, 4) transforms to points (..., P, 3): R p + t, broadcasting the leading dims."""
    return points @ transform[..., :3, :3].transpose(-1, -2) + transform[..., None, :3, 3]


# ----------------------------------------------------------------------------- numpy side


def np_axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of axis-angle vectors (..., 3) [rad], float64."""
    aa = np.asarray(axis_angle, dtype=np.float64)
    return Rotation.from_rotvec(aa.reshape(-1, 3)).as_matrix().reshape(aa.shape[:-1] + (3, 3))


def np_matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """Axis-angle vectors (..., 3) [rad], angles in [0, pi], of rotation matrices (..., 3, 3)."""
    m = np.asarray(matrix, dtype=np.float64)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(m.shape[:-2] + (3,))


def compose_axis_angles(*axis_angles: np.ndarray) -> np.ndarray:
    """Axis-angle of R(a_0) R(a_1) ... (the last one applied first), broadcast over (..., 3)."""
    arrays = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in axis_angles])
    shape = arrays[0].shape
    r = Rotation.from_rotvec(arrays[0].reshape(-1, 3))
    for a in arrays[1:]:
        r = r * Rotation.from_rotvec(a.reshape(-1, 3))
    return r.as_rotvec().reshape(shape)


def slerp_axis_angles(a0: np.ndarray, a1: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Spherical interpolation, the short way round, between rotations a0 and a1 (..., 3).

    Args:
        a0, a1: axis-angle vectors (..., 3) [rad] of the same shape.
        weight: (...) interpolation weights in [0, 1] (0: a0, 1: a1).

    Returns:
        (..., 3) axis-angle vectors of R(a0) exp(w log(R(a0)^T R(a1))).
    """
    a0 = np.asarray(a0, dtype=np.float64)
    shape = a0.shape
    r0 = Rotation.from_rotvec(a0.reshape(-1, 3))
    r1 = Rotation.from_rotvec(np.asarray(a1, dtype=np.float64).reshape(-1, 3))
    w = np.broadcast_to(np.asarray(weight, dtype=np.float64), shape[:-1]).reshape(-1, 1)
    step = (r0.inv() * r1).as_rotvec()  # in [0, pi]: the shorter arc
    return (r0 * Rotation.from_rotvec(step * w)).as_rotvec().reshape(shape)


def euler_to_axis_angle(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Axis-angle vector (3,) of R = Rz(roll) Ry(yaw) Rx(pitch), angles in degrees."""
    return Rotation.from_euler("ZYX", [roll, yaw, pitch], degrees=True).as_rotvec()
