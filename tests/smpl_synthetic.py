"""A small synthetic SMPL-format model for tests: arrays, `.npz` and official-style `.pkl`.

The `.pkl` imitates SMPL's official files without chumpy or scipy: a Python-2 style protocol-2
pickle (numpy under `numpy.core`, byte strings as Python-2 `str`) of a
dict whose `v_template`, `shapedirs` and `weights` are chumpy `Ch` objects (class global
`chumpy.ch.Ch`, state dict with the array under `x`), whose `J_regressor` is a scipy
`csc_matrix` (class global `scipy.sparse.csc.csc_matrix`, state dict with data / indices /
indptr / _shape), whose `kintree_table` has the root parent 2^32 - 1, plus a few extra keys.
"""

from __future__ import annotations

import copyreg
import io
import pickle
import struct

import numpy as np

SMPL_PARENTS_24 = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
VERTICES_PER_JOINT = 2


def synthetic_smpl_arrays(
    num_joints: int = 24, num_betas: int = 10, posedirs: bool = True, seed: int = 0
) -> dict:
    """SMPL-format arrays: `VERTICES_PER_JOINT` vertices near each joint of a rough skeleton.

    Vertex 2k and 2k + 1 belong mostly to joint k (weight 0.7, the rest to its parent), so
    the head joint (15) owns vertices 30 and 31 with weight 0.7 (the root's own: 1.0).
    """
    rng = np.random.default_rng(seed)
    parents = SMPL_PARENTS_24[:num_joints]
    joints = np.zeros((num_joints, 3))
    for j in range(1, num_joints):
        joints[j] = joints[parents[j]] + rng.normal(0.0, 0.1, 3) + np.array([0.0, 0.08, 0.0])
    num_vertices = VERTICES_PER_JOINT * num_joints
    owner = np.repeat(np.arange(num_joints), VERTICES_PER_JOINT)
    v_template = joints[owner] + rng.normal(0.0, 0.03, (num_vertices, 3))
    weights = np.zeros((num_vertices, num_joints))
    for i, j in enumerate(owner):
        if parents[j] < 0:
            weights[i, j] = 1.0
        else:
            weights[i, j] = 0.7
            weights[i, parents[j]] = 0.3
    # Each joint is a weighted mean of its own vertices and one random other vertex.
    regressor = np.zeros((num_joints, num_vertices))
    for j in range(num_joints):
        own = np.nonzero(owner == j)[0]
        regressor[j, own] = 0.4
        regressor[j, (own[0] + 7) % num_vertices] += 0.2
    faces = np.stack([np.arange(num_vertices), (np.arange(num_vertices) + 1) % num_vertices,
                      (np.arange(num_vertices) + 5) % num_vertices], 1)
    root_parent = 2**32 - 1  # as in SMPL's official files
    kintree = np.array([[root_parent if p < 0 else p for p in parents], list(range(num_joints))],
                       dtype=np.int64)
    out = {
        "v_template": v_template,
        "f": faces.astype(np.uint32),
        "J_regressor": regressor,
        "kintree_table": kintree,
        "weights": weights,
        "shapedirs": rng.normal(0.0, 0.01, (num_vertices, 3, num_betas)),
    }
    if posedirs:
        out["posedirs"] = rng.normal(0.0, 0.005, (num_vertices, 3, 9 * (num_joints - 1)))
    return out


def save_npz(path, arrays: dict) -> None:
    np.savez(path, **arrays)


class _Ch:
    """Pickles like chumpy's Ch (a terminal array)."""

    def __init__(self, x):
        self.state = {"x": np.asarray(x), "_dirty_vars": set(), "_itr": None, "_make_dense": False,
                      "_make_sparse": False, "_depends_on_deps": {}}

    def __reduce_ex__(self, protocol):
        return copyreg.__newobj__, (type(self),), self.state


class _CscMatrix:
    """Pickles like an old scipy.sparse.csc_matrix."""

    def __init__(self, dense):
        dense = np.asarray(dense)
        cols = [np.nonzero(dense[:, c])[0] for c in range(dense.shape[1])]
        self.state = {
            "_shape": dense.shape,
            "maxprint": 50,
            "indices": np.concatenate(cols).astype(np.int32),
            "indptr": np.concatenate([[0], np.cumsum([len(c) for c in cols])]).astype(np.int32),
            "data": np.concatenate([dense[c, k] for k, c in enumerate(cols)]),
        }

    def __reduce_ex__(self, protocol):
        return copyreg.__newobj__, (type(self),), self.state


class _Evil:
    """Pickles as a call of os.system: the loader must refuse it."""

    def __reduce__(self):
        import os

        return os.system, ("true",)


_GLOBAL_NAMES = {_Ch: ("chumpy.ch", "Ch"), _CscMatrix: ("scipy.sparse.csc", "csc_matrix")}


class _SMPLStylePickler(pickle._Pickler):
    """Writes like Python 2 did: the stand-ins above under chumpy's and scipy's global names,
    numpy's functions under `numpy.core` (numpy 2 renamed it `numpy._core`), and byte
    strings as Python-2 `str` (BINSTRING opcodes, read back as latin1 text)."""

    dispatch = pickle._Pickler.dispatch.copy()

    def save_global(self, obj, name=None):
        module = getattr(obj, "__module__", "") or ""
        if obj in _GLOBAL_NAMES:
            module, qualname = _GLOBAL_NAMES[obj]
        elif module.startswith("numpy._core"):
            module, qualname = "numpy.core" + module[len("numpy._core"):], obj.__qualname__
        else:
            super().save_global(obj, name)
            return
        self.write(pickle.GLOBAL + f"{module}\n{qualname}\n".encode())
        self.memoize(obj)

    def save_py2_str(self, obj):
        if len(obj) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(obj)]) + obj)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(obj)) + obj)
        self.memoize(obj)

    dispatch[bytes] = save_py2_str


def official_style_dict(arrays: dict) -> dict:
    """The arrays wrapped the way SMPL's official `.pkl` holds them."""
    out = dict(arrays)
    for key in ("v_template", "shapedirs", "weights"):
        out[key] = _Ch(arrays[key])
    out["J_regressor"] = _CscMatrix(arrays["J_regressor"])
    out["bs_style"] = "lbs"
    out["bs_type"] = "lrotmin"
    out["J"] = np.asarray(arrays["J_regressor"]) @ np.asarray(arrays["v_template"])
    return out


def save_official_pkl(path, arrays: dict, evil: bool = False) -> None:
    """Write `arrays` as an official-style SMPL pickle (protocol 2, chumpy/scipy globals)."""
    data = official_style_dict(arrays)
    if evil:
        data["extra"] = _Evil()
    buffer = io.BytesIO()
    _SMPLStylePickler(buffer, protocol=2).dump(data)
    with open(path, "wb") as handle:
        handle.write(buffer.getvalue())
