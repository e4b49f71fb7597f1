"""SMPL's skeleton convention, in one place: joint names, parents, counts.

Poses enter every body (the default body, SMPL-format models, AMASS motions) as SMPL's first
22 joints in axis-angle, 66 numbers; the body shape as 16 coefficients (AMASS's count).
"""

from __future__ import annotations

NUM_JOINTS = 22
POSE_DIM = 3 * NUM_JOINTS
NUM_BETAS = 16
# The joints in SMPL's order, with SMPL's own names.
SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)
# Parent of each joint (-1: the root); SMPL files store the root's parent as 2**32 - 1.
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
# Joint index by name.
JOINT = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
HEAD_JOINT = JOINT["head"]

assert len(SMPL_JOINT_NAMES) == len(SMPL_PARENTS) == NUM_JOINTS
