"""Input normalisation shared by the exporters and the preview renderer.

Exporters and pictures run on the host: they accept torch tensors (any device, gradients
ignored) or numpy arrays, check them with the project's one validator (ValueError naming the
argument), and hand back float numpy arrays with a leading frame axis.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from hairwarp._validate import FLOAT_DTYPES, check_tensor

INT_DTYPES = (torch.int32, torch.int64)


def as_tensor(name: str, x) -> torch.Tensor:
    """A torch tensor or numpy array as a detached CPU tensor; anything else -> ValueError."""
    if isinstance(x, np.ndarray):
        if x.dtype.kind not in "fiu":
            raise ValueError(f"{name}: expected a numeric array, got dtype {x.dtype}")
        return torch.from_numpy(np.ascontiguousarray(x))
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    raise ValueError(f"{name}: expected a torch.Tensor or numpy.ndarray, got {type(x).__name__}")


def _non_empty(name: str, t: torch.Tensor, what: str) -> None:
    if t.numel() == 0:
        raise ValueError(f"{name}: expected a non-empty {what}, got shape {tuple(t.shape)}")


def hair_frames(name: str, hair, *, frames: bool | None = None) -> tuple[np.ndarray, bool]:
    """Hair `(T, M, N, 3)` or `(M, N, 3)` [m] -> (`(T, M, N, 3)` numpy array, had a frame axis).

    Args:
        name: argument name for errors.
        hair: strand vertex positions; N >= 2 (a strand is a polyline).
        frames: True accepts only `(T, M, N, 3)`, False only `(M, N, 3)`, None both.
    """
    t = as_tensor(name, hair)
    want = {True: "(T, M, N, 3)", False: "(M, N, 3)", None: "(T, M, N, 3) or (M, N, 3)"}[frames]
    allowed = {True: (4,), False: (3,), None: (3, 4)}[frames]
    if t.dim() not in allowed or t.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    check_tensor(name, t, dtypes=FLOAT_DTYPES)
    _non_empty(name, t, "hair tensor")
    if t.shape[-2] < 2:
        raise ValueError(f"{name}: expected at least 2 vertices per strand, got shape {tuple(t.shape)}")
    batched = t.dim() == 4
    a = t.numpy()
    return (a if batched else a[None]), batched


def body_frames(
    name: str, vertices, num_frames: int | None = None, *, frames: bool | None = None
) -> np.ndarray:
    """Body vertices `(T, V, 3)` or `(V, 3)` [m] -> `(T_body, V, 3)`, T_body in {1, num_frames}."""
    t = as_tensor(name, vertices)
    want = {True: "(T, V, 3)", False: "(V, 3)", None: "(T, V, 3) or (V, 3)"}[frames]
    allowed = {True: (3,), False: (2,), None: (2, 3)}[frames]
    if t.dim() not in allowed or t.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape {want}, got {tuple(t.shape)}")
    check_tensor(name, t, dtypes=FLOAT_DTYPES)
    _non_empty(name, t, "vertex tensor")
    a = t.numpy()
    a = a if a.ndim == 3 else a[None]
    if num_frames is not None and a.shape[0] not in (1, num_frames):
        raise ValueError(f"{name}: expected 1 or {num_frames} frames (as the hair has), got {a.shape[0]}")
    return a


def faces_array(name: str, faces, num_vertices: int) -> np.ndarray:
    """Triangle indices `(F, 3)` int32/int64 in [0, V) -> int64 numpy array."""
    t = as_tensor(name, faces)
    check_tensor(name, t, shape=(None, 3), dtypes=INT_DTYPES)
    _non_empty(name, t, "face tensor")
    a = t.numpy().astype(np.int64, copy=False)
    lo, hi = int(a.min()), int(a.max())
    if lo < 0 or hi >= num_vertices:
        raise ValueError(f"{name}: vertex indices must lie in [0, {num_vertices}), got range [{lo}, {hi}]")
    return a


def body_pair(vertices, faces, num_frames: int | None = None, *, frames: bool | None = None):
    """Validate (body_vertices, body_faces) together: both or neither."""
    if vertices is None and faces is None:
        return None, None
    if vertices is None:
        raise ValueError("body_vertices: required when body_faces is given")
    if faces is None:
        raise ValueError("body_faces: required when body_vertices is given")
    v = body_frames("body_vertices", vertices, num_frames, frames=frames)
    return v, faces_array("body_faces", faces, v.shape[1])


def per_vertex_frames(name: str, values, hair_shape: tuple[int, ...]) -> np.ndarray:
    """Per-vertex scalars `(T, M, N)` or `(M, N)` matching hair `(T, M, N, 3)` -> `(T, M, N)`."""
    t = as_tensor(name, values)
    num_frames, m, n = hair_shape[:3]
    if tuple(t.shape) == (m, n):
        t = t[None]
    if t.dim() != 3 or tuple(t.shape[1:]) != (m, n) or t.shape[0] not in (1, num_frames):
        want = f"({m}, {n})" if num_frames == 1 else f"({num_frames}, {m}, {n})"
        raise ValueError(f"{name}: expected shape {want} (one value per hair vertex), got {tuple(t.shape)}")
    check_tensor(name, t, dtypes=FLOAT_DTYPES)
    return np.broadcast_to(t.numpy(), (num_frames, m, n))


def check_positive_number(name: str, value) -> float:
    """A finite number > 0 (fps, widths, dpi)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite positive number, got {value!r}")
    return v


def check_path(name: str, path, suffixes: tuple[str, ...]) -> str:
    """A path whose extension is one of `suffixes` (lower case, with the dot); parents created."""
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{name}: expected a file path, got {type(path).__name__}")
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in suffixes:
        raise ValueError(f"{name}: expected a file ending in {' or '.join(suffixes)}, got {path!r}")
    return path


def ensure_parent(path: str) -> None:
    """Create the folder that will hold `path`."""
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
