"""The heading taken out before the networks (`hairwarp.models.heading`): yaw of a root
orientation, poses and contact features turned about +y, and the methods' drapes equivariant
to the body's heading (static and dynamic networks, the shipped checkpoint)."""

import math

import torch

from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors, yaw_rotation
from hairwarp.scene.rotations import axis_angle_to_matrix


def _poses(rng, b=6):
    theta = torch.tensor(rng.normal(scale=0.4, size=(b, 66)))
    theta[:, :3] = torch.tensor(rng.normal(scale=1.2, size=(b, 3)))  # any root orientation
    return theta


def _wrap(a):
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def test_turning_a_pose_adds_to_its_heading_and_keeps_the_joints(rng):
    theta = _poses(rng)
    angle = torch.tensor(rng.uniform(-3.0, 3.0, size=theta.shape[0]))
    turned = turn_pose(theta, angle)
    torch.testing.assert_close(_wrap(heading(turned) - heading(theta) - angle), torch.zeros_like(angle),
                               rtol=0, atol=1e-9)
    assert torch.equal(turned[:, 3:], theta[:, 3:])
    # The turned root is the yaw rotation times the root: the same rotation matrices.
    torch.testing.assert_close(axis_angle_to_matrix(turned[:, :3]),
                               yaw_rotation(angle) @ axis_angle_to_matrix(theta[:, :3]), rtol=0, atol=1e-9)
    canonical = turn_pose(theta, -heading(theta))
    torch.testing.assert_close(heading(canonical), torch.zeros_like(angle), rtol=0, atol=1e-9)
    # A body facing +z has heading 0; facing +x, pi / 2.
    facing_x = torch.zeros(1, 66, dtype=torch.float64)
    facing_x[0, 1] = math.pi / 2
    assert abs(float(heading(facing_x)) - math.pi / 2) < 1e-12 and float(heading(torch.zeros(1, 66))) == 0.0


def test_turning_contact_features_turns_their_vectors_only(rng):
    b, cells, samples = 3, 5, 4
    contact = torch.tensor(rng.normal(size=(b, cells, 7 * samples)))
    angle = torch.tensor([0.3, -2.0, math.pi], dtype=torch.float64)
    turned = turn_contact_features(contact, angle).reshape(b, cells, samples, 7)
    per = contact.reshape(b, cells, samples, 7)
    assert torch.equal(turned[..., 0], per[..., 0])  # signed distances
    r = yaw_rotation(angle)
    for a, c in ((1, 4), (4, 7)):
        expected = torch.einsum("bij,bcsj->bcsi", r, per[..., a:c])
        torch.testing.assert_close(turned[..., a:c], expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(turn_vectors(turn_vectors(per[..., 1:4].contiguous(), angle), -angle), per[..., 1:4],
                               rtol=0, atol=1e-12)


def test_heading_runs_inside_a_graph_without_a_host_read(rng):
    """No data-dependent branch on the host: the drape's CUDA graph captures it (CUDA only for
    capture; here the near-pi rotation path is checked to need no branch)."""
    theta = torch.zeros(2, 66, dtype=torch.float64)
    theta[0, 1] = math.pi  # facing -z: the root's axis-angle near pi
    canonical = turn_pose(theta, -heading(theta))
    torch.testing.assert_close(heading(canonical), torch.zeros(2, dtype=torch.float64), rtol=0, atol=1e-9)
    torch.testing.assert_close(axis_angle_to_matrix(canonical[:, :3]), torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
                               rtol=0, atol=1e-9)
