"""Hair and body export to the plain formats artists' tools read: OBJ and PLY.

- Hair as polylines: OBJ `v` lines and one `l` line per strand; PLY (ASCII or binary
  little-endian) `vertex` (x, y, z float) and `edge` (vertex1, vertex2 int) elements, strands
  stored one after the other (vertex m * N + i is vertex i of strand m). Blender, Houdini,
  MeshLab and trimesh import both as curves / line sets.
- Bodies as triangle meshes: OBJ `v` + `f` lines, PLY `vertex` + `face` elements.
- Sequences: `export_frames` writes one numbered file per frame (hair and body) into a folder.
- USC-HairSalon `.data` (the HairSalon / PERM strand format): `write_hair_data` and
  `read_hair_data`, re-exported from `hairwarp.io.hair_data` (strands of any lengths; written in
  the units given, metres for hairwarp data).
- USD (animated, one file): `hairwarp.io.usd.write_usd`.

All in hairwarp's frame: metres, y up. Writers accept torch tensors (any device, float32 or
float64) or numpy arrays; text files keep 9 significant digits for float32 data and 17 for
float64, so what is read back is bit-identical. Readers return float32 tensors (float64 with
`dtype=torch.float64`).
"""

from __future__ import annotations

import os

import numpy as np
import torch

from hairwarp.io._arrays import (
    body_frames,
    body_pair,
    check_path,
    ensure_parent,
    faces_array,
    hair_frames,
)
from hairwarp.io.hair_data import read_hair_data, write_hair_data

__all__ = [
    "export_frames",
    "read_hair_data",
    "read_hair_obj",
    "read_hair_ply",
    "read_obj",
    "read_ply",
    "write_hair_data",
    "write_hair_obj",
    "write_hair_ply",
    "write_mesh_obj",
    "write_mesh_ply",
]

MESH_FORMATS = ("obj", "ply")


def _float_format(a: np.ndarray) -> str:
    """Shortest printf format that round-trips the array's precision exactly."""
    return "%.17g" if a.dtype == np.float64 else "%.9g"


def _points(a: np.ndarray) -> np.ndarray:
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float32)


def _write_obj(path: str, vertices: np.ndarray, element: str, indices: np.ndarray, header: str) -> None:
    """OBJ with `v` lines and one `element` line ('l' or 'f') per row of 0-based `indices`."""
    ensure_parent(path)
    fmt = _float_format(vertices)
    with open(path, "w") as f:
        f.write(f"# {header}\n# written by hairwarp: metres, y up\n")
        np.savetxt(f, vertices, fmt=f"v {fmt} {fmt} {fmt}")
        np.savetxt(f, indices + 1, fmt=element + " %d" * indices.shape[1])


def write_hair_obj(path: str | os.PathLike, hair) -> str:
    """Write one frame of hair as OBJ polylines (`v` lines, then one `l` line per strand).

    Args:
        path: `.obj` file; its folder is created.
        hair: (M, N, 3) strand vertices [m], N >= 2.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".obj",))
    h, _ = hair_frames("hair", hair, frames=False)
    m, n = h.shape[1:3]
    _write_obj(path, _points(h[0].reshape(-1, 3)), "l", np.arange(m * n).reshape(m, n),
               f"hair: {m} strands x {n} vertices")
    return path


def write_mesh_obj(path: str | os.PathLike, vertices, faces) -> str:
    """Write a triangle mesh (a body frame) as OBJ (`v` and `f` lines).

    Args:
        path: `.obj` file.
        vertices: (V, 3) [m].
        faces: (F, 3) int32/int64 triangles.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".obj",))
    v = body_frames("vertices", vertices, frames=False)[0]
    fa = faces_array("faces", faces, len(v))
    _write_obj(path, _points(v), "f", fa, f"mesh: {len(v)} vertices, {len(fa)} triangles")
    return path


def read_obj(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> dict:
    """Read an OBJ's vertices, faces (fan-triangulated) and polylines (what our writers write).

    Args:
        path: `.obj` file.
        dtype: float dtype of the returned vertices.

    Returns:
        dict with `vertices` (V, 3) tensor, `faces` (F, 3) int64 tensor (0-based) and `lines`,
        a list of int64 tensors, one per `l` line (0-based). Texture/normal indices
        (`f 1/2/3`) are ignored.

    Raises:
        ValueError: when the file is missing or malformed.
    """
    path = check_path("path", path, (".obj",))
    if not os.path.isfile(path):
        raise ValueError(f"path: no such file {path!r}")
    vertices, faces, lines = [], [], []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if parts[0] == "v":
                    if len(parts) < 4:
                        raise ValueError("fewer than 3 coordinates")
                    vertices.append([float(x) for x in parts[1:4]])
                elif parts[0] in ("f", "l"):
                    idx = [int(p.split("/")[0]) for p in parts[1:]]
                    # Negative OBJ indices count back from the last vertex read so far.
                    idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
                    if parts[0] == "l":
                        lines.append(idx)
                    else:
                        faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
            except (ValueError, IndexError):
                raise ValueError(f"path: malformed OBJ line {number} of {path!r}: {line.strip()!r}") from None
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    fa = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    for idx in [fa.reshape(-1)] + [np.asarray(ln) for ln in lines]:
        if idx.size and (idx.min() < 0 or idx.max() >= len(v)):
            raise ValueError(f"path: {path!r} refers to vertices beyond the {len(v)} it holds")
    return {
        "vertices": torch.from_numpy(v).to(dtype),
        "faces": torch.from_numpy(fa),
        "lines": [torch.as_tensor(ln, dtype=torch.int64) for ln in lines],
    }


def _strands_from_chains(vertices: torch.Tensor, chains: list[np.ndarray], path: str) -> torch.Tensor:
    """Equal-length vertex chains -> (M, N, 3) hair."""
    if not chains:
        raise ValueError(f"path: {path!r} holds no polylines")
    lengths = {len(c) for c in chains}
    if len(lengths) != 1:
        raise ValueError(
            f"path: the strands of {path!r} have different vertex counts {sorted(lengths)[:5]}; "
            "resample them to one count first"
        )
    return vertices[torch.as_tensor(np.stack(chains))]


def read_hair_obj(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Read hair written by `write_hair_obj`: one `l` line per strand, all of one length.

    Returns:
        (M, N, 3) tensor [m].

    Raises:
        ValueError: when the file has no polylines or strands of different lengths.
    """
    data = read_obj(path, dtype)
    return _strands_from_chains(data["vertices"], [ln.numpy() for ln in data["lines"]], os.fspath(path))


# --- PLY -----------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _write_ply(path: str, vertices: np.ndarray, edges=None, faces=None, binary: bool = True,
               comment: str = "") -> None:
    ensure_parent(path)
    ftype = "double" if vertices.dtype == np.float64 else "float"
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
             "comment written by hairwarp: metres, y up"]
    if comment:
        lines.append(f"comment {comment}")
    lines += [f"element vertex {len(vertices)}"] + [f"property {ftype} {c}" for c in "xyz"]
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    if edges is not None:
        lines += [f"element edge {len(edges)}", "property int vertex1", "property int vertex2"]
    header = ("\n".join(lines + ["end_header"]) + "\n").encode("ascii")
    with open(path, "wb") as f:
        f.write(header)
        if binary:
            f.write(vertices.astype(vertices.dtype.newbyteorder("<")).tobytes())
            if faces is not None:
                rec = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
                rec["n"], rec["i"] = 3, faces
                f.write(rec.tobytes())
            if edges is not None:
                f.write(edges.astype("<i4").tobytes())
        else:
            fmt = _float_format(vertices)
            np.savetxt(f, vertices, fmt=f"{fmt} {fmt} {fmt}")
            if faces is not None:
                np.savetxt(f, faces, fmt="3 %d %d %d")
            if edges is not None:
                np.savetxt(f, edges, fmt="%d %d")


def _strand_edges(m: int, n: int) -> np.ndarray:
    """(M * (N-1), 2) edges (m*N + i, m*N + i + 1) of strands stored one after the other."""
    start = (np.arange(m)[:, None] * n + np.arange(n - 1)[None, :]).reshape(-1)
    return np.stack([start, start + 1], axis=1)


def write_hair_ply(path: str | os.PathLike, hair, binary: bool = True) -> str:
    """Write one frame of hair as a PLY line set (vertices and strand edges).

    Args:
        path: `.ply` file.
        hair: (M, N, 3) strand vertices [m], N >= 2.
        binary: binary little-endian (small, fast) or ASCII.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".ply",))
    h, _ = hair_frames("hair", hair, frames=False)
    m, n = h.shape[1:3]
    _write_ply(path, _points(h[0].reshape(-1, 3)), edges=_strand_edges(m, n), binary=bool(binary),
               comment=f"hair {m} strands x {n} vertices")
    return path


def write_mesh_ply(path: str | os.PathLike, vertices, faces, binary: bool = True) -> str:
    """Write a triangle mesh (a body frame) as PLY.

    Args:
        path: `.ply` file.
        vertices: (V, 3) [m].
        faces: (F, 3) int32/int64 triangles.
        binary: binary little-endian or ASCII.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument.
    """
    path = check_path("path", path, (".ply",))
    v = body_frames("vertices", vertices, frames=False)[0]
    fa = faces_array("faces", faces, len(v))
    _write_ply(path, _points(v), faces=fa, binary=bool(binary))
    return path


def _parse_ply_header(f, path: str):
    if f.readline().strip() != b"ply":
        raise ValueError(f"path: {path!r} is not a PLY file")
    fmt, elements = None, []
    while True:
        line = f.readline()
        if not line:
            raise ValueError(f"path: {path!r} ends inside its PLY header")
        parts = line.decode("ascii", "replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append({"name": parts[1], "count": int(parts[2]), "props": []})
        elif parts[0] == "property":
            if parts[1] == "list":
                elements[-1]["props"].append((parts[4], _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]]))
            else:
                elements[-1]["props"].append((parts[2], _PLY_TYPES[parts[1]], None))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"path: unsupported PLY format {fmt!r} in {path!r}")
    return fmt, elements


def read_ply(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> dict:
    """Read a PLY's vertices, faces (fan-triangulated) and edges, ASCII or binary.

    Args:
        path: `.ply` file.
        dtype: float dtype of the returned vertices.

    Returns:
        dict with `vertices` (V, 3) tensor, `faces` (F, 3) int64 tensor and `edges` (E, 2)
        int64 tensor (empty when the file has none). Other elements and properties are skipped.

    Raises:
        ValueError: when the file is missing, truncated or malformed.
    """
    path = check_path("path", path, (".ply",))
    if not os.path.isfile(path):
        raise ValueError(f"path: no such file {path!r}")
    out = {"vertex": None, "face": [], "edge": np.zeros((0, 2), dtype=np.int64)}
    try:
        with open(path, "rb") as f:
            fmt, elements = _parse_ply_header(f, path)
            if fmt == "ascii":
                tokens = f.read().split()
                pos = 0
                for el in elements:
                    fast = _ascii_element_fast(out, el, tokens, pos)
                    if fast is not None:
                        pos = fast
                        continue
                    rows = []
                    for _ in range(el["count"]):
                        row = {}
                        for name, t, list_t in el["props"]:
                            if list_t is None:
                                row[name] = float(tokens[pos])
                                pos += 1
                            else:
                                k = int(tokens[pos])
                                row[name] = [int(x) for x in tokens[pos + 1:pos + 1 + k]]
                                pos += 1 + k
                        rows.append(row)
                    _collect(out, el["name"], rows, ascii_rows=True)
            else:
                order = "<" if fmt == "binary_little_endian" else ">"
                data = f.read()
                pos = 0
                for el in elements:
                    pos = _read_binary_element(out, el, data, pos, order)
    except (KeyError, IndexError, ValueError, TypeError) as err:
        if isinstance(err, ValueError) and str(err).startswith("path:"):
            raise
        raise ValueError(f"path: malformed or truncated PLY {path!r} ({err})") from None
    v = out["vertex"] if out["vertex"] is not None else np.zeros((0, 3))
    faces = np.concatenate(out["face"]) if out["face"] else np.zeros((0, 3), dtype=np.int64)
    for idx in (faces, out["edge"]):
        if idx.size and (idx.min() < 0 or idx.max() >= len(v)):
            raise ValueError(f"path: {path!r} refers to vertices beyond the {len(v)} it holds")
    return {
        "vertices": torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64)).to(dtype),
        "faces": torch.from_numpy(faces.astype(np.int64)),
        "edges": torch.from_numpy(out["edge"].astype(np.int64)),
    }


def _ascii_element_fast(out: dict, el: dict, tokens: list, pos: int) -> int | None:
    """Vectorised read of an ASCII element of scalar properties or of triangles only; None when
    the element needs the general row-by-row path.
    """
    props, count = el["props"], el["count"]
    if all(list_t is None for _, _, list_t in props):
        width = len(props)
        if len(tokens) < pos + count * width:
            raise ValueError("fewer values than the header announces")
        arr = np.asarray(tokens[pos:pos + count * width], dtype=np.float64).reshape(count, width)
        names = [name for name, _, _ in props]
        if el["name"] == "vertex":
            out["vertex"] = arr[:, [names.index(c) for c in "xyz"]]
        elif el["name"] == "edge":
            out["edge"] = arr[:, [names.index("vertex1"), names.index("vertex2")]].astype(np.int64)
        return pos + count * width
    if el["name"] == "face" and len(props) == 1 and len(tokens) >= pos + 4 * count:
        arr = np.asarray(tokens[pos:pos + 4 * count], dtype=np.float64).reshape(count, 4)
        if (arr[:, 0] == 3).all():
            out["face"].append(arr[:, 1:].astype(np.int64))
            return pos + 4 * count
    return None


def _fan(polys) -> np.ndarray:
    tris = [[p[0], p[k], p[k + 1]] for p in polys for k in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def _collect(out: dict, name: str, rows, ascii_rows: bool) -> None:
    if name == "vertex":
        out["vertex"] = np.array([[r["x"], r["y"], r["z"]] for r in rows], dtype=np.float64).reshape(-1, 3)
    elif name == "face":
        key = "vertex_indices" if rows and "vertex_indices" in rows[0] else "vertex_index"
        out["face"].append(_fan([r[key] for r in rows]))
    elif name == "edge":
        out["edge"] = np.array([[r["vertex1"], r["vertex2"]] for r in rows], dtype=np.int64).reshape(-1, 2)


def _read_binary_element(out: dict, el: dict, data: bytes, pos: int, order: str) -> int:
    props = el["props"]
    if all(list_t is None for _, _, list_t in props):
        dt = np.dtype([(name, order + t) for name, t, _ in props])
        arr = np.frombuffer(data, dtype=dt, count=el["count"], offset=pos)
        pos += dt.itemsize * el["count"]
        if el["name"] == "vertex":
            out["vertex"] = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
        elif el["name"] == "edge":
            out["edge"] = np.stack([arr["vertex1"], arr["vertex2"]], axis=1).astype(np.int64)
        return pos
    if el["name"] == "face" and len(props) == 1:
        _, count_t, index_t = props[0]
        ct, it = np.dtype(order + count_t), np.dtype(order + index_t)
        # Fast path: every face a triangle (what our writer and most exporters write).
        rec = np.dtype([("n", ct), ("i", it, (3,))])
        if el["count"] * rec.itemsize <= len(data) - pos:
            arr = np.frombuffer(data, dtype=rec, count=el["count"], offset=pos)
            if (arr["n"] == 3).all():
                out["face"].append(arr["i"].astype(np.int64))
                return pos + rec.itemsize * el["count"]
    # General case: walk the records one by one.
    rows = []
    for _ in range(el["count"]):
        row = {}
        for name, t, list_t in props:
            if list_t is None:
                dt = np.dtype(order + t)
                row[name] = np.frombuffer(data, dtype=dt, count=1, offset=pos)[0]
                pos += dt.itemsize
            else:
                ct, it = np.dtype(order + t), np.dtype(order + list_t)
                k = int(np.frombuffer(data, dtype=ct, count=1, offset=pos)[0])
                pos += ct.itemsize
                row[name] = np.frombuffer(data, dtype=it, count=k, offset=pos).tolist()
                pos += it.itemsize * k
        rows.append(row)
    _collect(out, el["name"], rows, ascii_rows=False)
    return pos


def _chains_from_edges(edges: np.ndarray, num_vertices: int, path: str) -> list[np.ndarray]:
    """Follow edges from every vertex that no edge enters: one chain per strand."""
    nxt = np.full(num_vertices, -1, dtype=np.int64)
    indegree = np.zeros(num_vertices, dtype=np.int64)
    nxt[edges[:, 0]] = edges[:, 1]
    np.add.at(indegree, edges[:, 1], 1)
    outdegree = np.bincount(edges[:, 0], minlength=num_vertices)
    if (indegree > 1).any() or (outdegree > 1).any():
        raise ValueError(f"path: the edges of {path!r} branch; expected disjoint polylines")
    # All strands advance together, one vertex per step (-1 once a strand has ended).
    cur = np.flatnonzero((indegree == 0) & (outdegree == 1))
    columns = [cur]
    while len(cur) and len(columns) <= num_vertices:
        cur = np.where(cur >= 0, nxt[np.maximum(cur, 0)], -1)
        if (cur < 0).all():
            break
        columns.append(cur)
    table = np.stack(columns, axis=1)  # (M, L), -1 past each strand's end
    lengths = (table >= 0).sum(axis=1)
    chains = [row[:k] for row, k in zip(table, lengths)]
    if int(lengths.sum()) != len(np.unique(edges)):
        raise ValueError(f"path: the edges of {path!r} contain a closed loop; expected open polylines")
    return chains


def read_hair_ply(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Read hair written by `write_hair_ply` (or any PLY line set of equal-length polylines).

    Returns:
        (M, N, 3) tensor [m]; strands in the order of their first vertex in the file.

    Raises:
        ValueError: when the file has no edges, branching edges, loops, or unequal strands.
    """
    data = read_ply(path, dtype)
    edges = data["edges"].numpy()
    if len(edges) == 0:
        raise ValueError(f"path: {os.fspath(path)!r} holds no edges (hair polylines)")
    chains = _chains_from_edges(edges, len(data["vertices"]), os.fspath(path))
    return _strands_from_chains(data["vertices"], chains, os.fspath(path))


# --- sequences -----------------------------------------------------------------------------------


def export_frames(
    directory: str | os.PathLike,
    hair,
    body_vertices=None,
    body_faces=None,
    fmt: str = "ply",
    binary: bool = True,
    prefix: str = "",
) -> list[str]:
    """Write a motion as numbered per-frame files: `{prefix}hair_0000.{fmt}`, `{prefix}body_0000.{fmt}`, ...

    Args:
        directory: output folder (created).
        hair: (T, M, N, 3) or (M, N, 3) strand vertices [m].
        body_vertices: (T, V, 3), or (V, 3) / (1, V, 3) for a still body (written once, as
            `body_0000`) [m]; None for hair alone.
        body_faces: (F, 3) int triangles, with `body_vertices`.
        fmt: "ply" or "obj".
        binary: binary PLY (ignored for OBJ).
        prefix: prepended to every file name.

    Returns:
        The paths written, hair frames first, then body frames.

    Raises:
        ValueError: naming the malformed argument.
    """
    if fmt not in MESH_FORMATS:
        raise ValueError(f"fmt: expected one of {MESH_FORMATS}, got {fmt!r}")
    if not isinstance(directory, (str, os.PathLike)):
        raise ValueError(f"directory: expected a folder path, got {type(directory).__name__}")
    if not isinstance(prefix, str) or os.sep in prefix:
        raise ValueError(f"prefix: expected a file-name prefix without '{os.sep}', got {prefix!r}")
    h, _ = hair_frames("hair", hair)
    body_v, faces = body_pair(body_vertices, body_faces, h.shape[0])
    directory = os.fspath(directory)
    os.makedirs(directory, exist_ok=True)
    digits = max(4, len(str(h.shape[0] - 1)))
    paths = []
    for t in range(h.shape[0]):
        p = os.path.join(directory, f"{prefix}hair_{t:0{digits}d}.{fmt}")
        paths.append(write_hair_ply(p, h[t], binary) if fmt == "ply" else write_hair_obj(p, h[t]))
    if body_v is not None:
        for t in range(len(body_v)):
            p = os.path.join(directory, f"{prefix}body_{t:0{digits}d}.{fmt}")
            paths.append(write_mesh_ply(p, body_v[t], faces, binary) if fmt == "ply"
                         else write_mesh_obj(p, body_v[t], faces))
    return paths

