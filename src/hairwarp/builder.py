"""Scenes from names and files: the one place that turns a user's arguments into a `Scene`.

    build_scene(hairstyle="bob", body="default", pose="head_turn", time=0.5)       # one frame
    build_scene(hairstyle="my_hair.data", body="my_smpl.npz", pose="walk.npz", start=1.5, num_frames=120)

Hairstyle: a procedural preset, a USC-HairSalon `.data` file, or a hair latent `.npy` (512
numbers decoded through the shipped basis). Body: "default" (the shipped body) or an
SMPL-format model file (`.npz` / `.pkl`). Pose: "rest", a procedural motion, or an AMASS `.npz`.
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


def load_body(body: str = "default"):
    """(body, scalp) of "default" or an SMPL-format model file."""
    from hairwarp.scene.body import SMPLBody, default_body
    from hairwarp.scene.scalp import build_scalp

    if body == "default":
        model = default_body()
    else:
        _existing_file("body", body)
        try:
            model = SMPLBody(body)
        except (ValueError, KeyError, OSError) as exc:
            raise ValueError(f"body: {_first_line(exc)}") from None
    try:
        scalp = build_scalp(model)
    except ValueError as exc:
        raise ValueError(f"body: cannot place a scalp on this body ({_first_line(exc)})") from None
    return model, scalp


def data_units(path: str, units: str = "auto") -> str:
    """The length unit of a `.data` file: `units`, or for "auto" cm/m by the hair's extent."""
    from hairwarp.io.hair_data import read_hair_data

    if units != "auto":
        return units
    strands = [s for s in read_hair_data(path) if len(s)]
    if not strands:
        return "m"
    points = np.concatenate(strands)
    return "cm" if float((points.max(0) - points.min(0)).max()) > AUTO_CM_EXTENT else "m"


def load_hairstyle(hairstyle: str, body, scalp, *, grow: str = "body", data_units_: str = "auto",
                   data_up: str = "y", align_roots: bool = False, strand_stride: int = 1,
                   num_vertices: int = 100, seed: int = 0):
    """A `Hairstyle` from a preset name, a `.data` file or a latent `.npy`, at the asked size."""
    from hairwarp.scene.hairstyles import Hairstyle, list_hairstyle_presets
    from hairwarp.scene.scene import preset_hairstyle

    stride = positive_int("strand_stride", strand_stride)
    n = positive_int("num_vertices", num_vertices, minimum=3)
    suffix = os.path.splitext(hairstyle)[1].lower()
    keep = None
    if suffix == ".data":
        from hairwarp.io.hair_data import load_hairstyle as load_data

        _existing_file("hairstyle", hairstyle)
        try:
            style = load_data(hairstyle, scalp, units=data_units(hairstyle, data_units_), up=data_up,
                              num_vertices=n, align="roots" if align_roots else "none")
        except ValueError as exc:
            raise ValueError(f"hairstyle: {_first_line(exc)}") from None
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
        raise ValueError(f"hairstyle: expected a preset ({', '.join(list_hairstyle_presets())}), a .data file "
                         f"or a latent .npy, got {hairstyle!r}")
    if stride > 1:
        keep = torch.arange(0, style.num_strands, stride)
    return style.subset(keep, n)


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


def build_scene(hairstyle: str = "long_straight", body: str = "default", pose: str = REST_POSE, *,
                frame: int | None = None, time: float | None = None, start: float | None = None,
                num_frames: int | None = None, duration: float | None = None, grow: str = "body",
                data_units: str = "auto", data_up: str = "y", align_roots: bool = False,
                strand_stride: int = 1, num_vertices: int = 100, seed: int = 0) -> Scene:
    """A `Scene` from names and files (see the module docstring).

    Args:
        hairstyle: a preset name, a `.data` file or a latent `.npy`.
        body: "default" or an SMPL-format model file.
        pose: "rest", a procedural motion name or an AMASS `.npz`.
        frame, time: keep this one frame (index, or time [s]) of the motion.
        start, num_frames: keep the motion from `start` [s] for `num_frames` frames (None: to
            the end). Without frame/time/start the whole motion is kept.
        duration: procedural motions: length [s] (None: the motion's own).
        grow: presets: grow the strands around the rest "body" or the "head" proxy alone.
        data_units: `.data`: "m", "cm", "mm" or "auto" (cm when the hair spans more than
            `AUTO_CM_EXTENT` units).
        data_up: `.data`: the file's up axis, "y" or "z".
        align_roots: `.data`: translate the hair so its mean root meets the scalp's.
        strand_stride: keep every this-many-th strand (presets: grow on every such root).
        num_vertices: vertices per strand N (>= 3).
        seed: presets: the hairstyle's seed.

    Raises:
        ValueError: naming the argument and what was expected.
    """
    model, scalp = load_body(body)
    style = load_hairstyle(hairstyle, model, scalp, grow=grow, data_units_=data_units, data_up=data_up,
                           align_roots=align_roots, strand_stride=strand_stride, num_vertices=num_vertices,
                           seed=seed)
    motion = load_motion(pose, model, default_body=body == "default", duration=duration)
    if frame is not None and time is not None:
        raise ValueError("frame: give frame or time, not both")
    if time is not None:
        where = f"frame {int(round(time * motion.fps))}"
        motion = frame_window(motion, int(round(time * motion.fps)), 1, "time")
    elif frame is not None:
        where = f"frame {frame}"
        motion = frame_window(motion, int(frame), 1, "frame")
    elif start is not None or num_frames is not None:
        first = int(round((start or 0.0) * motion.fps))
        count = None if num_frames is None else positive_int("num_frames", num_frames)
        motion = frame_window(motion, first, count, "start")
        where = f"from {start or 0.0:g} s"
    else:
        where = "all frames"
    label = (f"{style.name or 'hair'} on {'default body' if body == 'default' else os.path.basename(body)}, "
             f"{pose if pose == REST_POSE else os.path.basename(pose)} {where}")
    return Scene(body=model, scalp=scalp, hairstyle=style, motion=motion, name=label)
