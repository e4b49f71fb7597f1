"""Motions: procedural motions, the AMASS loader, resampling, dynamic score, descriptors."""

import math

import numpy as np
import pytest
import torch

from hairwarp.scene import motion as mo
from hairwarp.scene.motion import (
    DESCRIPTOR_DIM, DESCRIPTOR_SLICES, JOINT, REST_JOINTS, Motion, dynamic_score, filter_dynamic,
    frame_descriptors, list_motions, load_amass, motion_descriptor_windows, motion_descriptors,
    procedural_motion, resample_motion, subsample_motion,
)
from references import motion as ref

# Rotation conversions in float64 through matrices / quaternions.
_ROT_TOL = 1e-10
# Motions are stored as float32.
_F32_TOL = 2e-6
# Descriptors in float64 against the frame-by-frame reference: finite differences of
# quantities of order 1 divided by dt^2 = 1/3600 amplify rounding ~4e3 times.
_DESC_TOL = 1e-8
DT = 1.0 / 60.0


def _world(pose):
    return ref.world_joint_positions(np.asarray(pose, dtype=np.float64), REST_JOINTS)


# ------------------------------------------------------------------ procedural motions


@pytest.mark.parametrize("name", list_motions())
def test_procedural_motion_shapes_and_determinism(name):
    m = procedural_motion(name)
    assert isinstance(m, Motion) and m.fps == 60.0 and m.name == name
    assert m.poses.shape == (m.num_frames, 66) and m.poses.dtype == torch.float32
    assert m.trans.shape == (m.num_frames, 3) and m.betas.shape == (16,)
    assert m.num_frames >= 3 * 60
    assert torch.isfinite(m.poses).all() and torch.isfinite(m.trans).all()
    assert dynamic_score(m) > 0.02  # mean over 22 joints: a head-only motion scores low
    assert torch.equal(procedural_motion(name, seed=5).poses, procedural_motion(name, seed=5).poses)
    assert not torch.equal(procedural_motion(name, seed=5).poses, procedural_motion(name, seed=6).poses)
    short = procedural_motion(name, duration=0.5)
    assert short.num_frames == 31
    # Starts from rest: hair can be draped statically on frame 0.
    v0 = (m.poses[1] - m.poses[0]).abs().max()
    assert float(v0) < 0.02


def test_procedural_motion_bad_input():
    with pytest.raises(ValueError, match="name"):
        procedural_motion("moonwalk")
    with pytest.raises(ValueError, match="duration"):
        procedural_motion("nod", duration=-1.0)


def test_head_turn_is_a_yaw_of_neck_and_head():
    m = procedural_motion("head_turn").poses.double().numpy().reshape(-1, 22, 3)
    for j in (JOINT["neck"], JOINT["head"]):
        assert np.abs(m[:, j, 1]).max() > 0.2
        np.testing.assert_array_equal(m[:, j, [0, 2]], 0.0)
    total = m[:, JOINT["neck"], 1] + m[:, JOINT["head"], 1]
    assert math.radians(55) < np.abs(total).max() < math.radians(65)


def test_whiplash_stops_abruptly():
    m = procedural_motion("whiplash")
    poses = m.poses.double().numpy()
    yaw = poses[:, 3 * JOINT["head"] + 1] + poses[:, 3 * JOINT["neck"] + 1]
    speed = np.abs(np.diff(yaw)) * m.fps
    k = int(np.argmax(speed))
    assert speed[k] > 8.0  # rad/s, a violent turn
    assert speed[k + 1] < 0.05 * speed[k]  # and a stop within one frame


def test_torso_bend_moves_the_head_forward_and_down():
    m = procedural_motion("torso_bend")
    poses = m.poses.double().numpy()
    head = np.array([_world(p)[JOINT["head"]] for p in poses])
    k = int(np.argmax(head[:, 2]))
    assert head[k, 2] - head[0, 2] > 0.3  # forward [m]
    assert head[0, 1] - head[k, 1] > 0.2  # and down
    # The legs stay vertical: the ankles hardly move.
    ankle = np.array([_world(p)[JOINT["left_ankle"]] for p in poses[[0, k]]])
    assert np.linalg.norm(ankle[1] - ankle[0]) < 0.3 * np.linalg.norm(head[k] - head[0])


def test_arm_raise_lifts_wrists_above_the_head():
    poses = procedural_motion("arm_raise").poses.double().numpy()
    w0 = _world(poses[0])
    top = max(range(len(poses)), key=lambda i: _world(poses[i])[JOINT["left_wrist"], 1])
    w = _world(poses[top])
    assert w0[JOINT["left_wrist"], 1] < w0[JOINT["pelvis"], 1] + 0.25  # at rest: arms down
    for j in ("left_wrist", "right_wrist"):
        assert w[JOINT[j], 1] > w[JOINT["head"], 1]


def test_sway_walk_moves_forward():
    m = procedural_motion("sway_walk")
    tr = m.trans.double().numpy()
    assert tr[-1, 2] > 2.0 and abs(tr[-1, 1]) < 0.05
    speed = np.linalg.norm(np.diff(tr, axis=0), axis=1) * m.fps
    assert speed.max() < 2.0  # walking, not running


# ------------------------------------------------------------------ AMASS


def _amass(tmp_path, name, frames=101, fps=120.0, cols=156, fps_key="mocap_framerate", betas=10,
           drop=(), extra=None, rng=None):
    rng = rng or np.random.default_rng(0)
    t = np.arange(frames) / fps
    poses = rng.normal(size=(frames, cols)) * 0.05 + 0.3 * np.sin(t)[:, None]
    # Upright in AMASS's z-up world: the SMPL body (y up) turned +90 degrees about x.
    poses[:, :3] = [math.pi / 2, 0.0, 0.0]
    data = {
        "poses": poses,
        "trans": np.stack([0.1 * t, 0.2 + 0 * t, 0.9 + 0.01 * t], axis=1),
        "betas": np.arange(betas, dtype=np.float64) * 0.1,
        fps_key: np.array(fps),
        "gender": np.array("neutral"),
    }
    if cols == 165:
        data["root_orient"] = poses[:, :3]
        data["pose_body"] = poses[:, 3:66]
    data.update(extra or {})
    written = {k: v for k, v in data.items() if k not in drop}
    path = tmp_path / name
    np.savez(path, **written)
    return path, data


@pytest.mark.parametrize(
    "cols, fps_key", [(156, "mocap_framerate"), (165, "mocap_frame_rate"), (66, "mocap_framerate")]
)
def test_load_amass_variants(tmp_path, cols, fps_key):
    path, data = _amass(tmp_path, f"m{cols}.npz", cols=cols, fps_key=fps_key)
    m = load_amass(path)
    assert m.fps == 60.0 and m.num_frames == 51  # 101 frames at 120 fps span 5/6 s
    assert m.poses.shape == (51, 66) and m.name == f"m{cols}"
    # Every other source frame is an output frame: body joints unchanged there.
    np.testing.assert_allclose(m.poses[:, 3:].double().numpy(), data["poses"][::2, 3:66], atol=_F32_TOL)
    # z up -> y up: the upright root becomes the identity; trans (x, y, z) -> (x, z, -y).
    np.testing.assert_allclose(m.poses[:, :3].double().numpy(), 0.0, atol=_F32_TOL)
    tr = data["trans"][::2]
    want = np.stack([tr[:, 0], tr[:, 2], -tr[:, 1]], 1)
    np.testing.assert_allclose(m.trans.double().numpy(), want, atol=_F32_TOL)
    np.testing.assert_allclose(m.betas.numpy(), np.r_[np.arange(10) * 0.1, np.zeros(6)], atol=1e-7)


def test_load_amass_from_root_orient_and_pose_body(tmp_path):
    path, data = _amass(tmp_path, "x.npz", cols=165, fps=60.0, betas=300, drop=("poses",))
    m = load_amass(path, z_up=False)
    assert m.num_frames == 101
    np.testing.assert_allclose(m.poses.double().numpy(), data["poses"][:, :66], atol=_F32_TOL)
    np.testing.assert_allclose(m.betas.numpy(), np.arange(16) * 0.1, atol=1e-6)  # cut to 16


def test_load_amass_root_joint_makes_the_conversion_exact(tmp_path):
    path, data = _amass(tmp_path, "r.npz", fps=60.0)
    j0 = REST_JOINTS[0] + np.array([0.0, 0.9, 0.02])  # a pelvis not at the origin
    rest = REST_JOINTS + (j0 - REST_JOINTS[0])
    m = load_amass(path, root_joint=j0)
    rc = mo.Z_UP_TO_Y_UP

    def world(pose, trans):  # SMPL: x = R_root (x_local) + J0 + trans
        return ref.world_joint_positions(pose, rest) + j0 + trans

    for k in (0, 50, 100):
        old = world(data["poses"][k, :66], data["trans"][k])
        new = world(m.poses[k].double().numpy(), m.trans[k].double().numpy())
        np.testing.assert_allclose(new, old @ rc.T, atol=1e-5)  # every joint, rotated z-up -> y-up
        assert new[JOINT["head"], 1] > new[JOINT["pelvis"], 1] + 0.25  # and upright (spine bent a bit)


def test_resample_interpolates_between_frames():
    m = procedural_motion("head_turn", duration=1.0, fps=30.0)
    up = resample_motion(m, 60.0)
    assert up.num_frames == 2 * m.num_frames - 1
    src = m.poses.double().numpy()
    for k in (3, 11, 20):
        got = up.poses[2 * k + 1].double().numpy()
        for j in range(22):
            want = ref.slerp_aa(src[k, 3 * j:3 * j + 3], src[k + 1, 3 * j:3 * j + 3], 0.5)
            np.testing.assert_allclose(ref.rodrigues(got[3 * j:3 * j + 3]), ref.rodrigues(want), atol=1e-5)
    down = resample_motion(procedural_motion("nod", duration=1.0, fps=120.0), 60.0)
    assert down.num_frames == 61


MALFORMED = {
    "no_poses": (dict(drop=("poses",)), "'poses'"),
    "bad_columns": (dict(extra={"poses": np.zeros((5, 70))}), "'poses'"),
    "nan_poses": (dict(extra={"poses": np.full((101, 156), np.nan)}), "'poses'"),
    "no_trans": (dict(drop=("trans",)), "'trans'"),
    "trans_frames": (dict(extra={"trans": np.zeros((7, 3))}), "'trans'"),
    "no_fps": (dict(drop=("mocap_framerate",)), "'mocap_framerate'"),
    "zero_fps": (dict(extra={"mocap_framerate": np.array(0.0)}), "'mocap_framerate'"),
    "text_betas": (dict(extra={"betas": np.array(["a", "b"])}), "'betas'"),
    "pose_body_width": (
        dict(cols=165, drop=("poses",), extra={"pose_body": np.zeros((101, 60))}), "'pose_body'"
    ),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_load_amass_malformed(tmp_path, case):
    kwargs, key = MALFORMED[case]
    path, _ = _amass(tmp_path, f"{case}.npz", **kwargs)
    with pytest.raises(ValueError) as info:
        load_amass(path)
    assert str(path) in str(info.value) and key in str(info.value)


def test_load_amass_not_an_npz(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="junk.npz"):
        load_amass(path)


def test_subsample_and_dynamic_filter():
    m = procedural_motion("nod")
    s = subsample_motion(m, 3)
    assert s.num_frames == (m.num_frames + 2) // 3 and s.fps == 60.0
    torch.testing.assert_close(s.poses, m.poses[::3])
    assert subsample_motion(m, 3, keep_fps=False).fps == 20.0
    # Playing every 3rd frame at the same rate triples the angular speed.
    assert dynamic_score(s) == pytest.approx(3 * dynamic_score(m), rel=0.05)
    still = Motion(torch.zeros(30, 66), torch.zeros(30, 3), torch.zeros(16), name="still")
    assert dynamic_score(still) == 0.0
    motions = [still, m, s, procedural_motion("tilt")]
    kept = filter_dynamic(motions)
    assert len(kept) == 2 and still not in kept and s in kept
    assert len(filter_dynamic(motions, quantile=0.0)) == 4
    with pytest.raises(ValueError, match="k"):
        subsample_motion(m, 0)
    with pytest.raises(ValueError, match="quantile"):
        filter_dynamic(motions, 1.5)


def test_motion_validates_fields():
    with pytest.raises(ValueError, match="poses"):
        Motion(torch.zeros(5, 60), torch.zeros(5, 3), torch.zeros(16))
    with pytest.raises(ValueError, match="trans"):
        Motion(torch.zeros(5, 66), torch.zeros(4, 3), torch.zeros(16))
    with pytest.raises(ValueError, match="poses.*NaN"):
        Motion(torch.full((5, 66), float("nan")), torch.zeros(5, 3), torch.zeros(16))
    with pytest.raises(ValueError, match="fps"):
        Motion(torch.zeros(5, 66), torch.zeros(5, 3), torch.zeros(16), fps=0.0)


# ------------------------------------------------------------------ descriptors


def test_descriptors_match_reference(rng):
    poses = np.cumsum(rng.normal(size=(14, 66)) * 0.03, axis=0)
    betas = rng.normal(size=16)
    got = frame_descriptors(torch.tensor(poses), torch.tensor(betas), DT).numpy()
    assert got.shape == (14, DESCRIPTOR_DIM)
    for t in range(14):
        np.testing.assert_allclose(got[t], ref.frame_descriptor(poses, t, betas, DT, REST_JOINTS),
                                   rtol=1e-9, atol=_DESC_TOL)
    assert np.abs(got[5:, DESCRIPTOR_SLICES["joint_acceleration"]]).max() > 1.0  # not all zero


def test_constant_pose_gives_zero_motion(rng):
    pose = torch.tensor(rng.normal(size=66) * 0.5).expand(12, 66)
    betas = torch.tensor(rng.normal(size=16))
    d = motion_descriptors(pose, betas, DT, window=10)
    assert d.shape == (10, DESCRIPTOR_DIM)
    torch.testing.assert_close(d[:, :132], torch.zeros(10, 132, dtype=torch.float64), rtol=0, atol=1e-9)
    torch.testing.assert_close(d[:, 132:], betas.expand(10, 16))


def test_constant_rate_head_turn(rng):
    omega = 2.0  # [rad/s]
    t = np.arange(20) * DT
    poses = np.zeros((20, 66))
    poses[:, 3 * JOINT["head"] + 1] = omega * t
    d = frame_descriptors(torch.tensor(poses), torch.zeros(16, dtype=torch.float64), DT).numpy()
    w = d[1:, DESCRIPTOR_SLICES["joint_angular_velocity"]].reshape(-1, 22, 3)
    want = np.zeros((22, 3))
    want[JOINT["head"], 1] = omega
    np.testing.assert_allclose(w, np.broadcast_to(want, w.shape), atol=1e-9)
    np.testing.assert_allclose(d[:, DESCRIPTOR_SLICES["joint_acceleration"]], 0.0, atol=1e-9)
    np.testing.assert_allclose(d[:, DESCRIPTOR_SLICES["gravity_velocity"]], 0.0, atol=1e-12)


def test_constant_rate_neck_turn_gives_centripetal_head_acceleration():
    omega = 3.0
    poses = np.zeros((30, 66))
    poses[:, 3 * JOINT["neck"] + 1] = omega * np.arange(30) * DT
    d = frame_descriptors(torch.tensor(poses), torch.zeros(16, dtype=torch.float64), DT).numpy()
    acc = d[:, DESCRIPTOR_SLICES["joint_acceleration"]].reshape(-1, 21, 3)[:, JOINT["head"] - 1]
    arm = REST_JOINTS[JOINT["head"]] - REST_JOINTS[JOINT["neck"]]

    def yaw(angle):
        c, s = math.cos(angle), math.sin(angle)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    for k in range(5, 30):
        r = yaw(omega * k * DT) @ arm
        # Second difference of uniform circular motion: -(2 - 2 cos(w dt))/dt^2 of the radius
        # vector at the middle frame k - 1, i.e. -w^2 r_perp up to O(dt^2).
        perp = (yaw(omega * (k - 1) * DT) @ arm) * [1, 0, 1]
        np.testing.assert_allclose(acc[k], -(2 - 2 * math.cos(omega * DT)) / DT**2 * perp, atol=1e-8)
        assert np.linalg.norm(acc[k]) == pytest.approx(omega**2 * np.linalg.norm(r * [1, 0, 1]), rel=1e-3)


def test_gravity_velocity_of_a_root_pitch():
    omega = 1.5
    poses = np.zeros((10, 66))
    poses[:, 0] = omega * np.arange(10) * DT
    d = frame_descriptors(torch.tensor(poses), torch.zeros(16, dtype=torch.float64), DT).numpy()
    g = d[:, DESCRIPTOR_SLICES["gravity_velocity"]]
    # g_root(t) = R_x(wt)^T (0,-1,0) = (0, -cos wt, sin wt): derivative magnitude w.
    np.testing.assert_allclose(np.linalg.norm(g[1:], axis=1), 2 * math.sin(omega * DT / 2) / DT, rtol=1e-9)
    assert np.abs(g[0]).max() == 0.0


def test_windows_and_batches_agree(rng):
    poses = torch.tensor(np.cumsum(rng.normal(size=(2, 16, 66)) * 0.02, axis=1))
    betas = torch.tensor(rng.normal(size=(2, 16)))
    win = motion_descriptor_windows(poses, betas, DT, window=10)
    assert win.shape == (2, 16, 10, DESCRIPTOR_DIM)
    for b in range(2):
        for t in (0, 3, 9, 10, 15):
            single = motion_descriptors(poses[b, : t + 1], betas[b], DT, window=10)
            torch.testing.assert_close(win[b, t], single, rtol=1e-9, atol=1e-9)
    # Windows that reach before frame 0 repeat frame 0's descriptor.
    torch.testing.assert_close(win[:, 3, :7], win[:, 0, -1:].expand(2, 7, DESCRIPTOR_DIM))
    f32 = motion_descriptors(poses.float(), betas.float(), DT, include_betas=False)
    assert f32.dtype == torch.float32 and f32.shape == (2, 10, 132)


def test_procedural_motion_descriptors_are_finite():
    m = procedural_motion("whiplash")
    w = motion_descriptor_windows(m.poses, m.betas, m.dt)
    assert w.shape == (m.num_frames, 10, DESCRIPTOR_DIM) and torch.isfinite(w).all()
    assert float(w[..., DESCRIPTOR_SLICES["joint_angular_velocity"]].abs().max()) > 5.0


@pytest.mark.parametrize("kwargs, match", [
    (dict(poses=torch.zeros(5, 60)), "poses"),
    (dict(poses=torch.full((5, 66), float("inf"))), "poses"),
    (dict(betas=torch.zeros(10)), "betas"),
    (dict(dt=0.0), "dt"),
    (dict(window=0), "window"),
    (dict(joints=torch.zeros(21, 3)), "joints"),
])
def test_descriptor_bad_input(kwargs, match):
    args = dict(poses=torch.zeros(5, 66), betas=torch.zeros(16), dt=DT, window=10)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        motion_descriptors(**args)
