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
        A list of S float32 arrays of shape (n_i, 3), in the file's units and axes (views into
        one array: `read_hair_data_flat`).

    Raises:
        ValueError: naming the file and what is wrong (empty, truncated, negative or absurd
            counts, NaN/Inf coordinates, trailing bytes).
    """
    points, counts = read_hair_data_flat(path)
    if len(counts) == 0:
        return []
    return np.split(points, np.cumsum(counts)[:-1])


def read_hair_data_flat(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a `.data` strand file as one array: the strands' vertices concatenated.

    One pass over the vertex counts (each strand's offset depends on the ones before it), then
    the coordinates gathered and checked in single numpy operations.

    Args:
        path: file path.

    Returns:
        (points (V, 3) float32 in the file's units and axes, counts (S,) int64): strand i is
        points[sum(counts[:i]) : sum(counts[:i + 1])].

    Raises:
        ValueError: as `read_hair_data`, with the same messages (the first fault in file order).
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
    counts = []
    fault = None  # a structural fault at strand len(counts); strands before it are whole
    offset = 4
    unpack = _INT.unpack_from
    for i in range(count):
        if offset + 4 > size:
            fault = f"{name}: truncated: file ends before the vertex count of strand {i} of {count}"
            break
        (n,) = unpack(data, offset)
        offset += 4
        if n < 0:
            fault = f"{name}: strand {i} has a negative vertex count {n}"
            break
        end = offset + 12 * n
        if end > size:
            fault = (f"{name}: truncated: strand {i} declares {n} vertices ({12 * n} bytes) but only "
                     f"{size - offset} bytes remain")
            break
        counts.append(n)
        offset = end
    counts = np.array(counts, dtype=np.int64)
    # The whole strands as 4-byte words: each strand's count word, then its 3 n coordinates.
    whole = 4 + 4 * len(counts) + 12 * int(counts.sum())
    words = np.frombuffer(data, dtype="<f4", count=(whole - 4) // 4, offset=4)
    is_coordinate = np.ones(len(words), dtype=bool)
    is_coordinate[np.arange(len(counts)) + 3 * (np.cumsum(counts) - counts)] = False
    points = words[is_coordinate].astype(np.float32, copy=False).reshape(-1, 3)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        row = int(np.argmin(finite))
        strand = int(np.searchsorted(np.cumsum(counts), row, side="right"))
        vertex = row - int(counts[:strand].sum())
        raise ValueError(f"{name}: strand {strand} vertex {vertex} has a NaN or Inf coordinate")
    if fault is not None:
        raise ValueError(fault)
    if offset != size:
        raise ValueError(f"{name}: {size - offset} trailing bytes after the last of {count} strands")
    return points, counts


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
    from hairwarp.scene.groom import flat_strand_lengths, flatten_strands

    return flat_strand_lengths(*flatten_strands(as_strand_list("strands", strands)))


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
    orient_roots: bool = True,
) -> Hairstyle:
    """Load a `.data` hairstyle onto the scalp grid, in our frame (metres, y up, face +z).

    Steps: read; convert units and the up axis; place it on the head (`align`); drop strands
    with fewer than 2 vertices or shorter than `min_length` (Section 3.1); resample to
    `num_vertices` by arc length; map each root to the nearest scalp root (and after a
    similarity fit, turn the strand there from the file's scalp normal to ours).

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
        orient_roots: after a similarity fit, turn the root part of each snapped strand so it
            leaves our scalp at the angle it left the file's (`hairwarp.scene.groom`).

    Returns:
        A `Hairstyle`: strands (M, num_vertices, 3) float32 [m]; root_index the nearest scalp
        root of each strand; filtered the file strand indices dropped; info with the keys
        "root_distance_mean", "root_distance_max", "root_distance_median" [m] (root to
        nearest scalp root, before snapping), "num_file_strands", "translation" [m], "scale",
        "fit" (the fit's description, or None), and after a turn at the roots
        "root_rotation_deg_median" / "_max" [deg].

    Raises:
        ValueError: for a malformed file (naming it), bad arguments, or when no strand
            survives the filtering.
    """
    from hairwarp.scene.groom import attach_flat_strands, place_flat_groom, transform_points

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
    raw, counts = read_hair_data_flat(name)
    points = transform_points(raw, _UP_AXES[up] * LENGTH_UNITS[units])
    if not (counts >= 2).any():
        raise ValueError(f"{name}: no strand with at least 2 vertices")
    head = scalp_arrays(scalp)[0] if head_points is None else np.asarray(head_points, dtype=np.float64)
    try:
        style, fit = place_flat_groom(points, counts, scalp, head, fit=modes[align], num_vertices=int(num_vertices),
                                      min_length=float(min_length), name=os.path.basename(name),
                                      orient_roots=orient_roots)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    if not snap_roots:
        moved = points if fit is None else fit.apply(points)
        style = attach_flat_strands(moved, counts, scalp, num_vertices=int(num_vertices), min_length=float(min_length),
                                    snap_roots=False, name=style.name, info=style.info)
    style.info["translation"] = np.zeros(3) if fit is None else fit.translation
    style.info["scale"] = 1.0 if fit is None else fit.scale
    return style
