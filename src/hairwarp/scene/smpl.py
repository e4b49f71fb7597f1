"""SMPL-format body models in plain torch: file loading and linear blend skinning.

Reads the `.npz` that hairwarp ships (`hairwarp/assets/default_body.npz`, see
`tools/bake_default_body.py`) and SMPL-format files that a user owns: an `.npz` of arrays, or
the official `.pkl` (a latin1 Python-2 pickle whose arrays are chumpy objects and whose
`J_regressor` is a scipy sparse matrix; both are read through stand-in classes, so neither
chumpy nor scipy is imported, and nothing but arrays may come out of the pickle). The
`smplx` package is not used.

Keys (SMPL's names): `v_template` (V, 3), `f` (F, 3), `J_regressor` (J, V) dense or sparse,
`kintree_table` (2, J) whose first row holds the parents (the root's is 2^32 - 1 or -1),
`weights` (V, J), `shapedirs` (V, 3, K) with K = 10, 16, 300, ... (at most the first 16 are
used), optionally `posedirs` (V, 3, 9 (J - 1)) (zero when absent). J >= 22 and the first 22
joints follow SMPL's order and tree; joints past 22 (SMPL's hands) get identity rotations.
Optional extras that hairwarp's own file adds: `joint_names`, `head_vertex_indices`,
`attribution`, `metadata_json`.

Pose convention (SMPL's): the rest pose is a T-pose whose joint frames are world aligned, so
pose vector entries 3k..3k+2 are the axis-angle rotation [rad] of joint k relative to its
parent, in world axes at rest; entries 0..2 rotate the root. y is up.
"""

from __future__ import annotations

import json
import os
import pickle
from dataclasses import dataclass, field

import numpy as np
import torch

from hairwarp.scene.rotations import axis_angle_to_matrix, rigid_transform
from hairwarp.scene.skeleton import NUM_BETAS, NUM_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS

_ROOT_PARENTS = (-1, 2**32 - 1)
# Skin weight rows must sum to one within this (float32 storage gives ~1e-7).
_WEIGHT_SUM_TOL = 1e-4


@dataclass(frozen=True)
class SMPLModel:
    """The arrays of an SMPL-format body model, validated, as float64/int64 CPU tensors.

    Attributes:
        v_template: (V, 3) rest (T-pose) template vertices [m], y up.
        faces: (F, 3) int64 triangle vertex indices.
        shapedirs: (V, 3, K) shape blend shapes [m per unit beta], K <= 16.
        posedirs: (V, 3, 9 (J - 1)) pose corrective blend shapes [m], or None.
        J_regressor: (J, V) dense joint regressor.
        parents: (J,) parent of each joint, -1 for the root.
        weights: (V, J) skinning weights.
        joint_names: names of the first 22 joints (SMPL's unless the file says otherwise).
        head_vertex_indices: (H,) int64 head-region vertices, or None when the file has none.
        metadata: free-form extras of the file (attribution, bake statistics).
        source: the file it came from.
    """

    v_template: torch.Tensor
    faces: torch.Tensor
    shapedirs: torch.Tensor
    posedirs: torch.Tensor | None
    J_regressor: torch.Tensor
    parents: tuple[int, ...]
    weights: torch.Tensor
    joint_names: tuple[str, ...] = SMPL_JOINT_NAMES
    head_vertex_indices: torch.Tensor | None = None
    metadata: dict = field(default_factory=dict)
    source: str = ""

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.J_regressor.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])


# ----------------------------------------------------------------------------------------
# Loading


class _ChumpyStandIn:
    """Takes the place of chumpy's `Ch` while unpickling: keeps the pickled state only."""

    def __setstate__(self, state):
        self.state = state

    def to_numpy(self, where: str) -> np.ndarray:
        state = getattr(self, "state", None)
        if isinstance(state, dict) and "x" in state:
            return np.asarray(state["x"])
        raise ValueError(
            f"{where}: a chumpy expression, not a plain chumpy array; cannot read it without chumpy"
        )


class _SparseStandIn:
    """Takes the place of a scipy.sparse matrix while unpickling; densified with numpy."""

    scipy_name = ""

    def __setstate__(self, state):
        self.state = state

    def to_numpy(self, where: str) -> np.ndarray:
        state = getattr(self, "state", None)
        if not isinstance(state, dict):
            raise ValueError(f"{where}: unreadable sparse matrix")
        shape = state.get("_shape", state.get("shape"))
        fmt = self.scipy_name[:3]
        try:
            shape = tuple(int(s) for s in shape)
            dense = np.zeros(shape, dtype=np.float64)
            data = np.asarray(state["data"], dtype=np.float64)
            if fmt in ("csc", "csr"):
                indices = np.asarray(state["indices"], dtype=np.int64)
                indptr = np.asarray(state["indptr"], dtype=np.int64)
                outer = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
                rows, cols = (indices, outer) if fmt == "csc" else (outer, indices)
            elif fmt == "coo":
                rows = np.asarray(state.get("row", state.get("coords", [None, None])[0]), dtype=np.int64)
                cols = np.asarray(state.get("col", state.get("coords", [None, None])[1]), dtype=np.int64)
            else:
                raise ValueError(f"unsupported sparse format {self.scipy_name!r}")
            np.add.at(dense, (rows, cols), data)
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise ValueError(f"{where}: unreadable sparse matrix ({exc})") from None
        return dense


_NUMPY_GLOBALS = {"_reconstruct", "ndarray", "dtype", "scalar", "_frombuffer"}
_BUILTIN_GLOBALS = {"object", "set", "frozenset", "list", "dict", "tuple", "int", "float", "complex",
                    "bytes", "bytearray", "str", "slice", "bool"}


class _SMPLUnpickler(pickle.Unpickler):
    """Unpickler that only builds numpy arrays, builtins and the stand-ins above."""

    def find_class(self, module, name):
        if module.startswith("chumpy"):
            return _ChumpyStandIn
        if module.startswith("scipy.sparse"):
            return type(name, (_SparseStandIn,), {"scipy_name": name})
        if module.split(".")[0] == "numpy" and name in _NUMPY_GLOBALS:
            if module.startswith("numpy.core") and hasattr(np, "_core"):
                module = "numpy._core" + module[len("numpy.core"):]  # numpy 2 renamed numpy.core
            return super().find_class(module, name)
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return super().find_class(module, name)
        if module == "_codecs" and name == "encode":  # how protocol 2 spells bytes in Python 3
            return super().find_class(module, name)
        if module in ("__builtin__", "builtins") and name in _BUILTIN_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _read_pkl(path: str) -> dict:
    try:
        with open(path, "rb") as handle:
            data = _SMPLUnpickler(handle, encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError) as exc:
        raise ValueError(f"{path}: not a readable SMPL pickle ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a pickled dict of arrays, got {type(data).__name__}")
    out = {}
    for key, value in data.items():
        if isinstance(value, (_ChumpyStandIn, _SparseStandIn)):
            value = value.to_numpy(f"{path}: key {key!r}")
        out[key] = value
    return out


def _read_npz(path: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as archive:
            out = {}
            for key in archive.files:
                try:
                    out[key] = archive[key]
                except ValueError:
                    raise ValueError(
                        f"{path}: key {key!r} is a pickled object array; store it as a plain (dense) array"
                    ) from None
            return out
    except (OSError, EOFError) as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None


def _array(path, data, key, *, ndim, dtype_kind="f"):
    if key not in data:
        raise ValueError(f"{path}: missing key {key!r}")
    value = data[key]
    try:
        value = np.asarray(value)
    except Exception as exc:  # pragma: no cover - numpy refusing an object
        raise ValueError(f"{path}: key {key!r} is not an array ({exc})") from None
    if value.ndim != ndim:
        raise ValueError(f"{path}: key {key!r}: expected {ndim} dimensions, got shape {value.shape}")
    if dtype_kind == "f":
        if value.dtype.kind not in "fiu":
            raise ValueError(f"{path}: key {key!r}: expected numbers, got dtype {value.dtype}")
        value = value.astype(np.float64)
        if not np.isfinite(value).all():
            raise ValueError(f"{path}: key {key!r}: contains NaN or Inf")
    elif value.dtype.kind not in "iu":
        if value.dtype.kind == "f" and np.isfinite(value).all() and (value == np.round(value)).all():
            value = value.astype(np.int64)
        else:
            raise ValueError(f"{path}: key {key!r}: expected integers, got dtype {value.dtype}")
    if value.size == 0:
        raise ValueError(f"{path}: key {key!r}: empty array, shape {value.shape}")
    return value


def smpl_model_from_arrays(data: dict, source: str = "<arrays>") -> SMPLModel:
    """Validate a dict of SMPL arrays (as read from a file) and build an `SMPLModel`.

    Raises:
        ValueError: naming `source` and the key at fault (missing, wrong shape, NaN/Inf,
            indices out of range, a skeleton that is not SMPL's).
    """
    path = source
    v_template = _array(path, data, "v_template", ndim=2)
    num_vertices = v_template.shape[0]
    if v_template.shape[1] != 3:
        raise ValueError(f"{path}: key 'v_template': expected shape (V, 3), got {v_template.shape}")

    faces = _array(path, data, "f", ndim=2, dtype_kind="i").astype(np.int64)
    if faces.shape[1] != 3:
        raise ValueError(f"{path}: key 'f': expected shape (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= num_vertices:
        raise ValueError(f"{path}: key 'f': vertex indices outside [0, {num_vertices})")

    kintree = _array(path, data, "kintree_table", ndim=2, dtype_kind="i")
    if kintree.shape[0] != 2:
        raise ValueError(f"{path}: key 'kintree_table': expected shape (2, J), got {kintree.shape}")
    num_joints = kintree.shape[1]
    if num_joints < NUM_JOINTS:
        raise ValueError(
            f"{path}: key 'kintree_table': expected at least {NUM_JOINTS} joints, got {num_joints}"
        )
    raw_parents = [int(p) for p in kintree[0].astype(np.int64)]
    if raw_parents[0] not in _ROOT_PARENTS:
        raise ValueError(
            f"{path}: key 'kintree_table': the root's parent must be -1 or 2^32-1, got {raw_parents[0]}"
        )
    parents = tuple([-1] + raw_parents[1:])
    for j in range(1, num_joints):
        if not 0 <= parents[j] < j:
            raise ValueError(
                f"{path}: key 'kintree_table': joint {j} has parent {parents[j]}; "
                "parents must precede children"
            )
    if parents[:NUM_JOINTS] != SMPL_PARENTS:
        raise ValueError(
            f"{path}: key 'kintree_table': the first 22 joints do not follow SMPL's tree {SMPL_PARENTS}"
        )

    j_regressor = _array(path, data, "J_regressor", ndim=2)
    if j_regressor.shape != (num_joints, num_vertices):
        raise ValueError(
            f"{path}: key 'J_regressor': expected shape ({num_joints}, {num_vertices}), "
            f"got {j_regressor.shape}"
        )
    weights = _array(path, data, "weights", ndim=2)
    if weights.shape != (num_vertices, num_joints):
        raise ValueError(
            f"{path}: key 'weights': expected shape ({num_vertices}, {num_joints}), got {weights.shape}"
        )
    row_sums = weights.sum(1)
    if np.abs(row_sums - 1.0).max() > _WEIGHT_SUM_TOL:
        worst = row_sums[np.abs(row_sums - 1).argmax()]
        raise ValueError(f"{path}: key 'weights': rows must sum to 1 (worst {worst})")
    # Renormalised in float64 so that the rest pose reproduces the template to round-off
    # (float32 files store the weights to ~1e-7).
    weights = weights / row_sums[:, None]

    shapedirs = _array(path, data, "shapedirs", ndim=3)
    if shapedirs.shape[:2] != (num_vertices, 3):
        raise ValueError(
            f"{path}: key 'shapedirs': expected shape ({num_vertices}, 3, K), got {shapedirs.shape}"
        )
    shapedirs = shapedirs[:, :, :NUM_BETAS]

    posedirs = None
    if "posedirs" in data and data["posedirs"] is not None:
        posedirs = _array(path, data, "posedirs", ndim=3)
        expected = (num_vertices, 3, 9 * (num_joints - 1))
        if posedirs.shape != expected:
            raise ValueError(f"{path}: key 'posedirs': expected shape {expected}, got {posedirs.shape}")
        if not np.any(posedirs):
            posedirs = None

    joint_names = SMPL_JOINT_NAMES
    if "joint_names" in data:
        names = tuple(str(n) for n in np.asarray(data["joint_names"]).ravel()[:NUM_JOINTS])
        if len(names) != NUM_JOINTS:
            raise ValueError(f"{path}: key 'joint_names': expected at least {NUM_JOINTS} names")
        joint_names = names

    head = None
    if "head_vertex_indices" in data:
        head = _array(path, data, "head_vertex_indices", ndim=1, dtype_kind="i").astype(np.int64)
        if head.min() < 0 or head.max() >= num_vertices:
            raise ValueError(f"{path}: key 'head_vertex_indices': indices outside [0, {num_vertices})")

    metadata = {}
    if "metadata_json" in data:
        try:
            metadata = json.loads(str(np.asarray(data["metadata_json"])))
        except (json.JSONDecodeError, TypeError) as exc:
            raise ValueError(f"{path}: key 'metadata_json': not JSON ({exc})") from None
    if "attribution" in data:
        metadata.setdefault("attribution", str(np.asarray(data["attribution"])))

    def t(x, dtype=torch.float64):
        return torch.from_numpy(np.ascontiguousarray(x)).to(dtype)

    return SMPLModel(
        v_template=t(v_template),
        faces=t(faces, torch.int64),
        shapedirs=t(shapedirs),
        posedirs=None if posedirs is None else t(posedirs),
        J_regressor=t(j_regressor),
        parents=parents,
        weights=t(weights),
        joint_names=joint_names,
        head_vertex_indices=None if head is None else t(head, torch.int64),
        metadata=metadata,
        source=str(source),
    )


def load_smpl_model(path: str | os.PathLike) -> SMPLModel:
    """Load an SMPL-format model file (`.npz`, or the official `.pkl`).

    Args:
        path: file path; the suffix picks the reader (`.pkl` or `.npz`).

    Returns:
        The validated `SMPLModel`.

    Raises:
        ValueError: naming the file and the key at fault when the file is missing,
            unreadable, lacks a key, or holds arrays of the wrong shape or with NaN/Inf.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"{path}: no such file")
    suffix = os.path.splitext(path)[1].lower()
    if suffix == ".pkl":
        data = _read_pkl(path)
    elif suffix == ".npz":
        data = _read_npz(path)
    else:
        raise ValueError(f"{path}: expected a .npz or .pkl SMPL model file")
    return smpl_model_from_arrays(data, source=path)


# ----------------------------------------------------------------------------------------
# Skinning


@dataclass(frozen=True)
class LBSOutput:
    """Linear blend skinning results (batched).

    Attributes:
        vertices: (B, V, 3) posed vertices [m].
        joint_transforms: (B, J, 4, 4) world transforms G_k of the joint frames (rotation,
            and the posed joint position as translation) [m].
        skinning_transforms: (B, J, 4, 4) A_k = G_k [I | -J_k]: map rest world points to posed
            world points as joint k moves them.
        rest_joints: (B, J, 3) joint positions of the shaped rest body [m].
    """

    vertices: torch.Tensor
    joint_transforms: torch.Tensor
    skinning_transforms: torch.Tensor
    rest_joints: torch.Tensor


def linear_blend_skinning(
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor | None,
    J_regressor: torch.Tensor,
    parents: tuple[int, ...],
    weights: torch.Tensor,
    betas: torch.Tensor,
    rotations: torch.Tensor,
    trans: torch.Tensor | None = None,
) -> LBSOutput:
    """SMPL's forward pass: shape blend shapes, joints, pose correctives, kinematics, LBS.

    No input checks here (callers validate); everything stays in the dtype and device of
    `v_template`, differentiable with respect to every tensor argument.

    Args:
        v_template: (V, 3) rest template [m].
        shapedirs: (V, 3, K) shape blend shapes.
        posedirs: (V, 3, 9 (J - 1)) pose correctives, or None.
        J_regressor: (J, V) joint regressor.
        parents: (J,) parents, -1 for the root; parents precede children.
        weights: (V, J) skinning weights.
        betas: (B, K') shape coefficients, K' <= K (missing ones are zero).
        rotations: (B, J, 3, 3) each joint's rotation relative to its parent.
        trans: (B, 3) global translation [m], or None.

    Returns:
        `LBSOutput`.
    """
    batch = rotations.shape[0]
    num_joints = len(parents)
    k = betas.shape[1]
    v_shaped = v_template + torch.einsum("vck,bk->bvc", shapedirs[:, :, :k], betas)  # (B, V, 3)
    joints = torch.einsum("jv,bvc->bjc", J_regressor, v_shaped)  # (B, J, 3)
    v_posed = v_shaped
    if posedirs is not None:
        eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
        pose_feature = (rotations[:, 1:] - eye).reshape(batch, -1)
        v_posed = v_shaped + torch.einsum("vcp,bp->bvc", posedirs, pose_feature)

    # Kinematic chain: G_k = G_parent [R_k | J_k - J_parent], G_root = [R_root | J_root].
    offsets = joints.clone()
    offsets[:, 1:] = joints[:, 1:] - joints[:, list(parents[1:])]
    local = rigid_transform(rotations, offsets)  # (B, J, 4, 4)
    chain = [local[:, 0]]
    for j in range(1, num_joints):
        chain.append(chain[parents[j]] @ local[:, j])
    world = torch.stack(chain, 1)
    # A_k = G_k [I | -J_k]: the transform that moves rest points rigidly with joint k.
    skin_t = world[..., :3, 3] - (world[..., :3, :3] @ joints[..., None])[..., 0]
    skinning = rigid_transform(world[..., :3, :3], skin_t)
    if trans is not None:
        world = world.clone()
        world[..., :3, 3] = world[..., :3, 3] + trans[:, None]
        skinning = skinning.clone()
        skinning[..., :3, 3] = skinning[..., :3, 3] + trans[:, None]

    blended = torch.einsum("vj,bjrc->bvrc", weights, skinning[:, :, :3, :])  # (B, V, 3, 4)
    vertices = (blended[..., :3] @ v_posed[..., None])[..., 0] + blended[..., 3]
    return LBSOutput(
        vertices=vertices, joint_transforms=world, skinning_transforms=skinning, rest_joints=joints
    )


def pose_rotations(poses: torch.Tensor, num_joints: int) -> torch.Tensor:
    """(B, J, 3, 3) joint rotations from (B, 66) axis-angle poses; joints past 22 identity."""
    rot = axis_angle_to_matrix(poses.reshape(poses.shape[0], NUM_JOINTS, 3))
    if num_joints > NUM_JOINTS:
        eye = torch.eye(3, dtype=poses.dtype, device=poses.device)
        extra = eye.expand(poses.shape[0], num_joints - NUM_JOINTS, 3, 3)
        rot = torch.cat([rot, extra], 1)
    return rot
