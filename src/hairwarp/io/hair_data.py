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

from hairwarp._validate import check_positive
from hairwarp.scene.hairstyles import Hairstyle, as_strand_list, scalp_arrays
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
    head_points=None,
) -> Hairstyle:
    """Load a `.data` hairstyle onto the scalp grid, in our frame (metres, y up, face +z).

    Steps: read; convert units and the up axis; place it on the head (`align`); drop strands
    with fewer than 2 vertices or shorter than `min_length` (Section 3.1); resample to
    `num_vertices` by arc length; map each root to the nearest scalp root.

    Args:
        path: the `.data` file (PERM files: y up, face +z, centimetres).
        scalp: the scalp whose grid roots the strands attach to.
        units: the file's length unit, "m", "cm" or "mm".
        up: the file's up axis, "y" or "z" (z-up data are rotated by -90 degrees about x).
        num_vertices: vertices per output strand (100 in the paper).
        min_length: strands shorter than this [m] are dropped.
        align: "none" (the file's placement), "roots" (translate the mean root onto the mean
            scalp root), "similarity" (ICP with scale onto the head: `hairwarp.scene.groom`)
            or "auto" (similarity when the roots lie off the scalp).
        snap_roots: translate each strand so its root sits exactly on its scalp root.
        head_points: (P, 3) rest head surface [m], the similarity fit's target (default: the
            scalp grid roots).

    Returns:
        A `Hairstyle`: strands (M, num_vertices, 3) float32 [m]; root_index the nearest scalp
        root of each strand; filtered the file strand indices dropped; info with the keys
        "root_distance_mean", "root_distance_max", "root_distance_median" [m] (root to
        nearest scalp root, before snapping), "num_file_strands", "translation" [m], "scale",
        and "fit" (the fit's description, or None).

    Raises:
        ValueError: for a malformed file (naming it), bad arguments, or when no strand
            survives the filtering.
    """
    from hairwarp.scene.groom import attach_strands, place_groom

    if units not in LENGTH_UNITS:
        raise ValueError(f"units: expected one of {sorted(LENGTH_UNITS)}, got {units!r}")
    if up not in _UP_AXES:
        raise ValueError(f"up: expected one of {sorted(_UP_AXES)}, got {up!r}")
    modes = {"none": "none", "roots": "translate", "similarity": "similarity", "auto": "auto"}
    if align not in modes:
        raise ValueError(f"align: expected one of {list(modes)}, got {align!r}")
    check_positive("min_length", min_length, allow_zero=True)
    if int(num_vertices) < 2:
        raise ValueError(f"num_vertices: expected an int >= 2, got {num_vertices}")
    scalp_arrays(scalp)  # checks the scalp before reading the file
    name = os.fspath(path)
    raw = read_hair_data(name)
    rot = _UP_AXES[up] * LENGTH_UNITS[units]
    strands = [a.astype(np.float64) @ rot.T for a in raw]
    if not any(len(a) >= 2 for a in strands):
        raise ValueError(f"{name}: no strand with at least 2 vertices")
    head = scalp_arrays(scalp)[0] if head_points is None else np.asarray(head_points, dtype=np.float64)
    try:
        style, fit = place_groom(strands, scalp, head, fit=modes[align], num_vertices=int(num_vertices),
                                 min_length=float(min_length), name=os.path.basename(name))
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    if not snap_roots:
        moved = [a if fit is None else fit.apply(a) for a in strands]
        style = attach_strands(moved, scalp, num_vertices=int(num_vertices), min_length=float(min_length),
                               snap_roots=False, name=style.name, info=style.info)
    style.info["translation"] = np.zeros(3) if fit is None else fit.translation
    style.info["scale"] = 1.0 if fit is None else fit.scale
    return style
