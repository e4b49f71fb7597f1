"""The comparison scenes: fixed, versioned, seeded, and held in this one place.

Every method of the harness (`hairwarp.evaluation.harness`) runs on exactly these inputs. A
change to any scene (hairstyle, pose, motion window, selection rule) must bump
`SCENES_VERSION`, which every result file records.

Scenes (the default body, arms lowered to the sides, hairstyles grown around the rest body so
that the rest drape is nearly free of penetration; hairstyle seed `SCENE_SEED`):

- "table1": the paper's Table 1 scene (Section 4.3.2, Fig. 8 middle row): long straight hair
  on a head pitched forward 25 deg and rolled 20 deg, keeping the strands whose tip starts
  inside the body (about two thirds of the 32 x 32 scalp), so that *every* tip initially
  penetrates the shoulders and chest, most of them by more than a centimetre.
- "short_rest", "medium_rest": short straight / medium wavy hair, rest pose.
- "medium_poses": medium wavy hair in three poses (batch of 3): head turned 45 deg, nodded
  25 deg, tilted 25 deg.
- "whiplash": medium wavy hair, the procedural whiplash motion (an 80 deg head turn in
  0.25 s that stops abruptly), frames from 0.35 s to 1.0 s (40 frames at 60 fps).
- "torso_bend": long straight hair, the procedural torso bend, frames from 0.3 s to 1.3 s
  (61 frames; the upper body leans forward by about 60 deg).

Full size: every root of the 32 x 32 scalp (1024 strands, fewer for "table1"), 100 vertices
per strand. `reduced=True`: one root in 4 (256 strands) spread over the scalp
(`hairwarp.scene.scalp.grid_subset`), 100 vertices, for quick CPU runs. Tests pick their own
smaller sizes through `strand_stride` and `num_vertices`. The reduced strands are a subset of
the full scene's strands (resampled, never regrown), and every
result names the size it used (`ComparisonScene.size`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from hairwarp.config import EnergyConfig
from hairwarp.scene.hairstyles import Hairstyle, generate_hairstyle, hairstyle_preset
from hairwarp.scene.motion import Motion, procedural_motion
from hairwarp.scene.rotations import euler_to_axis_angle
from hairwarp.scene.scalp import root_subset
from hairwarp.scene.skeleton import JOINT, POSE_DIM
from hairwarp.scene.scene import Scene, SceneFrames

# Bump on any change to what the scenes hold. 2: a strand stride keeps a lattice spread over
# the scalp (`grid_subset`), where 1 kept every k-th root of the row-major grid (columns).
SCENES_VERSION = 2
# Seed of every hairstyle's randomness.
SCENE_SEED = 0
# `reduced=True` keeps one scalp root in this many (1024 -> 256).
REDUCED_STRAND_STRIDE = 4
# Vertices per strand (100 in the paper).
FULL_NUM_VERTICES = 100
# Arms lowered from the T-pose to the sides [deg] (as the procedural motions' rest pose).
_ARMS_DOWN_DEG = 65.0
# Share of a head rotation taken by the neck joint (the head joint takes the rest), as in the
# procedural motions.
_NECK_SHARE = 0.35


@dataclass(frozen=True)
class SceneSpec:
    """What one comparison scene holds.

    Attributes:
        name: the scene's key.
        kind: "static" (a batch of independent poses) or "motion" (a time sequence).
        hairstyle: preset name (`hairwarp.scene.hairstyles.list_hairstyle_presets()`).
        description: one line for tables.
        head_poses: static scenes: per frame, (pitch, yaw, roll) of the head [deg] about x, y,
            z (pitch > 0 nods forward), split between the neck and head joints.
        motion: motion scenes: the procedural motion's name.
        window: motion scenes: (start, end) [s] of the frames kept.
        tips_inside_only: keep only the strands whose tip starts inside the body.
    """

    name: str
    kind: str
    hairstyle: str
    description: str
    head_poses: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.0),)
    motion: str | None = None
    window: tuple[float, float] | None = None
    tips_inside_only: bool = False


SCENE_SPECS: dict[str, SceneSpec] = {
    "table1": SceneSpec(
        "table1", "static", "long_straight",
        "long straight hair, head pitched 25 deg forward and rolled 20 deg, every tip inside the body",
        head_poses=((25.0, 0.0, 20.0),), tips_inside_only=True,
    ),
    "short_rest": SceneSpec("short_rest", "static", "short_straight", "short straight hair, rest pose"),
    "medium_rest": SceneSpec("medium_rest", "static", "medium_wavy", "medium wavy hair, rest pose"),
    "medium_poses": SceneSpec(
        "medium_poses", "static", "medium_wavy",
        "medium wavy hair; head turned 45 deg, nodded 25 deg, tilted 25 deg (3 drapes)",
        head_poses=((0.0, 45.0, 0.0), (25.0, 0.0, 0.0), (0.0, 0.0, 25.0)),
    ),
    "whiplash": SceneSpec(
        "whiplash", "motion", "medium_wavy", "medium wavy hair, whiplash head turn, 0.35-1.0 s",
        motion="whiplash", window=(0.35, 1.0),
    ),
    "torso_bend": SceneSpec(
        "torso_bend", "motion", "long_straight", "long straight hair, torso bend, 0.3-1.3 s",
        motion="torso_bend", window=(0.3, 1.3),
    ),
}
SCENE_NAMES = tuple(SCENE_SPECS)
STATIC_SCENES = tuple(n for n, s in SCENE_SPECS.items() if s.kind == "static")
MOTION_SCENES = tuple(n for n, s in SCENE_SPECS.items() if s.kind == "motion")


@dataclass(eq=False)
class ComparisonScene:
    """One comparison scene at a chosen size.

    Attributes:
        name: the scene's key in `SCENE_SPECS`.
        spec: what it holds.
        scene: the `hairwarp.scene.scene.Scene` (body, hairstyle, motion).
        reduced: whether the quick (subsampled) size was asked for.
        size: {"strands", "vertices", "frames", "strand_stride"}: the size actually used.
        version: `SCENES_VERSION`.
    """

    name: str
    spec: SceneSpec
    scene: Scene
    reduced: bool
    size: dict
    version: int = SCENES_VERSION

    @property
    def kind(self) -> str:
        return self.spec.kind

    @property
    def is_motion(self) -> bool:
        return self.spec.kind == "motion"

    @property
    def num_frames(self) -> int:
        return self.scene.num_frames

    @property
    def fps(self) -> float:
        return float(self.scene.motion.fps)

    def frames(self, indices=None, *, device="cpu", dtype=torch.float32) -> SceneFrames:
        """`Scene.frames` of this scene (all frames by default)."""
        return self.scene.frames(indices, device=device, dtype=dtype)

    def energy_config(self, base: EnergyConfig | None = None) -> EnergyConfig:
        """`base` (default `EnergyConfig()`) with the time step set to this scene's frame spacing."""
        base = base or EnergyConfig()
        return base.replace(time_step=1.0 / self.fps)

    def describe(self) -> dict:
        """JSON-ready facts: name, kind, description, size, version."""
        return {"name": self.name, "kind": self.kind, "description": self.spec.description,
                "size": dict(self.size), "reduced": self.reduced, "scenes_version": self.version}


def head_pose(pitch: float = 0.0, yaw: float = 0.0, roll: float = 0.0) -> torch.Tensor:
    """(66,) SMPL pose: arms lowered to the sides, the head rotated by (pitch, yaw, roll) [deg].

    The rotation is split between the neck (`_NECK_SHARE`) and the head joint, as in the
    procedural motions.
    """
    pose = torch.zeros(POSE_DIM // 3, 3, dtype=torch.float64)
    down = math.radians(_ARMS_DOWN_DEG)
    pose[JOINT["left_shoulder"], 2] = -down
    pose[JOINT["right_shoulder"], 2] = down
    share = {"neck": _NECK_SHARE, "head": 1.0 - _NECK_SHARE}
    for joint, s in share.items():
        pose[JOINT[joint]] = torch.as_tensor(euler_to_axis_angle(s * pitch, s * yaw, s * roll))
    return pose.reshape(POSE_DIM).to(torch.float32)


@functools.lru_cache(maxsize=8)
def _grown_hairstyle(preset: str) -> tuple[Scene, Hairstyle]:
    """The full-size preset hairstyle grown around the rest body (cached: ~2-3 s each)."""
    from hairwarp.scene.scene import default_scene

    base = default_scene(preset, seed=SCENE_SEED)
    body = base.body
    style = generate_hairstyle(base.scalp, hairstyle_preset(preset, seed=SCENE_SEED),
                               num_vertices=FULL_NUM_VERTICES, body=(body.rest_vertices, body.faces))
    return base, style


def _motion_for(spec: SceneSpec) -> Motion:
    if spec.kind == "static":
        poses = torch.stack([head_pose(*p) for p in spec.head_poses])
        return Motion(poses=poses, trans=torch.zeros(len(poses), 3), betas=torch.zeros(16), fps=60.0,
                      name=spec.name)
    full = procedural_motion(spec.motion)
    start, end = spec.window
    a = int(round(start * full.fps))
    b = min(int(round(end * full.fps)) + 1, full.num_frames)
    return full.replace(poses=full.poses[a:b].clone(), trans=full.trans[a:b].clone(), name=spec.name)


def _tips_inside(scene: Scene) -> torch.Tensor:
    """(M,) bool: the strands whose tip lies inside the body in the scene's first frame."""
    from hairwarp.ops import hair_body_signed_distance

    frames = scene.frames([0])
    d = hair_body_signed_distance(frames.rigid.positions, frames.body_mesh)[0]
    return d[:, -1] < 0


def comparison_scene(name: str, reduced: bool = False, *, strand_stride: int | None = None,
                     num_vertices: int | None = None) -> ComparisonScene:
    """A comparison scene by name (see the module docstring and `SCENE_NAMES`).

    Args:
        name: one of `SCENE_NAMES`.
        reduced: keep one root in `REDUCED_STRAND_STRIDE` (quick CPU runs).
        strand_stride: keep one root in this many instead (overrides `reduced`'s stride),
            spread over the scalp (`hairwarp.scene.scalp.root_subset`).
        num_vertices: vertices per strand (default 100), by arc-length resampling.

    Returns:
        ComparisonScene; `size` says the strands, vertices and frames used.
    """
    if name not in SCENE_SPECS:
        raise ValueError(f"name: expected one of {list(SCENE_NAMES)}, got {name!r}")
    stride = REDUCED_STRAND_STRIDE if reduced else 1
    if strand_stride is not None:
        if not isinstance(strand_stride, int) or isinstance(strand_stride, bool) or strand_stride < 1:
            raise ValueError(f"strand_stride: expected a positive int, got {strand_stride!r}")
        stride = strand_stride
    n = FULL_NUM_VERTICES if num_vertices is None else num_vertices
    if not isinstance(n, int) or isinstance(n, bool) or n < 3:
        raise ValueError(f"num_vertices: expected an int >= 3, got {num_vertices!r}")
    spec = SCENE_SPECS[name]
    base, style = _grown_hairstyle(spec.hairstyle)
    motion = _motion_for(spec)
    keep = root_subset(style.num_strands, base.scalp.resolution, stride)
    if spec.tips_inside_only:
        full = Scene(body=base.body, scalp=base.scalp, hairstyle=style, motion=motion, name=name)
        inside = _tips_inside(full)
        keep = keep[inside[keep]]
        if keep.numel() == 0:
            raise ValueError(f"strand_stride: {stride} keeps no strand whose tip starts inside the body")
    hair = style.subset(keep, n)
    scene = Scene(body=base.body, scalp=base.scalp, hairstyle=hair, motion=motion, name=name)
    size = {"strands": hair.num_strands, "vertices": n, "frames": motion.num_frames, "strand_stride": stride}
    return ComparisonScene(name=name, spec=spec, scene=scene, reduced=bool(reduced), size=size)
