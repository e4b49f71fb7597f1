"""USC-HairSalon `.data` strand files: read, write, resample, and load onto the scalp grid.

The format (little-endian): int32 strand count S, then for each strand an int32 vertex count
n_i followed by n_i * 3 float32 coordinates (x, y, z). Strands may have different vertex
counts (USC-HairSalon marks bald roots with 1-vertex strands). PERM's `.data` files are y up,
face +z, in centimetres; ours are metres, y up, face +z.
"""

from __future__ import annotations

import os
import struct

import numpy as np
import torch

from hairwarp._validate import check_positive
from hairwarp.scene.hairstyles import Hairstyle, as_strand_list, resample_strands, scalp_arrays
from hairwarp.scene.scalp import Scalp

_INT = struct.Struct("<i")
# Strands shorter than this [m] are dropped by `load_hairstyle` (Section 3.1 filters overly
# short strands; USC-HairSalon's bald-root markers have one vertex and no length at all).
DEFAULT_MIN_LENGTH = 0.02


def read_hair_data(path: str | os.PathLike) -> list[np.ndarray]:
    """Read a `.data` strand file.

    Args:
        path: file path.

    Returns:
        A list of S float32 arrays of shape (n_i, 3), in the file's units and axes.

    Raises:
        ValueError: naming the file and what is wrong (empty, truncated, negative or absurd
            counts, NaN/Inf coordinates, trailing bytes).
    """
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            data = f.read()
    except OSError as e:
        raise ValueError(f"{name}: cannot read ({e.strerror or e})") from e
    size = len(data)
    if size == 0:
        raise ValueError(f"{name}: empty file")
    if size < 4:
        raise ValueError(f"{name}: truncated: {size} bytes, no room for the int32 strand count")
    (count,) = _INT.unpack_from(data, 0)
    if count < 0:
        raise ValueError(f"{name}: negative strand count {count}")
    # Each strand needs at least its 4-byte vertex count.
    if count > (size - 4) // 4:
        raise ValueError(f"{name}: strand count {count} is absurd for a file of {size} bytes")
    strands = []
    offset = 4
    for i in range(count):
        if offset + 4 > size:
            raise ValueError(f"{name}: truncated: file ends before the vertex count of strand {i} of {count}")
        (n,) = _INT.unpack_from(data, offset)
        offset += 4
        if n < 0:
            raise ValueError(f"{name}: strand {i} has a negative vertex count {n}")
        end = offset + 12 * n
        if end > size:
            raise ValueError(
                f"{name}: truncated: strand {i} declares {n} vertices ({12 * n} bytes) but only "
                f"{size - offset} bytes remain"
            )
        xyz = np.frombuffer(data, dtype="<f4", count=3 * n, offset=offset).reshape(n, 3)
        if not np.isfinite(xyz).all():
            bad = int(np.nonzero(~np.isfinite(xyz).all(axis=1))[0][0])
            raise ValueError(f"{name}: strand {i} vertex {bad} has a NaN or Inf coordinate")
        strands.append(xyz.astype(np.float32))
        offset = end
    if offset != size:
        raise ValueError(f"{name}: {size - offset} trailing bytes after the last of {count} strands")
    return strands


def write_hair_data(path: str | os.PathLike, strands) -> None:
    """Write strands to a `.data` file (float32, little-endian).

    Args:
        path: file path.
        strands: a sequence of (n_i, 3) arrays or tensors, or one (S, N, 3) array/tensor.

    Raises:
        ValueError: if a strand is not (n, 3) or holds NaN/Inf.
    """
    name = os.fspath(path)
    items = as_strand_list("strands", strands)
    if len(items) > 2**31 - 1:
        raise ValueError(f"strands: too many strands for an int32 count: {len(items)}")
    parts = [_INT.pack(len(items))]
    for a in items:
        parts.append(_INT.pack(a.shape[0]))
        parts.append(np.ascontiguousarray(a, dtype="<f4").tobytes())
    with open(name, "wb") as f:
        f.write(b"".join(parts))


def strand_lengths(strands) -> np.ndarray:
    """Arc length of each strand [file units], (S,) float64."""
    items = as_strand_list("strands", strands)
    return np.array([
        float(np.linalg.norm(np.diff(np.asarray(a, dtype=np.float64), axis=0), axis=1).sum()) for a in items
    ])


_UP_AXES = {
    "y": np.eye(3),
    # z up -> y up: a rotation of -90 degrees about x, (x, y, z) -> (x, z, -y).
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}
# Metres per file unit.
LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def load_hairstyle(
    path: str | os.PathLike,
    scalp: Scalp,
    units: str = "cm",
    up: str = "y",
    num_vertices: int = 100,
    min_length: float = DEFAULT_MIN_LENGTH,
    align: str = "none",
    snap_roots: bool = True,
) -> Hairstyle:
    """Load a `.data` hairstyle onto the scalp grid, in our frame (metres, y up, face +z).

    Steps: read; convert units and the up axis; optionally translate it onto the scalp;
    drop strands with fewer than 2 vertices or shorter than `min_length` (Section 3.1);
    resample to `num_vertices` by arc length; map each root to the nearest scalp root.

    Args:
        path: the `.data` file (PERM files: y up, face +z, centimetres).
        scalp: the scalp whose grid roots the strands attach to.
        units: the file's length unit, "m", "cm" or "mm".
        up: the file's up axis, "y" or "z" (z-up data are rotated by -90 degrees about x).
        num_vertices: vertices per output strand (100 in the paper).
        min_length: strands shorter than this [m] are dropped.
        align: "none", or "roots" to translate the hair so the mean of its root positions
            matches the mean scalp root position (a crude stand-in for the paper's ICP).
        snap_roots: translate each strand so its root sits exactly on its scalp root.

    Returns:
        A `Hairstyle`: strands (M, num_vertices, 3) float32 [m]; root_index the nearest scalp
        root of each strand; filtered the file strand indices dropped; info with the keys
        "root_distance_mean", "root_distance_max", "root_distance_median" [m] (root to
        nearest scalp root, before snapping), "num_file_strands", "translation" [m].

    Raises:
        ValueError: for a malformed file (naming it), bad arguments, or when no strand
            survives the filtering.
    """
    if units not in LENGTH_UNITS:
        raise ValueError(f"units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
    if up not in _UP_AXES:
        raise ValueError(f"up: expected one of {sorted(_UP_AXES)}, got {up!r}")
    if align not in ("none", "roots"):
        raise ValueError(f"align: expected 'none' or 'roots', got {align!r}")
    check_positive("min_length", min_length, allow_zero=True)
    if int(num_vertices) < 2:
        raise ValueError(f"num_vertices: expected an int >= 2, got {num_vertices}")
    scalp_pos, scalp_nrm, scalp_uv = scalp_arrays(scalp)
    name = os.fspath(path)
    raw = read_hair_data(name)
    rot = _UP_AXES[up] * LENGTH_UNITS[units]
    strands = [a.astype(np.float64) @ rot.T for a in raw]
    translation = np.zeros(3)
    if align == "roots":
        roots = np.array([a[0] for a in strands if len(a) >= 2])
        if len(roots) == 0:
            raise ValueError(f"{name}: no strand with at least 2 vertices")
        translation = scalp_pos.mean(axis=0) - roots.mean(axis=0)
        strands = [a + translation for a in strands]
    lengths = np.array([float(np.linalg.norm(np.diff(a, axis=0), axis=1).sum()) if len(a) >= 2 else 0.0
                        for a in strands])
    keep = np.nonzero((lengths >= float(min_length)) & (lengths > 0))[0]
    filtered = np.nonzero(~np.isin(np.arange(len(strands)), keep))[0]
    if len(keep) == 0:
        raise ValueError(
            f"{name}: no strand is at least {min_length} m long (of {len(strands)} strands; check `units`)"
        )
    res = resample_strands([strands[i] for i in keep], int(num_vertices), dtype=torch.float64).numpy()
    # Nearest scalp root of each strand root, in chunks to bound the distance matrix.
    nearest = np.empty(len(res), dtype=np.int64)
    dist = np.empty(len(res))
    for start in range(0, len(res), 4096):
        r = res[start:start + 4096, 0]
        d2 = ((r[:, None, :] - scalp_pos[None, :, :]) ** 2).sum(-1)
        j = d2.argmin(axis=1)
        nearest[start:start + 4096] = j
        dist[start:start + 4096] = np.sqrt(d2[np.arange(len(r)), j])
    if snap_roots:
        res = res + (scalp_pos[nearest] - res[:, 0])[:, None, :]
        res[:, 0] = scalp_pos[nearest]
    return Hairstyle(
        strands=torch.tensor(res, dtype=torch.float32),
        root_uv=torch.tensor(scalp_uv[nearest], dtype=torch.float32),
        root_normals=torch.tensor(scalp_nrm[nearest], dtype=torch.float32),
        root_index=torch.tensor(nearest, dtype=torch.int64),
        filtered=torch.tensor(filtered, dtype=torch.int64),
        name=os.path.basename(name),
        info={
            "root_distance_mean": float(dist.mean()),
            "root_distance_median": float(np.median(dist)),
            "root_distance_max": float(dist.max()),
            "num_file_strands": len(strands),
            "translation": translation,
        },
    )
