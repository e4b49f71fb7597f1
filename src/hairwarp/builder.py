"""Scenes from names and files: the one place that turns a user's arguments into a `Scene`.

    build_scene(hairstyle="bob", body="default", pose="head_turn", time=0.5)       # one frame
    build_scene(hairstyle="my_hair.data", body="my_smpl.npz", pose="walk.npz", start=1.5, num_frames=120)

Hairstyle: a procedural preset, a USC-HairSalon `.data` file, a USD groom (BasisCurves in
`.usd`/`.usda`/`.usdc`, any vertex count per strand), or a hair latent `.npy` (512 numbers
decoded through the shipped basis). A groom whose roots are off this body's scalp (made on
another head) is fitted first: a similarity transform by ICP (`hairwarp.scene.groom`).
Body: "default" (the shipped body), an SMPL-format model file (`.npz` / `.pkl`), a static mesh
(`.obj`, `.ply`, `.glb`, `.gltf`, `.stl`, `.off`, read with trimesh; metres, y up, facing +z),
or an animated mesh (a USD file whose Mesh points are time-sampled, units and up axis from the
stage; or an `.npz` with `vertices` (T, V, 3), `faces` (F, 3) and optional `fps`). A mesh body
has no pose parameters: it plays its own frames, the hair follows its head region's rigid
motion with the roots projected onto the surface, and the networks refuse it (the physics
methods run). Pose: "rest", a procedural motion, or an AMASS `.npz` (SMPL bodies only).
The command line (`drape`, `simulate`) and the Python API (`hairwarp.build_scene`) both come
here. Errors are one `ValueError` whose message starts with the argument's name.
"""

from __future__ import annotations

import os

import numpy as np
import torch

from hairwarp.scene.scene import Scene

# `data_units="auto"` reads a `.data` file as centimetres when its bounding box is larger than
# this many file units (a head of hair in metres spans < 1 m; PERM's, in cm, spans 20-100).
AUTO_CM_EXTENT = 3.0
# The pose name of the body's rest pose (one frame).
REST_POSE = "rest"
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
USD_SUFFIXES = (".usd", ".usda", ".usdc")
# Frame rate of an animated mesh .npz without an `fps` entry [1/s].
DEFAULT_MESH_FPS = 30.0
FIT_MODES = ("auto", "similarity", "translate", "none")
# Guides of a groom of more strands than this, when none are asked for (the paper's 32 x 32).
DEFAULT_GUIDES = 1024


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def _existing_file(name: str, path: str) -> str:
    if not os.path.isfile(path):
        raise ValueError(f"{name}: no such file {path!r}")
    return path


def positive_int(name: str, value, minimum: int = 1) -> int:
    """`value` as an int >= `minimum`, or a ValueError naming `name`."""
    if isinstance(value, bool) or value is None or int(value) != value or int(value) < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def load_mesh_body(path: str):
    """(AnimatedMeshBody, fps) of a static mesh file, an animated USD or a vertices/faces `.npz`."""
    from hairwarp.scene.body import mesh_body

    suffix = os.path.splitext(path)[1].lower()
    name = os.path.basename(path)
    fps = DEFAULT_MESH_FPS
    if suffix in USD_SUFFIXES:
        from hairwarp.io.usd import read_usd_mesh

        try:
            data = read_usd_mesh(path)
        except ValueError as exc:
            raise ValueError(f"body: {_first_line(exc).removeprefix('path: ')}") from None
        vertices, faces, fps = data["vertices"], data["faces"], data["fps"]
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if "faces" not in data.files:
                raise ValueError(f"body: {name} holds vertices but no faces (F, 3)")
            vertices, faces = torch.as_tensor(data["vertices"]), torch.as_tensor(data["faces"].astype(np.int64))
            if "fps" in data.files:
                fps = float(data["fps"])
        if not fps > 0:
            raise ValueError(f"body: {name}: fps must be positive, got {fps}")
    else:
        import trimesh

        try:
            loaded = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise ValueError(f"body: trimesh cannot read {name} ({_first_line(exc)})") from None
        faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
        if len(faces) == 0:
            raise ValueError(f"body: {name} holds no triangles (a point cloud or an empty scene)")
        vertices, faces = torch.as_tensor(np.asarray(loaded.vertices)), torch.as_tensor(faces)
    return mesh_body(vertices, faces, source=name), fps


def load_body(body: str = "default"):
    """(body, scalp, mesh fps or None) of "default", an SMPL-format model file or a mesh file."""
    from hairwarp.scene.body import SMPLBody, default_body
    from hairwarp.scene.scalp import build_scalp

    fps = None
    suffix = os.path.splitext(body)[1].lower()
    if body == "default":
        model = default_body()
    else:
        _existing_file("body", body)
        is_mesh_npz = False
        if suffix == ".npz":
            with np.load(body, allow_pickle=False) as data:
                is_mesh_npz = "vertices" in data.files
        try:
            if suffix in MESH_SUFFIXES + USD_SUFFIXES or is_mesh_npz:
                model, fps = load_mesh_body(body)
            elif suffix in (".npz", ".pkl"):
                model = SMPLBody(body)
            else:
                raise ValueError(f"expected 'default', an SMPL-format .npz/.pkl, a mesh ({', '.join(MESH_SUFFIXES)}), "
                                 f"a USD file or a vertices/faces .npz, got {body!r}")
        except (ValueError, KeyError, OSError) as exc:
            message = _first_line(exc)
            raise ValueError(message if message.startswith("body:") else f"body: {message}") from None
    try:
        scalp = build_scalp(model)
    except ValueError as exc:
        raise ValueError(f"body: cannot place a scalp on this body ({_first_line(exc)})") from None
    return model, scalp, fps


def data_units(path: str, units: str = "auto") -> str:
    """The length unit of a `.data` file: `units`, or for "auto" cm/m by the hair's extent."""
    from hairwarp.io.hair_data import read_hair_data_flat

    if units != "auto":
        return units
    points, _ = read_hair_data_flat(path)
    if len(points) == 0:
        return "m"
    return "cm" if float((points.max(0) - points.min(0)).max()) > AUTO_CM_EXTENT else "m"


def load_hairstyle(hairstyle: str, body, scalp, *, grow: str = "body", data_units_: str = "auto",
                   data_up: str = "y", fit: str = "auto", strand_stride: int = 1,
                   num_vertices: int = 100, seed: int = 0):
    """A `Hairstyle` from a preset, a `.data` file, a USD groom or a latent `.npy`, at the asked size."""
    from hairwarp.scene.hairstyles import Hairstyle, list_hairstyle_presets
    from hairwarp.scene.scene import preset_hairstyle

    stride = positive_int("strand_stride", strand_stride)
    n = positive_int("num_vertices", num_vertices, minimum=3)
    suffix = os.path.splitext(hairstyle)[1].lower()
    keep = None
    if fit not in FIT_MODES:
        raise ValueError(f"fit: expected one of {FIT_MODES}, got {fit!r}")
    head_points = body.rest_vertices[body.head_vertex_indices].double().cpu().numpy()
    if suffix == ".data":
        from hairwarp.io.hair_data import load_hairstyle as load_data

        _existing_file("hairstyle", hairstyle)
        try:
            style = load_data(hairstyle, scalp, units=data_units(hairstyle, data_units_), up=data_up,
                              num_vertices=n, align={"translate": "roots"}.get(fit, fit), head_points=head_points)
        except ValueError as exc:
            raise ValueError(f"hairstyle: {_first_line(exc)}") from None
        _say_fit(style)
    elif suffix in USD_SUFFIXES:
        from hairwarp.io.hair_data import DEFAULT_MIN_LENGTH
        from hairwarp.io.usd import read_usd_curves
        from hairwarp.scene.groom import place_groom

        _existing_file("hairstyle", hairstyle)
        try:
            curves = read_usd_curves(hairstyle)
            style, _ = place_groom(curves["strands"], scalp, head_points, fit=fit, num_vertices=n,
                                   min_length=DEFAULT_MIN_LENGTH, name=os.path.basename(hairstyle))
        except ValueError as exc:
            raise ValueError(f"hairstyle: {_first_line(exc).removeprefix('path: ')}") from None
        _say_fit(style)
    elif suffix == ".npy":
        from hairwarp.scene.hair_latent import HairLatentBasis

        _existing_file("hairstyle", hairstyle)
        try:
            z = np.load(hairstyle, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ValueError(f"hairstyle: {hairstyle!r} is not a readable .npy ({_first_line(exc)})") from None
        basis = HairLatentBasis.load_default()
        if not np.issubdtype(z.dtype, np.number) or z.size != basis.latent_dim:
            raise ValueError(f"hairstyle: a latent .npy holds {basis.latent_dim} numbers; {hairstyle!r} holds "
                             f"an array of shape {z.shape} and dtype {z.dtype}")
        if not np.isfinite(z).all():
            raise ValueError(f"hairstyle: {hairstyle!r} holds NaN or Inf")
        strands, uv = basis.decode(torch.as_tensor(z, dtype=torch.float64).reshape(-1), scalp)
        index = torch.cdist(uv.double(), scalp.uv.double()).argmin(dim=1)  # the scalp root of each strand
        style = Hairstyle(strands=strands.to(torch.float32), root_uv=uv.to(torch.float32),
                          root_normals=scalp.normals[index].to(torch.float32), root_index=index,
                          filtered=torch.zeros(0, dtype=torch.int64), name=os.path.basename(hairstyle))
    elif hairstyle in list_hairstyle_presets():
        if grow not in ("body", "head"):
            raise ValueError(f"grow: expected 'body' or 'head', got {grow!r}")
        return preset_hairstyle(hairstyle, body, scalp, seed=seed, grow_around_body=grow == "body",
                                strand_stride=stride, num_vertices=n)
    else:
        raise ValueError(f"hairstyle: expected a preset ({', '.join(list_hairstyle_presets())}), a .data file, "
                         f"a USD groom (.usd/.usda/.usdc) or a latent .npy, got {hairstyle!r}")
    if stride > 1:
        keep = torch.arange(0, style.num_strands, stride)
    return style.subset(keep, n)


def _say_fit(style) -> None:
    fit = style.info.get("fit")
    if fit:
        print(f"placed the groom's roots on the scalp: {fit}; median root distance to its scalp root "
              f"{style.info['root_distance_median'] * 1e3:.1f} mm before snapping")


def _rest_pelvis(body):
    """(3,) rest position of the body's root joint [m], for the AMASS z-up conversion."""
    model = getattr(body, "model", None)
    if model is None or getattr(model, "J_regressor", None) is None:
        return None
    return (model.J_regressor[0].double() @ model.v_template.double()).numpy()


def load_motion(pose: str, body, *, default_body: bool, duration: float | None = None):
    """The whole `Motion` of a pose name or file (one frame for the rest pose)."""
    from hairwarp.scene.motion import list_motions, load_amass, procedural_motion
    from hairwarp.scene.scene import static_motion

    if duration is not None and not duration > 0:
        raise ValueError(f"duration: expected a positive number of seconds, got {duration}")
    if pose == REST_POSE:
        return static_motion(name=REST_POSE)
    if pose in list_motions():
        return procedural_motion(pose, duration=duration)
    if pose.lower().endswith(".npz"):
        _existing_file("pose", pose)
        try:
            motion = load_amass(pose, root_joint=_rest_pelvis(body))
        except ValueError as exc:
            raise ValueError(f"pose: {_first_line(exc)}") from None
        if default_body and bool(motion.betas.abs().sum() > 0):
            # AMASS betas are SMPL's shape space; the default body has its own.
            print("note: the motion's SMPL betas do not apply to the default body; using its mean shape")
            motion = motion.replace(betas=torch.zeros_like(motion.betas))
        return motion
    raise ValueError(f"pose: expected '{REST_POSE}', a procedural motion ({', '.join(list_motions())}) "
                     f"or an AMASS .npz, got {pose!r}")


def frame_window(motion, start_frame: int, count: int | None, name: str):
    """The motion cut to frames [start_frame, start_frame + count) (count None: to the end)."""
    if not 0 <= start_frame < motion.num_frames:
        raise ValueError(f"{name}: the motion has {motion.num_frames} frames "
                         f"({motion.duration:.3f} s at {motion.fps:g} fps); frame {start_frame} is outside it")
    end = motion.num_frames if count is None else min(motion.num_frames, start_frame + count)
    return motion.replace(poses=motion.poses[start_frame:end].clone(), trans=motion.trans[start_frame:end].clone())


def build_scene(hairstyle: str = "long_straight", body: str = "default", pose: str | None = None, *,
                default_motion: str = REST_POSE,
                frame: int | None = None, time: float | None = None, start: float | None = None,
                num_frames: int | None = None, duration: float | None = None, grow: str = "body",
                data_units: str = "auto", data_up: str = "y", fit: str = "auto",
                strand_stride: int = 1, num_vertices: int = 100, seed: int = 0,
                guides: int | None = None) -> Scene:
    """A `Scene` from names and files (see the module docstring).

    Args:
        hairstyle: a preset name, a `.data` file, a USD groom or a latent `.npy`.
        body: "default", an SMPL-format model file, or a static or animated mesh file.
        pose: "rest", a procedural motion name or an AMASS `.npz` (SMPL bodies; a mesh body
            plays its own frames). None: `default_motion` for SMPL bodies, a mesh body's frames.
        default_motion: the pose of SMPL bodies when `pose` is None.
        frame: keep this one frame (index) of the motion.
        time: keep the frame at this time [s] instead.
        start: keep the motion from this time [s] ...
        num_frames: ... for this many frames (None: to the end). Without frame, time or start
            the whole motion is kept.
        duration: procedural motions: length [s] (None: the motion's own).
        grow: presets: grow the strands around the rest "body" or the "head" proxy alone.
        data_units: `.data`: "m", "cm", "mm" or "auto" (cm when the hair spans more than
            `AUTO_CM_EXTENT` units).
        data_up: `.data`: the file's up axis, "y" or "z".
        fit: grooms from files: "auto" (fit a similarity transform by ICP when the roots lie
            off the scalp), "similarity" (always), "translate" (mean root onto the mean scalp
            root) or "none" (keep the file's placement); the roots are then projected.
        strand_stride: keep every this-many-th strand of a groom file (presets: grow on one root
            in this many, spread over the scalp: `Scalp.every`).
        num_vertices: vertices per strand N (>= 3).
        seed: presets: the hairstyle's seed.
        guides: simulate the groom through this many guide strands, the rest following them
            (`hairwarp.scene.guides`); None: every strand of a groom of at most
            `DEFAULT_GUIDES`, else `DEFAULT_GUIDES` guides.

    Raises:
        ValueError: naming the argument and what was expected.
    """
    from hairwarp.scene.motion import Motion

    model, scalp, mesh_fps = load_body(body)
    style = load_hairstyle(hairstyle, model, scalp, grow=grow, data_units_=data_units, data_up=data_up,
                           fit=fit, strand_stride=strand_stride, num_vertices=num_vertices, seed=seed)
    if pose is None:
        pose = default_motion if model.has_smpl_pose else REST_POSE
    if model.has_smpl_pose:
        motion = load_motion(pose, model, default_body=body == "default", duration=duration)
        extra = motion.betas[model.num_betas:]
        if extra.numel() and bool(extra.abs().sum() > 0):
            print(f"note: the body has {model.num_betas} shape coefficients, the motion {motion.betas.numel()}; "
                  f"using the first {model.num_betas}")
    else:
        if pose != REST_POSE:
            raise ValueError(f"pose: a mesh body plays its own {model.num_frames} frame(s); it takes no pose "
                             f"(got {pose!r}), only frame, time, start and num_frames")
        t = model.num_frames
        motion = Motion(poses=torch.zeros(t, 66), trans=torch.zeros(t, 3), betas=torch.zeros(16),
                        fps=float(mesh_fps), name=os.path.splitext(os.path.basename(body))[0])
    if frame is not None and time is not None:
        raise ValueError("frame: give frame or time, not both")
    first, count = 0, None
    if time is not None:
        first, count, name = int(round(time * motion.fps)), 1, "time"
    elif frame is not None:
        first, count, name = int(frame), 1, "frame"
    elif start is not None or num_frames is not None:
        first, name = int(round((start or 0.0) * motion.fps)), "start"
        count = None if num_frames is None else positive_int("num_frames", num_frames)
    if time is not None or frame is not None or start is not None or num_frames is not None:
        motion = frame_window(motion, first, count, name)
        where = f"frame {first}" if count == 1 else f"from {first / motion.fps:g} s"
        if not model.has_smpl_pose:
            model = model.window(first, first + motion.num_frames)
    else:
        where = "all frames"
    guide_set = make_guides(style, guides)
    if guide_set is not None:
        print(f"simulating {guide_set.describe()}")
        style = guide_set.guide_hairstyle()
    label = (f"{style.name or 'hair'} on {'default body' if body == 'default' else os.path.basename(body)}, "
             f"{pose if pose == REST_POSE else os.path.basename(pose)} {where}")
    return Scene(body=model, scalp=scalp, hairstyle=style, motion=motion, name=label, guides=guide_set)


def make_guides(style, guides: int | None):
    """The `GuideSet` of a loaded groom for `guides` (see `build_scene`), or None to simulate it whole."""
    from hairwarp.scene.guides import GuideConfig, GuideSet

    m = style.num_strands
    if guides is None:
        if m <= DEFAULT_GUIDES:
            return None
        guides = DEFAULT_GUIDES
    k = positive_int("guides", guides)
    if k > m:
        raise ValueError(f"guides: expected at most the groom's {m} strands, got {k}")
    if k == m:
        return None
    return GuideSet.build(style, GuideConfig(num_guides=k))
