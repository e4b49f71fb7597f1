"""Body motions: named procedural motions, the AMASS loader, and the motion descriptors.

Poses follow the SMPL convention (Section 3.1): 22 joints x 3 axis-angle numbers = 66, joint 0
the root orientation, each joint's rotation relative to its parent, joint frames aligned with
the world at rest (T-pose, y up, face +z). Joint order: 0 pelvis, 1 l_hip, 2 r_hip, 3 spine1,
4 l_knee, 5 r_knee, 6 spine2, 7 l_ankle, 8 r_ankle, 9 spine3, 10 l_foot, 11 r_foot, 12 neck,
13 l_collar, 14 r_collar, 15 head, 16 l_shoulder, 17 r_shoulder, 18 l_elbow, 19 r_elbow,
20 l_wrist, 21 r_wrist. "Left" is the body's left, on the +x side.

Training follows Section 4.2.2: 60 fps (dt = 1/60 s), windows of T_w = 10 frames, optional
frame subsampling every k = 2..5 frames to strengthen the dynamics, and a dynamic-score filter
at the median.
"""

from __future__ import annotations

import dataclasses
import math
import os
import zipfile
from dataclasses import dataclass

import numpy as np
import torch

from hairwarp._validate import check_positive, check_tensor
from hairwarp.scene.rotations import (
    axis_angle_to_matrix,
    compose_axis_angles,
    matrix_to_axis_angle,
    np_axis_angle_to_matrix,
    np_matrix_to_axis_angle,
    slerp_axis_angles,
)
from hairwarp.scene.skeleton import JOINT, NUM_BETAS, NUM_JOINTS, POSE_DIM, SMPL_PARENTS

DEFAULT_FPS = 60.0

# Rest (T-pose) joint positions [m] of an average adult, SMPL-like, y up, face +z, pelvis at
# the origin. Hand-entered approximations (a few cm); they only set the lever arms of the
# joint-acceleration descriptors. Pass the body model's own joints for exact values.
REST_JOINTS = np.array([
    [0.000, 0.000, 0.000],    # pelvis
    [0.070, -0.090, -0.005],  # l_hip
    [-0.070, -0.090, -0.005],  # r_hip
    [0.000, 0.110, -0.025],   # spine1
    [0.105, -0.455, 0.005],   # l_knee
    [-0.105, -0.455, 0.005],  # r_knee
    [0.005, 0.245, 0.000],    # spine2
    [0.090, -0.880, -0.055],  # l_ankle
    [-0.090, -0.880, -0.055],  # r_ankle
    [0.005, 0.305, 0.000],    # spine3
    [0.120, -0.935, 0.065],   # l_foot
    [-0.120, -0.935, 0.065],  # r_foot
    [0.000, 0.520, -0.020],   # neck
    [0.080, 0.430, -0.025],   # l_collar
    [-0.080, 0.430, -0.025],  # r_collar
    [0.005, 0.590, 0.025],    # head
    [0.175, 0.455, -0.040],   # l_shoulder
    [-0.175, 0.455, -0.040],  # r_shoulder
    [0.430, 0.440, -0.065],   # l_elbow
    [-0.430, 0.440, -0.065],  # r_elbow
    [0.690, 0.445, -0.070],   # l_wrist
    [-0.690, 0.445, -0.070],  # r_wrist
])

# Layout of one per-frame motion descriptor m (see `motion_descriptors`).
DESCRIPTOR_SLICES = {
    "joint_angular_velocity": slice(0, 66),   # 22 x 3, local (relative-to-parent) [rad/s]
    "gravity_velocity": slice(66, 69),        # d/dt of gravity direction in the root frame [1/s]
    "joint_acceleration": slice(69, 132),     # joints 1..21 x 3, root frame [m/s^2]
    "betas": slice(132, 148),                 # body shape, appended unchanged
}
DESCRIPTOR_DIM = 148
DESCRIPTOR_DIM_NO_BETAS = 132


@dataclass(eq=False)
class Motion:
    """A body motion (SMPL convention).

    Attributes:
        poses: (T, 66) float32 axis-angle joint rotations [rad] (joint 0 = root orientation).
        trans: (T, 3) float32 root translation [m], y up.
        betas: (16,) float32 body shape.
        fps: frames per second [1/s].
        name: a label.
    """

    poses: torch.Tensor
    trans: torch.Tensor
    betas: torch.Tensor
    fps: float = DEFAULT_FPS
    name: str = ""

    def __post_init__(self):
        check_tensor("poses", self.poses, shape=(None, POSE_DIM), allow_empty=False)
        t = self.poses.shape[0]
        check_tensor("trans", self.trans, shape=(t, 3))
        check_tensor("betas", self.betas, shape=(NUM_BETAS,))
        check_positive("fps", self.fps)

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    @property
    def dt(self) -> float:
        """Time step [s]."""
        return 1.0 / float(self.fps)

    @property
    def duration(self) -> float:
        """Time from the first to the last frame [s]."""
        return (self.num_frames - 1) / float(self.fps)

    def replace(self, **changes) -> Motion:
        return dataclasses.replace(self, **changes)


def _motion(poses: np.ndarray, trans: np.ndarray, betas=None, fps=DEFAULT_FPS, name="") -> Motion:
    betas = np.zeros(NUM_BETAS) if betas is None else betas
    return Motion(
        poses=torch.tensor(poses, dtype=torch.float32),
        trans=torch.tensor(trans, dtype=torch.float32),
        betas=torch.tensor(betas, dtype=torch.float32),
        fps=float(fps),
        name=name,
    )


def _rot(axis: str, angle) -> np.ndarray:
    """Axis-angle vectors (..., 3) for rotations by `angle` about a world axis."""
    angle = np.asarray(angle, dtype=np.float64)
    out = np.zeros(angle.shape + (3,))
    out[..., "xyz".index(axis)] = angle
    return out


# ----------------------------------------------------------------------------------------------
# Procedural motions


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


# Arms lowered from the T-pose to the sides (A-pose) [rad], about z at the shoulders.
_ARMS_DOWN = math.radians(65.0)


def _rest_pose(t: np.ndarray) -> np.ndarray:
    """(T, 22, 3) rest pose: standing, arms lowered to the sides."""
    pose = np.zeros((len(t), NUM_JOINTS, 3))
    pose[:, JOINT["left_shoulder"]] = _rot("z", -_ARMS_DOWN)
    pose[:, JOINT["right_shoulder"]] = _rot("z", _ARMS_DOWN)
    return pose


def standing_pose() -> torch.Tensor:
    """(66,) float32 the procedural motions' rest pose, axis-angle [rad]: standing, arms lowered
    to the sides (the pose most training drapes hold).
    """
    return torch.as_tensor(_rest_pose(np.zeros(1))[0].reshape(-1), dtype=torch.float32)


def _jitter(rng, scale):
    return 1.0 if rng is None else float(np.exp(scale * rng.standard_normal()))


def _head_oscillation(axis, amplitude_deg, frequency):
    def make(t, rng):
        a = math.radians(amplitude_deg) * _jitter(rng, 0.15)
        f = frequency * _jitter(rng, 0.1)
        # Eased in over the first half second, so the hair starts from a quasi-static drape.
        angle = a * np.sin(2 * np.pi * f * t) * _smoothstep(t / 0.5)
        pose = _rest_pose(t)
        pose[:, JOINT["neck"]] = _rot(axis, 0.35 * angle)
        pose[:, JOINT["head"]] = _rot(axis, 0.65 * angle)
        return pose, np.zeros((len(t), 3))

    return make


def _whiplash(t, rng):
    """Fast head turns that stop abruptly (Fig. 4): constant angular acceleration up to a peak
    speed, then an instant stop, a hold, and the same back.
    """
    a = math.radians(80.0) * _jitter(rng, 0.1)
    turn = 0.25 * _jitter(rng, 0.1)  # [s] duration of each turn
    t0, t1 = 0.4, 0.4 + turn + 1.2
    u0 = np.clip((t - t0) / turn, 0.0, 1.0)
    u1 = np.clip((t - t1) / turn, 0.0, 1.0)
    angle = a * (u0**2 - u1**2)
    pose = _rest_pose(t)
    pose[:, JOINT["neck"]] = _rot("y", 0.4 * angle)
    pose[:, JOINT["head"]] = _rot("y", 0.6 * angle)
    return pose, np.zeros((len(t), 3))


def _bend_profile(t, down=1.5, hold=1.0, start=0.3):
    return _smoothstep((t - start) / down) - _smoothstep((t - start - down - hold) / down)


def _torso_bend(t, rng):
    """Bending forward at the waist (Fig. 9) and back up."""
    a = math.radians(85.0) * _jitter(rng, 0.1)
    b = a * _bend_profile(t)
    pose = _rest_pose(t)
    # +x rotation turns +y toward +z: the upper body leans forward, toward the face.
    for joint, share in (("pelvis", 0.25), ("spine1", 0.3), ("spine2", 0.25), ("spine3", 0.2)):
        pose[:, JOINT[joint]] = _rot("x", share * b)
    # Hips counter-rotate the pelvis share so the legs stay vertical.
    pose[:, JOINT["left_hip"]] = _rot("x", -0.25 * b)
    pose[:, JOINT["right_hip"]] = _rot("x", -0.25 * b)
    return pose, np.zeros((len(t), 3))


def _arm_raise(t, rng):
    """Both arms raised from the sides to above the head and lowered again."""
    up = math.radians(75.0) * _jitter(rng, 0.1)
    u = _bend_profile(t, down=1.2, hold=0.8)
    angle = -_ARMS_DOWN + (up + _ARMS_DOWN) * u
    pose = _rest_pose(t)
    pose[:, JOINT["left_shoulder"]] = _rot("z", angle)
    pose[:, JOINT["right_shoulder"]] = _rot("z", -angle)
    pose[:, JOINT["left_elbow"]] = _rot("y", 0.5 * u)
    pose[:, JOINT["right_elbow"]] = _rot("y", -0.5 * u)
    return pose, np.zeros((len(t), 3))


def _sway_walk(t, rng):
    """Walking forward (+z) with hip sway, arm swing and head bob."""
    f = 0.9 * _jitter(rng, 0.1)  # stride frequency [Hz] (two steps per stride)
    speed = 1.1 * f  # [m/s], a 1.1 m stride
    ease = _smoothstep(t / 0.6)
    ph = 2 * np.pi * f * t
    swing = math.radians(25.0) * np.sin(ph) * ease
    pose = _rest_pose(t)
    # Hip flexion forward is a -x rotation (a leg pointing down swings toward +z).
    pose[:, JOINT["left_hip"]] = _rot("x", -swing)
    pose[:, JOINT["right_hip"]] = _rot("x", swing)
    knee = math.radians(30.0) * ease
    pose[:, JOINT["left_knee"]] = _rot("x", knee * np.clip(np.sin(ph + 1.2), 0, None))
    pose[:, JOINT["right_knee"]] = _rot("x", knee * np.clip(-np.sin(ph + 1.2), 0, None))
    sway = math.radians(6.0) * np.sin(ph) * ease
    pose[:, JOINT["pelvis"]] = compose_axis_angles(_rot("y", sway), _rot("z", 0.6 * sway))
    pose[:, JOINT["spine2"]] = _rot("y", -0.8 * sway)
    pose[:, JOINT["head"]] = _rot("y", -0.2 * sway)
    arm = math.radians(20.0) * np.sin(ph) * ease
    # Arm swing about x in the parent frame, applied after lowering the arm.
    pose[:, JOINT["left_shoulder"]] = compose_axis_angles(_rot("x", arm), _rot("z", -_ARMS_DOWN * np.ones_like(t)))
    pose[:, JOINT["right_shoulder"]] = compose_axis_angles(_rot("x", -arm), _rot("z", _ARMS_DOWN * np.ones_like(t)))
    trans = np.zeros((len(t), 3))
    # Forward progress eased in, the body's centre shifts over the stance leg, and bobs twice
    # per stride.
    dt = t[1] - t[0] if len(t) > 1 else 0.0
    trans[:, 2] = speed * np.cumsum(ease) * dt
    trans[:, 0] = 0.03 * np.sin(ph) * ease
    trans[:, 1] = 0.015 * (np.cos(2 * ph) - 1) * ease
    return pose, trans


_PROCEDURAL = {
    "head_turn": (_head_oscillation("y", 60.0, 0.5), 4.0),
    "nod": (_head_oscillation("x", 30.0, 1.0), 3.0),
    "tilt": (_head_oscillation("z", 30.0, 0.5), 4.0),
    "whiplash": (_whiplash, 3.5),
    "torso_bend": (_torso_bend, 4.5),
    "arm_raise": (_arm_raise, 4.0),
    "sway_walk": (_sway_walk, 4.0),
}


def random_head_moves(seed: int, duration: float = 1.5, fps: float = DEFAULT_FPS) -> Motion:
    """Random quick head and neck moves with holds between them: training clips for dynamics.

    From the rest pose, moves follow one another: each turns the head (yaw up to +-70 deg, pitch
    and roll up to +-30 deg, drawn anew per move) over 0.12-0.5 s, either eased (smoothstep) or at
    constant angular acceleration with an abrupt stop, then holds for 0.1-0.6 s; every third move
    or so also leans the upper body by up to 20 deg. The hair's secondary motion comes from the
    starts and stops. Not one of `list_motions()`: the networks' default training data keeps its
    motions.

    Args:
        seed: the draw (any int).
        duration: length [s].
        fps: frame rate [1/s].

    Returns:
        A `Motion` of round(duration * fps) + 1 frames named "head_moves<seed>".
    """
    duration = check_positive("duration", duration)
    fps = check_positive("fps", fps)
    rng = np.random.default_rng(int(seed))
    t = np.arange(int(round(duration * fps)) + 1) / fps
    limits = np.radians([30.0, 70.0, 30.0, 20.0])  # pitch (x), yaw (y), roll (z), lean (x)
    keys, now, start = [np.zeros(4)], 0.1 * rng.random(), []
    while now < duration:
        target = rng.uniform(-1.0, 1.0, 4) * limits
        target[3] = target[3] if rng.random() < 0.35 else keys[-1][3]
        move = rng.uniform(0.12, 0.5)
        start.append((now, move, rng.random() < 0.5))
        keys.append(target)
        now += move + rng.uniform(0.1, 0.6)
    angles = np.zeros((len(t), 4))
    for (t0, move, abrupt), a, b in zip(start, keys[:-1], keys[1:]):
        u = np.clip((t - t0) / move, 0.0, 1.0)
        # Abrupt: constant acceleration to full speed, then an instant stop (as `whiplash`).
        w = u**2 if abrupt else _smoothstep(u)
        angles = np.where((t >= t0)[:, None], a + (b - a) * w[:, None], angles)
    pose = _rest_pose(t)
    neck = compose_axis_angles(_rot("x", 0.35 * angles[:, 0]),
                               compose_axis_angles(_rot("y", 0.35 * angles[:, 1]), _rot("z", 0.35 * angles[:, 2])))
    head = compose_axis_angles(_rot("x", 0.65 * angles[:, 0]),
                               compose_axis_angles(_rot("y", 0.65 * angles[:, 1]), _rot("z", 0.65 * angles[:, 2])))
    pose[:, JOINT["neck"]] = neck
    pose[:, JOINT["head"]] = head
    for joint, share in (("spine1", 0.4), ("spine2", 0.35), ("spine3", 0.25)):
        pose[:, JOINT[joint]] = _rot("x", share * angles[:, 3])
    return _motion(pose.reshape(len(t), POSE_DIM), np.zeros((len(t), 3)), fps=fps, name=f"head_moves{int(seed)}")


def list_motions() -> list[str]:
    """Names of the procedural motions."""
    return list(_PROCEDURAL)


def procedural_motion(
    name: str, duration: float | None = None, seed: int | None = None, fps: float = DEFAULT_FPS
) -> Motion:
    """A named procedural motion.

    Args:
        name: one of `list_motions()`: head_turn (yaw), nod (pitch), tilt (roll), whiplash
            (fast head turns with an abrupt stop, Fig. 4), torso_bend (bending forward,
            Fig. 9), arm_raise, sway_walk.
        duration: length [s]; None for the motion's natural length (3-4.5 s).
        seed: None for the nominal motion; an int jitters amplitudes and rates (+-10-15 %).
        fps: frame rate [1/s] (60 in the paper).

    Returns:
        A `Motion` with round(duration * fps) + 1 frames, betas zero.
    """
    if name not in _PROCEDURAL:
        raise ValueError(f"name: expected one of {list_motions()}, got {name!r}")
    make, default_duration = _PROCEDURAL[name]
    duration = default_duration if duration is None else check_positive("duration", duration)
    fps = check_positive("fps", fps)
    rng = None if seed is None else np.random.default_rng(int(seed))
    t = np.arange(int(round(duration * fps)) + 1) / fps
    pose, trans = make(t, rng)
    return _motion(pose.reshape(len(t), POSE_DIM), trans, fps=fps, name=name)


# ----------------------------------------------------------------------------------------------
# AMASS

# z up -> y up: rotation of -90 degrees about x, (x, y, z) -> (x, z, -y).
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
_POSE_COLUMNS = {66: "SMPL body", 72: "SMPL", 156: "SMPL+H", 165: "SMPL-X"}


def load_amass(
    path: str | os.PathLike,
    target_fps: float = DEFAULT_FPS,
    subsample: int = 1,
    z_up: bool = True,
    root_joint: np.ndarray | None = None,
) -> Motion:
    """Load an AMASS `.npz` motion as a y-up, `target_fps` `Motion`.

    Keys read: `poses` (T x 66, 72, 156 or 165; the first 66 numbers are the root orientation
    and the 21 body joints in every variant), or else `root_orient` (T x 3) with `pose_body`
    (T x 63) as SMPL-X files also carry; `trans` (T x 3); `betas` (any length, padded with
    zeros or cut to 16; absent = zeros); the frame rate from `mocap_framerate` (SMPL+H) or
    `mocap_frame_rate` (SMPL-X).

    AMASS is z up. With `z_up=True` the world is rotated by -90 degrees about x, so
    y_new = z_old: the root orientation becomes R_c R_root and the translation R_c t. Rotating
    about the world origin instead of the pelvis joint J0 shifts the body by the constant
    (R_c - I) J0; pass the body's rest pelvis position as `root_joint` (3,) [m] to remove that
    shift (trans_new = R_c (t + J0) - J0).

    The motion is resampled to `target_fps` (per-joint quaternion slerp, linear translation),
    then `subsample_motion(motion, subsample)` is applied if subsample > 1.

    Raises:
        ValueError: naming the file and the key at fault (missing, wrong shape, NaN/Inf,
            non-positive frame rate), or the file if it is not a readable `.npz`.
    """
    name = os.fspath(path)
    check_positive("target_fps", target_fps)
    try:
        with np.load(name, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise ValueError(f"{name}: not a readable .npz file ({e})") from e

    def array(key, ndim=None):
        a = data[key]
        if not np.issubdtype(a.dtype, np.number):
            raise ValueError(f"{name}: key '{key}' is not numeric (dtype {a.dtype})")
        a = a.astype(np.float64)
        if ndim is not None and a.ndim != ndim:
            raise ValueError(f"{name}: key '{key}' should have {ndim} dimensions, has shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name}: key '{key}' contains NaN or Inf")
        return a

    if "poses" in data:
        poses = array("poses", 2)
        if poses.shape[1] not in _POSE_COLUMNS:
            raise ValueError(
                f"{name}: key 'poses' has {poses.shape[1]} columns; expected one of {sorted(_POSE_COLUMNS)}"
            )
        poses = poses[:, :POSE_DIM]
    elif "root_orient" in data and "pose_body" in data:
        root = array("root_orient", 2)
        body = array("pose_body", 2)
        if root.shape[1] != 3:
            raise ValueError(f"{name}: key 'root_orient' should be T x 3, has shape {root.shape}")
        if body.shape[1] != 63:
            raise ValueError(f"{name}: key 'pose_body' should be T x 63, has shape {body.shape}")
        if root.shape[0] != body.shape[0]:
            raise ValueError(
                f"{name}: key 'pose_body' has {body.shape[0]} frames, 'root_orient' {root.shape[0]}"
            )
        poses = np.concatenate([root, body], axis=1)
    else:
        raise ValueError(f"{name}: missing key 'poses' (nor 'root_orient' + 'pose_body')")
    if poses.shape[0] < 1:
        raise ValueError(f"{name}: key 'poses' has no frames")
    if "trans" not in data:
        raise ValueError(f"{name}: missing key 'trans'")
    trans = array("trans", 2)
    if trans.shape != (poses.shape[0], 3):
        raise ValueError(
            f"{name}: key 'trans' should be {poses.shape[0]} x 3 like 'poses', has shape {trans.shape}"
        )
    if "betas" in data:
        b = array("betas").reshape(-1)
        betas = np.zeros(NUM_BETAS)
        betas[: min(len(b), NUM_BETAS)] = b[:NUM_BETAS]
    else:
        betas = np.zeros(NUM_BETAS)
    key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
    if key is None:
        raise ValueError(f"{name}: missing key 'mocap_framerate' (or 'mocap_frame_rate')")
    fps_arr = array(key)
    if fps_arr.size != 1 or not fps_arr.reshape(-1)[0] > 0:
        raise ValueError(f"{name}: key '{key}' should be one positive number, got {fps_arr.reshape(-1)[:3]}")
    fps = float(fps_arr.reshape(-1)[0])

    if z_up:
        rc = Z_UP_TO_Y_UP
        poses = poses.copy()
        poses[:, :3] = np_matrix_to_axis_angle(rc @ np_axis_angle_to_matrix(poses[:, :3]))
        j0 = np.zeros(3) if root_joint is None else np.asarray(root_joint, dtype=np.float64).reshape(3)
        trans = (trans + j0) @ rc.T - j0
    motion = _motion(poses, trans, betas, fps=fps, name=os.path.splitext(os.path.basename(name))[0])
    motion = resample_motion(motion, target_fps)
    if int(subsample) != 1:
        motion = subsample_motion(motion, int(subsample))
    return motion


def resample_motion(motion: Motion, target_fps: float = DEFAULT_FPS) -> Motion:
    """Resample a motion in time: per-joint quaternion slerp, linear translation.

    The result covers the same time span, with floor(duration * target_fps) + 1 frames.
    """
    target_fps = check_positive("target_fps", target_fps)
    if abs(target_fps - motion.fps) < 1e-9:
        return motion
    poses = motion.poses.detach().cpu().double().numpy().reshape(-1, NUM_JOINTS, 3)
    trans = motion.trans.detach().cpu().double().numpy()
    t_src = motion.num_frames - 1
    n = int(math.floor(motion.duration * target_fps + 1e-9)) + 1
    x = np.arange(n) * (motion.fps / target_fps)  # positions in source frames
    i0 = np.clip(np.floor(x).astype(int), 0, max(t_src - 1, 0))
    i1 = np.minimum(i0 + 1, t_src)
    w = np.clip(x - i0, 0.0, 1.0)
    new_poses = slerp_axis_angles(poses[i0], poses[i1], np.repeat(w[:, None], NUM_JOINTS, axis=1)).reshape(n, POSE_DIM)
    new_trans = trans[i0] * (1 - w[:, None]) + trans[i1] * w[:, None]
    return Motion(
        poses=torch.tensor(new_poses, dtype=motion.poses.dtype),
        trans=torch.tensor(new_trans, dtype=motion.trans.dtype),
        betas=motion.betas.clone(),
        fps=float(target_fps),
        name=motion.name,
    )


def subsample_motion(motion: Motion, k: int, offset: int = 0, keep_fps: bool = True) -> Motion:
    """Keep one frame every `k` (Section 4.2.2 uses k = 2..5, one k per sequence).

    Args:
        motion: the motion.
        k: frame interval (>= 1).
        offset: first frame kept (0 <= offset < k).
        keep_fps: True (the paper's use) keeps the frame rate, so the motion plays k times
            faster and its dynamics are stronger; False divides the frame rate by k (the same
            motion, coarser).
    """
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k: expected an int >= 1, got {k}")
    if not 0 <= int(offset) < k:
        raise ValueError(f"offset: expected 0 <= offset < {k}, got {offset}")
    if motion.num_frames <= offset:
        raise ValueError(f"motion: has {motion.num_frames} frames, none left after offset {offset}")
    return Motion(
        poses=motion.poses[offset::k].clone(),
        trans=motion.trans[offset::k].clone(),
        betas=motion.betas.clone(),
        fps=motion.fps if keep_fps else motion.fps / k,
        name=motion.name if k == 1 else f"{motion.name}@x{k}",
    )


def dynamic_score(motion: Motion) -> float:
    """How much a motion moves: the mean joint angular speed [rad/s].

    The angle of each joint's frame-to-frame relative rotation (all 22 joints, local
    rotations, root orientation included) divided by dt, averaged over joints and frames
    (Section 4.2.2's "dynamic score based on joint movements"). Zero for a single frame.
    """
    if motion.num_frames < 2:
        return 0.0
    r = np_axis_angle_to_matrix(motion.poses.detach().cpu().double().numpy().reshape(-1, NUM_JOINTS, 3))
    rel = np.swapaxes(r[:-1], -1, -2) @ r[1:]
    angle = np.linalg.norm(np_matrix_to_axis_angle(rel), axis=-1)
    return float(angle.mean() * motion.fps)


def filter_dynamic(motions: list[Motion], quantile: float = 0.5) -> list[Motion]:
    """Keep the motions whose `dynamic_score` is at least the `quantile` of all scores.

    Section 4.2.2 uses the median (quantile 0.5) of the scores of the candidate sequences.
    """
    if not 0.0 <= float(quantile) <= 1.0:
        raise ValueError(f"quantile: expected a value in [0, 1], got {quantile}")
    if len(motions) == 0:
        return []
    scores = np.array([dynamic_score(m) for m in motions])
    threshold = float(np.quantile(scores, float(quantile)))
    return [m for m, s in zip(motions, scores) if s >= threshold]


# ----------------------------------------------------------------------------------------------
# Motion descriptors (Section 3.3.1), torch so they run where the network runs


def _check_descriptor_inputs(poses, betas, dt, window, joints):
    check_tensor("poses", poses, shape=("...", None, POSE_DIM))
    if poses.shape[-2] < 1:
        raise ValueError("poses: expected at least one frame")
    check_tensor("betas", betas, shape=("...", NUM_BETAS), device=poses.device)
    if betas.dim() > 1 and tuple(betas.shape[:-1]) != tuple(poses.shape[:-2]):
        raise ValueError(
            f"betas: leading shape {tuple(betas.shape[:-1])} does not match poses' {tuple(poses.shape[:-2])}"
        )
    check_positive("dt", dt)
    if not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window: expected an int >= 1, got {window}")
    if joints is not None:
        check_tensor("joints", joints, shape=(NUM_JOINTS, 3), device=poses.device)


def frame_descriptors(
    poses: torch.Tensor, betas: torch.Tensor, dt: float, joints: torch.Tensor | None = None,
    include_betas: bool = True,
) -> torch.Tensor:
    """Per-frame motion descriptors m^(t) of Section 3.3.1 for every frame of a sequence.

    m^(t) concatenates (layout in `DESCRIPTOR_SLICES`):
      - the local angular velocity of every joint's rotation (relative to its parent; the
        root's relative to the world): log(R_j^(t-1)^T R_j^(t)) / dt, 22 x 3 [rad/s];
      - the first-order derivative of the gravity direction expressed in the root frame
        ("unposed gravity"), (g^(t) - g^(t-1)) / dt with g = R_root^T (0, -1, 0), 3 [1/s];
      - the second-order local joint accelerations: joints 1..21 placed by forward
        kinematics in the root frame (root rotation and translation removed),
        (x^(t) - 2 x^(t-1) + x^(t-2)) / dt^2, 21 x 3 [m/s^2];
      - the body shape beta, 16 (if `include_betas`).
    Frames before the first are taken equal to it (the body at rest before the sequence).

    Args:
        poses: (..., T, 66) axis-angle poses [rad].
        betas: (16,) or (..., 16) body shape.
        dt: time step [s] (1/60 in the paper).
        joints: optional (22, 3) rest joint positions [m] of the body; default `REST_JOINTS`.
        include_betas: append beta (D = 148) or not (D = 132).

    Returns:
        (..., T, D) descriptors, dtype and device of `poses`.
    """
    _check_descriptor_inputs(poses, betas, dt, 1, joints)
    dtype, device = poses.dtype, poses.device
    lead = poses.shape[:-2]
    t = poses.shape[-2]
    rot = axis_angle_to_matrix(poses.reshape(lead + (t, NUM_JOINTS, 3)))  # (..., T, 22, 3, 3)
    prev = torch.cat([rot[..., :1, :, :, :], rot[..., :-1, :, :, :]], dim=-4)
    omega = matrix_to_axis_angle(prev.transpose(-1, -2) @ rot) / dt  # (..., T, 22, 3)

    down = torch.tensor([0.0, -1.0, 0.0], dtype=dtype, device=device)
    g = (rot[..., 0, :, :].transpose(-1, -2) @ down)  # (..., T, 3)
    g_prev = torch.cat([g[..., :1, :], g[..., :-1, :]], dim=-2)
    g_vel = (g - g_prev) / dt

    rest = torch.as_tensor(REST_JOINTS if joints is None else joints, dtype=dtype, device=device)
    pos = _local_joint_positions(rot, rest)  # (..., T, 22, 3)
    p1 = torch.cat([pos[..., :1, :, :], pos[..., :-1, :, :]], dim=-3)
    p2 = torch.cat([pos[..., :1, :, :], p1[..., :-1, :, :]], dim=-3)
    acc = (pos - 2 * p1 + p2)[..., 1:, :] / (dt * dt)

    parts = [omega.reshape(lead + (t, 66)), g_vel, acc.reshape(lead + (t, 63))]
    if include_betas:
        b = betas.to(dtype)
        parts.append((b.unsqueeze(-2) if b.dim() > 1 else b).expand(lead + (t, NUM_BETAS)))
    return torch.cat(parts, dim=-1)


def _local_joint_positions(rot: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """Forward kinematics in the root frame: the root's own rotation is left out."""
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device).expand(rot.shape[:-3] + (3, 3))
    glob = [eye]
    pos = [torch.zeros(rot.shape[:-3] + (3,), dtype=rot.dtype, device=rot.device)]
    for j in range(1, NUM_JOINTS):
        p = SMPL_PARENTS[j]
        offset = rest[j] - rest[p]
        pos.append(pos[p] + (glob[p] @ offset))
        glob.append(glob[p] @ rot[..., j, :, :])
    return torch.stack(pos, dim=-2)


def motion_descriptor_windows(
    poses: torch.Tensor, betas: torch.Tensor, dt: float, window: int = 10,
    joints: torch.Tensor | None = None, include_betas: bool = True,
) -> torch.Tensor:
    """The descriptor windows M^(t) = {m^(t-T_w+1), ..., m^(t)} for every frame t.

    Windows that reach before the first frame repeat m^(0) (itself zero motion), so every
    window has T_w entries (Section 3.3.1: M^(t) keeps the length of the pose window).

    Args:
        poses: (..., T, 66) axis-angle poses [rad].
        betas: (16,) or (..., 16) body shape.
        dt: time step [s].
        window: T_w (10 in the paper).
        joints: optional (22, 3) rest joint positions [m].
        include_betas: append beta to each descriptor.

    Returns:
        (..., T, T_w, D) descriptors; [..., t, -1, :] is frame t's own descriptor.
    """
    _check_descriptor_inputs(poses, betas, dt, window, joints)
    m = frame_descriptors(poses, betas, dt, joints, include_betas)
    t = m.shape[-2]
    idx = torch.arange(t, device=m.device)[:, None] + torch.arange(-window + 1, 1, device=m.device)[None, :]
    idx = idx.clamp_min(0)  # (T, T_w)
    return m[..., idx, :]


def motion_descriptors(
    poses: torch.Tensor, betas: torch.Tensor, dt: float, window: int = 10,
    joints: torch.Tensor | None = None, include_betas: bool = True,
) -> torch.Tensor:
    """The descriptor window M^(t) for the window ending at the last frame t of `poses`.

    `poses` holds the history up to t (at least one frame; frames before the window supply
    the derivatives at its start). Equal to `motion_descriptor_windows(...)[..., -1, :, :]`.

    Args:
        poses: (..., T, 66) axis-angle poses [rad], ending at frame t.
        betas: (16,) or (..., 16) body shape.
        dt: time step [s] (1/60 in the paper).
        window: T_w (10 in the paper).
        joints: optional (22, 3) rest joint positions [m].
        include_betas: append beta (D = 148) or return D = 132 without it.

    Returns:
        (..., T_w, D) descriptors, oldest first.
    """
    _check_descriptor_inputs(poses, betas, dt, window, joints)
    # Only the last window + 2 frames matter (second differences look two frames back).
    keep = min(poses.shape[-2], window + 2)
    m = frame_descriptors(poses[..., -keep:, :], betas, dt, joints, include_betas)
    if keep < poses.shape[-2]:
        m = m[..., 2:, :]  # drop the two frames whose history was cut off
    t = m.shape[-2]
    idx = (torch.arange(-window + 1, 1, device=m.device) + t - 1).clamp_min(0)
    return m[..., idx, :]
