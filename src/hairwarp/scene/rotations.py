"""Axis-angle rotations in plain torch (SMPL's pose convention), batched and differentiable."""

from __future__ import annotations

import torch

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
    angle = torch.acos(cos)
    vee = torch.stack(
        [
            matrix[..., 2, 1] - matrix[..., 1, 2],
            matrix[..., 0, 2] - matrix[..., 2, 0],
            matrix[..., 1, 0] - matrix[..., 0, 1],
        ],
        -1,
    )
    sin = torch.sin(angle)
    out = torch.where(
        (sin > 1e-6)[..., None], vee * (angle / (2.0 * sin.clamp_min(1e-12)))[..., None], 0.5 * vee
    )
    # Near pi the antisymmetric part vanishes: the axis a comes from the symmetric part,
    # (R + R^T) / 2 - cos(t) I = (1 - cos t) a a^T, as its column of largest norm.
    near_pi = (sin < 1e-4) & (cos < 0)
    if bool(near_pi.any()):
        eye = torch.eye(3, dtype=matrix.dtype, device=matrix.device)
        sym = (matrix + matrix.transpose(-1, -2)) / 2 - cos[..., None, None] * eye
        col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)
        axis = torch.gather(sym, -1, col[..., None, None].expand(*col.shape, 3, 1))[..., 0]
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        # Sign: agree with the antisymmetric part where it is not exactly zero.
        sign = torch.where((axis * vee).sum(-1) < 0, -1.0, 1.0).to(matrix.dtype)
        out = torch.where(near_pi[..., None], axis * (sign * angle)[..., None], out)
    return out


def rigid_transform(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) homogeneous transforms from rotations (..., 3, 3) and translations (..., 3)."""
    top = torch.cat([rotation, translation[..., None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (..., 4, 4) transforms to points (..., P, 3): R p + t, broadcasting the leading dims."""
    return points @ transform[..., :3, :3].transpose(-1, -2) + transform[..., None, :3, 3]
