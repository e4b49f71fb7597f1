"""The body's heading taken out before a network and put back after it.

Hair draping is the same physics whichever way the body faces: turning the body, its hair and
the gravity-free horizontal plane about the vertical (y) turns the drape with them. The networks
read the root orientation (theta[:3]) as it is, and training poses face +z: a body facing
another way (an AMASS motion's, say) gets another drape, up to twice the rigid placement's
penetration when it faces -z (docs/characters.md, "Foreign files, measured"). So the methods
turn each input to face +z (the root's yaw about y removed from theta, the contact features'
vectors turned with it), run the network, and turn its deformation map back: the drape is
then equivariant to the heading by construction.

Yaw of a root rotation R: the angle about +y of its facing direction R e_z, projected on the
horizontal plane, atan2(f_x, f_z) (0 for a body facing +z). A body facing straight up or down
has no heading (any yaw leaves it facing there): the projection is then 0 and so is the yaw.
"""

from __future__ import annotations

import torch

from hairwarp.scene.rotations import axis_angle_to_matrix, matrix_to_axis_angle

# Contact features per sample: signed distance (1), push-out vector (3), offset from root (3).
_VECTOR_SLICES = ((1, 4), (4, 7))


def yaw_rotation(angle: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations by `angle` (...,) [rad] about +y."""
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1).reshape(*angle.shape, 3, 3)


def heading(theta: torch.Tensor) -> torch.Tensor:
    """Yaw [rad] of the root orientation of (..., 66) (or (..., >= 3)) axis-angle poses: (...,)."""
    facing = axis_angle_to_matrix(theta[..., :3])[..., :, 2]  # R e_z
    return torch.atan2(facing[..., 0], facing[..., 2])


def turn_pose(theta: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Theta with its root orientation turned by `angle` (broadcast over theta's batch) about +y."""
    root = yaw_rotation(angle).to(theta.dtype) @ axis_angle_to_matrix(theta[..., :3])
    return torch.cat([matrix_to_axis_angle(root), theta[..., 3:]], dim=-1)


def turn_vectors(vectors: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(B, ..., 3) vectors turned by `angle` (B,) [rad] about +y."""
    r = yaw_rotation(angle).to(vectors.dtype)
    shape = vectors.shape
    flat = vectors.reshape(shape[0], -1, 3)
    return (flat @ r.transpose(-1, -2)).reshape(shape)


def turn_contact_features(contact: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(B, ..., 7 K) contact features (`hairwarp.models.contact_features`) with their push-out
    and offset vectors turned by `angle` (B,) about +y (the distances are unchanged).
    """
    shape = contact.shape
    per_sample = contact.reshape(shape[0], -1, 7)
    parts = [per_sample[..., :1]] + [turn_vectors(per_sample[..., a:b].contiguous(), angle) for a, b in _VECTOR_SLICES]
    return torch.cat(parts, dim=-1).reshape(shape)


__all__ = ["heading", "turn_contact_features", "turn_pose", "turn_vectors", "yaw_rotation"]
