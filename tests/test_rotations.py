"""The one rotation module: torch (differentiable) and numpy (scipy) sides against Rodrigues."""

import math

import numpy as np
import torch

from hairwarp.scene import rotations as rot
from references import motion as ref

# Rotation conversions in float64.
_ROT_TOL = 1e-10


def _cases(rng):
    aa = rng.normal(size=(50, 3)) * rng.uniform(0, 3, size=(50, 1))
    aa[0] = 0.0
    aa[1] = [1e-9, 0, 0]
    return aa


def test_numpy_and_torch_match_rodrigues(rng):
    aa = _cases(rng)
    m = rot.np_axis_angle_to_matrix(aa)
    assert m.shape == (50, 3, 3)
    for a, r in zip(aa, m):
        np.testing.assert_allclose(r, ref.rodrigues(a), atol=_ROT_TOL)
    torch_m = rot.axis_angle_to_matrix(torch.tensor(aa))
    np.testing.assert_allclose(torch_m.numpy(), m, atol=_ROT_TOL)
    back_np = rot.np_matrix_to_axis_angle(m)
    back_torch = rot.matrix_to_axis_angle(torch.tensor(m)).numpy()
    np.testing.assert_allclose(rot.np_axis_angle_to_matrix(back_np), m, atol=_ROT_TOL)
    np.testing.assert_allclose(back_torch, back_np, atol=1e-9)


def test_small_angles_keep_their_digits():
    # acos-based logs lose half the digits here; the frame-to-frame steps of a motion are such angles.
    aa = np.array([[1e-6, -2e-6, 3e-7], [0.0, 1e-4, 0.0]])
    m = rot.axis_angle_to_matrix(torch.tensor(aa))
    back = rot.matrix_to_axis_angle(m).numpy()
    np.testing.assert_allclose(back, aa, rtol=1e-8, atol=1e-15)


def test_near_pi_round_trips():
    near_pi = np.array([[math.pi - 1e-7, 0, 0], [0, 0, math.pi], [2.0, 2.0, 0.5]])
    m = rot.np_axis_angle_to_matrix(near_pi)
    np.testing.assert_allclose(rot.np_axis_angle_to_matrix(rot.np_matrix_to_axis_angle(m)), m, atol=1e-9)
    back = rot.matrix_to_axis_angle(torch.tensor(m))
    np.testing.assert_allclose(rot.axis_angle_to_matrix(back).numpy(), m, atol=1e-9)


def test_slerp_matches_reference(rng):
    a0, a1 = rng.normal(size=(2, 20, 3)) * 0.8
    w = rng.uniform(size=20)
    got = rot.np_axis_angle_to_matrix(rot.slerp_axis_angles(a0, a1, w))
    for i in range(20):
        np.testing.assert_allclose(got[i], ref.rodrigues(ref.slerp_aa(a0[i], a1[i], w[i])), atol=1e-9)
    np.testing.assert_allclose(rot.slerp_axis_angles(a0, a1, np.zeros(20)), a0, atol=1e-12)


def test_compose_and_euler():
    a = np.array([0.3, 0.0, 0.0])
    b = np.array([0.0, 0.5, 0.0])
    m = rot.np_axis_angle_to_matrix(rot.compose_axis_angles(a, b))
    np.testing.assert_allclose(m, ref.rodrigues(a) @ ref.rodrigues(b), atol=_ROT_TOL)
    pitch, yaw, roll = 10.0, -20.0, 5.0
    rx, ry, rz = (ref.rodrigues(np.radians(v) * e) for v, e in
                  ((pitch, np.eye(3)[0]), (yaw, np.eye(3)[1]), (roll, np.eye(3)[2])))
    np.testing.assert_allclose(rot.np_axis_angle_to_matrix(rot.euler_to_axis_angle(pitch, yaw, roll)),
                               rz @ ry @ rx, atol=_ROT_TOL)


def test_axis_angle_gradient_is_finite_at_zero():
    aa = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    rot.axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
    torch.autograd.gradcheck(rot.axis_angle_to_matrix, (torch.tensor([[0.3, -0.2, 0.9]], dtype=torch.float64,
                                                                      requires_grad=True),))
