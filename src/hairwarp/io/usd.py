"""Universal Scene Description (USD) export of hair motions and the body they drape on.

One stage holds the hair as a `UsdGeom.BasisCurves` (linear curves, one per strand) and,
optionally, the body as a `UsdGeom.Mesh`, both animated with one time sample per frame. Time
codes are frame numbers: the stage's timeCodesPerSecond and framesPerSecond are both the
motion's fps, its start time code is 0 and its end time code T - 1, so DCC tools (Houdini,
Blender, Maya, usdview) play the motion at its real speed.

hairwarp works in metres with y up. `up_axis="Z"` rotates the data into a z-up stage (a
quarter turn about x: (x, y, z) -> (x, -z, y), the usual y-up to z-up conversion) and
`meters_per_unit` rescales it (0.01 for a centimetre stage); `read_usd` undoes both from the
stage's metadata.

`pxr` comes from the `usd-core` package (a dependency of hairwarp); it is imported only when
these functions run.

Layout of the stage::

    /Root        Xform (the default prim)
    /Root/Hair   BasisCurves: type linear, curveVertexCounts all N, points per frame, widths
    /Root/Body   Mesh: faceVertexCounts all 3, faceVertexIndices, points per frame
"""

from __future__ import annotations

import os

import numpy as np
import torch

from hairwarp.io._arrays import (
    as_tensor,
    body_pair,
    check_path,
    check_positive_number,
    ensure_parent,
    hair_frames,
)

USD_SUFFIXES = (".usd", ".usda", ".usdc")
ROOT_PATH = "/Root"
HAIR_PATH = "/Root/Hair"
BODY_PATH = "/Root/Body"
UP_AXES = ("Y", "Z")
# Hair colour shown by viewers that honour displayColor (a mid brown).
_HAIR_DISPLAY_COLOR = (0.45, 0.29, 0.14)
_BODY_DISPLAY_COLOR = (0.72, 0.76, 0.82)


def _pxr():
    """Import pxr lazily, with an error that says how to get it."""
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError as err:  # pragma: no cover - usd-core is installed in the test env
        raise ImportError(
            "USD export needs the `pxr` module from usd-core: `pip install usd-core`"
        ) from err
    return Gf, Sdf, Usd, UsdGeom, Vt


def _to_stage(points: np.ndarray, up_axis: str, meters_per_unit: float) -> np.ndarray:
    """Hairwarp (y up, metres) -> stage axes and units, float32."""
    p = points.astype(np.float64)
    if up_axis == "Z":
        p = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
    return (p / meters_per_unit).astype(np.float32)


def _from_stage(points: np.ndarray, up_axis: str, meters_per_unit: float) -> np.ndarray:
    """Stage axes and units -> hairwarp (y up, metres), float32 (exact for Y up, 1 m/unit)."""
    p = np.asarray(points, dtype=np.float32)
    if up_axis == "Z":
        p = np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)
    if meters_per_unit != 1.0:
        p = (p.astype(np.float64) * meters_per_unit).astype(np.float32)
    return p


def _extent(points: np.ndarray, pad: float = 0.0) -> np.ndarray:
    return np.stack([points.min(axis=0) - pad, points.max(axis=0) + pad]).astype(np.float32)


def _widths(widths, num_strands: int, num_vertices: int) -> tuple[np.ndarray, str]:
    """Widths [m]: a number (constant) or (M, N) per vertex -> (values, USD interpolation)."""
    if isinstance(widths, (torch.Tensor, np.ndarray)):
        t = as_tensor("widths", widths)
        if tuple(t.shape) != (num_strands, num_vertices):
            raise ValueError(
                f"widths: expected a number or shape ({num_strands}, {num_vertices}), got {tuple(t.shape)}"
            )
        w = t.to(torch.float64).numpy()
        if not np.isfinite(w).all() or (w <= 0).any():
            raise ValueError("widths: expected finite positive values")
        return w.reshape(-1), "vertex"
    return np.array([check_positive_number("widths", widths)]), "constant"


def write_usd(
    path: str | os.PathLike,
    hair,
    body_vertices=None,
    body_faces=None,
    fps: float = 60,
    widths=1e-3,
    up_axis: str = "Y",
    meters_per_unit: float = 1.0,
) -> str:
    """Write a hair motion (and the body) to a USD stage, one time sample per frame.

    Args:
        path: `.usd` / `.usdc` (binary crate) or `.usda` (text) file; its folder is created.
        hair: (T, M, N, 3) or (M, N, 3) strand vertices [m], y up, torch tensor (any device,
            float32 or float64) or numpy array. M strands of N >= 2 vertices, vertex 0 the root.
        body_vertices: (T, V, 3) body vertices per frame, or (V, 3) / (1, V, 3) for a still
            body (written without time samples) [m]; None for hair alone.
        body_faces: (F, 3) int32/int64 triangles, counter-clockwise seen from outside (USD's
            default rightHanded orientation), with `body_vertices`.
        fps: frames per second of the motion [1/s]; time code t is frame t.
        widths: strand diameter [m]: a number, or (M, N) per vertex.
        up_axis: "Y" (hairwarp's frame, written as is) or "Z" (rotated into a z-up stage).
        meters_per_unit: the stage's unit [m]; coordinates and widths are divided by it.

    Returns:
        The path written.

    Raises:
        ValueError: naming the malformed argument (shape, dtype, NaN/Inf, empty, face index
            out of range, frame counts that disagree, non-positive fps/widths, bad suffix).
        ImportError: when usd-core is not installed.
    """
    path = check_path("path", path, USD_SUFFIXES)
    hair_t, _ = hair_frames("hair", hair)
    num_frames, m, n, _ = hair_t.shape
    body_v, faces = body_pair(body_vertices, body_faces, num_frames)
    fps = check_positive_number("fps", fps)
    width_values, width_interp = _widths(widths, m, n)
    if up_axis not in UP_AXES:
        raise ValueError(f"up_axis: expected one of {UP_AXES}, got {up_axis!r}")
    meters_per_unit = check_positive_number("meters_per_unit", meters_per_unit)

    Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
    # Built in an anonymous layer and exported: no clash with a layer of the same path that
    # this process has already opened (USD's layer registry), and the format follows the suffix.
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(num_frames - 1)
    root = UsdGeom.Xform.Define(stage, ROOT_PATH)
    stage.SetDefaultPrim(root.GetPrim())
    stage.GetRootLayer().customLayerData = {"generator": "hairwarp"}

    curves = UsdGeom.BasisCurves.Define(stage, HAIR_PATH)
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(m, n, dtype=np.int32)))
    stage_widths = (width_values / meters_per_unit).astype(np.float32)
    curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(stage_widths))
    interpolation = UsdGeom.Tokens.vertex if width_interp == "vertex" else UsdGeom.Tokens.constant
    curves.SetWidthsInterpolation(interpolation)
    curves.CreateDisplayColorAttr([Gf.Vec3f(*_HAIR_DISPLAY_COLOR)])
    points_attr = curves.CreatePointsAttr()
    extent_attr = curves.CreateExtentAttr()
    half_width = float(stage_widths.max()) / 2
    for t in range(num_frames):
        p = _to_stage(hair_t[t].reshape(-1, 3), up_axis, meters_per_unit)
        points_attr.Set(Vt.Vec3fArray.FromNumpy(p), Usd.TimeCode(t))
        extent_attr.Set(Vt.Vec3fArray.FromNumpy(_extent(p, half_width)), Usd.TimeCode(t))

    if body_v is not None:
        mesh = UsdGeom.Mesh.Define(stage, BODY_PATH)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
        # A triangle mesh as it is: no subdivision surface on top of it in viewers.
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDisplayColorAttr([Gf.Vec3f(*_BODY_DISPLAY_COLOR)])
        points_attr = mesh.CreatePointsAttr()
        extent_attr = mesh.CreateExtentAttr()
        for t in range(len(body_v)):
            p = _to_stage(body_v[t], up_axis, meters_per_unit)
            # A still body is written as a default value, an animated one as time samples.
            code = Usd.TimeCode.Default() if len(body_v) == 1 else Usd.TimeCode(t)
            points_attr.Set(Vt.Vec3fArray.FromNumpy(p), code)
            extent_attr.Set(Vt.Vec3fArray.FromNumpy(_extent(p)), code)

    ensure_parent(path)
    if not stage.GetRootLayer().Export(path):
        raise OSError(f"path: USD could not write {path!r}")
    return path


def _samples(attr, Usd) -> tuple[list[float], list[np.ndarray]]:
    """(time codes, arrays) of an attribute: its time samples, or its default value alone."""
    times = list(attr.GetTimeSamples())
    if times:
        return times, [np.asarray(attr.Get(Usd.TimeCode(t)), dtype=np.float32) for t in times]
    value = attr.Get()
    return [], ([] if value is None else [np.asarray(value, dtype=np.float32)])


def _first_prim(stage, schema, preferred: str):
    prim = stage.GetPrimAtPath(preferred)
    if prim and prim.IsA(schema):
        return prim
    for prim in stage.Traverse():
        if prim.IsA(schema):
            return prim
    return None


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygon faces (counts, flat indices) -> (F, 3) triangles, fan from each first corner."""
    if (counts < 3).any():
        raise ValueError("path: the body mesh has faces with fewer than 3 corners")
    if (counts == 3).all():
        return indices.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [
        np.stack([np.full(c - 2, indices[s]), indices[s + 1:s + c - 1], indices[s + 2:s + c]], axis=1)
        for s, c in zip(starts, counts)
    ]
    return np.concatenate(tris)


def read_usd(path: str | os.PathLike) -> dict:
    """Read a stage written by `write_usd` (or any stage with one uniform BasisCurves).

    The first BasisCurves prim (`/Root/Hair` when present) is the hair, the first Mesh
    (`/Root/Body`) the body. Coordinates come back in metres, y up, whatever the stage's
    upAxis (Y or Z) and metersPerUnit.

    Args:
        path: `.usd`, `.usda` or `.usdc` file.

    Returns:
        dict with
            hair: (T, M, N, 3) float32 tensor [m], one frame per time sample (a stage without
                time samples gives T = 1);
            body_vertices: (T_body, V, 3) float32 tensor [m] (T_body = 1 for a still body), or
                None;
            body_faces: (F, 3) int32 tensor (polygons fan-triangulated), or None;
            fps: the stage's timeCodesPerSecond [1/s];
            time_codes: list of the hair's time codes;
            widths: (M, N) float32 tensor of strand diameters [m].

    Raises:
        ValueError: when the file is missing or unreadable, has no BasisCurves, or its curves
            do not all have the same vertex count.
        ImportError: when usd-core is not installed.
    """
    stage, up_axis, mpu, Usd, UsdGeom = _open_stage(path)
    prim = _first_prim(stage, UsdGeom.BasisCurves, HAIR_PATH)
    if prim is None:
        raise ValueError(f"path: {path!r} holds no BasisCurves (hair)")
    curves = UsdGeom.BasisCurves(prim)
    counts = np.asarray(curves.GetCurveVertexCountsAttr().Get(), dtype=np.int64)
    if counts.size == 0 or (counts != counts[0]).any():
        raise ValueError(f"path: the curves of {path!r} do not all have the same vertex count")
    m, n = len(counts), int(counts[0])
    times, frames = _samples(curves.GetPointsAttr(), Usd)
    if not frames:
        raise ValueError(f"path: the curves of {path!r} have no points")
    hair = np.stack([_from_stage(f, up_axis, mpu).reshape(m, n, 3) for f in frames])
    w = curves.GetWidthsAttr().Get()
    w = np.asarray(w if w is not None else [0.0], dtype=np.float64) * mpu
    widths = np.broadcast_to(w.reshape(-1)[0], (m, n)) if w.size == 1 else w.reshape(m, n)

    body_vertices = body_faces = None
    prim = _first_prim(stage, UsdGeom.Mesh, BODY_PATH)
    if prim is not None:
        mesh = UsdGeom.Mesh(prim)
        _, body = _samples(mesh.GetPointsAttr(), Usd)
        if body:
            body_vertices = torch.from_numpy(np.stack([_from_stage(b, up_axis, mpu) for b in body]))
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
            indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
            body_faces = torch.from_numpy(_triangulate(counts, indices).astype(np.int32))
    return {
        "hair": torch.from_numpy(hair),
        "body_vertices": body_vertices,
        "body_faces": body_faces,
        "fps": float(stage.GetTimeCodesPerSecond()),
        "time_codes": times if times else [0.0],
        "widths": torch.from_numpy(np.ascontiguousarray(widths, dtype=np.float32)),
    }


def _open_stage(path):
    """(stage, up axis "Y"/"Z", metres per unit, pxr modules) of a USD file, read fresh."""
    path = check_path("path", path, USD_SUFFIXES)
    if not os.path.isfile(path):
        raise ValueError(f"path: no such file {path!r}")
    Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
    # Opened as anonymous: a fresh read even if this process opened (or wrote) the path before.
    layer = Sdf.Layer.OpenAsAnonymous(path)
    if layer is None:
        raise ValueError(f"path: USD could not read {path!r}")
    stage = Usd.Stage.Open(layer)
    return stage, str(UsdGeom.GetStageUpAxis(stage)).upper(), float(UsdGeom.GetStageMetersPerUnit(stage)), Usd, UsdGeom


def _world(prim, points: np.ndarray, time, Usd, UsdGeom) -> np.ndarray:
    """Prim-local points (P, 3) in the stage's world frame (its Xform ancestors applied)."""
    matrix = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
    # USD matrices act on row vectors: p_world = [p 1] M. By einsum's own loop: a BLAS product
    # of millions of points with a 3 x 3 matrix crawls on a CPU whose cores are shared.
    return np.einsum("pj,jk->pk", points.astype(np.float64), matrix[:3, :3]) + matrix[3, :3]


def read_usd_curves(path: str | os.PathLike) -> dict:
    """Strands of the first BasisCurves of any USD file (what DCC tools export as a groom).

    Curves may have different vertex counts; their Xform ancestors, the stage's upAxis and
    metersPerUnit are applied, so strands come back in metres, y up. A time-sampled groom
    gives its first sample.

    Returns:
        dict with strands: list of (n_i, 3) float64 arrays [m] (views into `points`); points:
        (V, 3) float64 [m], the strands concatenated; counts: (S,) int64 vertices per strand
        (`hairwarp.scene.groom.place_flat_groom` takes these two); up_axis; meters_per_unit;
        prim: the curves' path.

    Raises:
        ValueError: no such file, no BasisCurves, no points, counts that disagree with the
            points, or a curve of fewer than 2 vertices (naming it).
    """
    stage, up_axis, mpu, Usd, UsdGeom = _open_stage(path)
    prim = _first_prim(stage, UsdGeom.BasisCurves, HAIR_PATH)
    if prim is None:
        raise ValueError(f"path: {os.fspath(path)!r} holds no BasisCurves (a groom)")
    curves = UsdGeom.BasisCurves(prim)
    counts = np.asarray(curves.GetCurveVertexCountsAttr().Get() or [], dtype=np.int64)
    times, frames = _samples(curves.GetPointsAttr(), Usd)
    if not frames or counts.size == 0:
        raise ValueError(f"path: the curves {prim.GetPath()} of {os.fspath(path)!r} have no points")
    points = frames[0]
    if int(counts.sum()) != len(points):
        raise ValueError(f"path: {prim.GetPath()} declares {int(counts.sum())} curve vertices but holds {len(points)}")
    short = np.nonzero(counts < 2)[0]
    if short.size:
        raise ValueError(f"path: curve {int(short[0])} of {prim.GetPath()} has {int(counts[short[0]])} vertex; "
                         "a strand needs at least 2")
    time = Usd.TimeCode(times[0]) if times else Usd.TimeCode.Default()
    world = _from_stage(_world(prim, points, time, Usd, UsdGeom), up_axis, mpu).astype(np.float64)
    strands = np.split(world, np.cumsum(counts)[:-1])
    return {"strands": strands, "points": world, "counts": counts, "up_axis": up_axis, "meters_per_unit": mpu,
            "prim": str(prim.GetPath())}


def read_usd_mesh(path: str | os.PathLike) -> dict:
    """The first Mesh of a USD file, animated if its points are time-sampled.

    Returns:
        dict with vertices: (T, V, 3) float32 tensor [m], y up (T = 1 without time samples);
        faces: (F, 3) int32 tensor (polygons fan-triangulated); fps: timeCodesPerSecond;
        time_codes; animated: whether the points had time samples.

    Raises:
        ValueError: no such file, no Mesh, no points or no faces.
    """
    stage, up_axis, mpu, Usd, UsdGeom = _open_stage(path)
    prim = _first_prim(stage, UsdGeom.Mesh, BODY_PATH)
    if prim is None:
        raise ValueError(f"path: {os.fspath(path)!r} holds no Mesh")
    mesh = UsdGeom.Mesh(prim)
    times, frames = _samples(mesh.GetPointsAttr(), Usd)
    if not frames or len(frames[0]) == 0:
        raise ValueError(f"path: the mesh {prim.GetPath()} of {os.fspath(path)!r} has no points")
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if counts.size == 0:
        raise ValueError(f"path: the mesh {prim.GetPath()} of {os.fspath(path)!r} has no faces")
    codes = times or [None]
    vertices = np.stack([
        _from_stage(_world(prim, f, Usd.TimeCode(t) if t is not None else Usd.TimeCode.Default(), Usd, UsdGeom),
                    up_axis, mpu) for f, t in zip(frames, codes)])
    return {"vertices": torch.from_numpy(vertices.astype(np.float32)),
            "faces": torch.from_numpy(_triangulate(counts, indices).astype(np.int32)),
            "fps": float(stage.GetTimeCodesPerSecond()), "time_codes": times or [0.0], "animated": bool(times)}
