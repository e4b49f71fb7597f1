"""`hairwarp drape`: drape one hairstyle on one body pose with a chosen method.

    hairwarp drape                                     # long straight hair, rest pose, L-BFGS
    hairwarp drape --hairstyle bob --pose head_turn --time 0.5 --method adam
    hairwarp drape --hairstyle my_hair.data --data-units cm --body my_smpl.npz --pose walk.npz --frame 40
    hairwarp drape --hairstyle z.npy --method static --checkpoint run/checkpoint.pt

Hairstyle: a procedural preset, a USC-HairSalon `.data` file, or a hair latent `.npy` (512
numbers, decoded through the shipped basis). Body: the default body or an SMPL-format model
(`.npz` / `.pkl`). Pose: the rest pose, a frame of a procedural motion, or a frame of an AMASS
`.npz`. Writes into --out: drape.usda (hair + body), drape.data (strands in metres),
drape.png and drape_rigid.png (front and side; red = inside the body), metrics.json and
metrics.md (penetration, length change, energy, time, against the rigid placement of Eq. 1).

This module also holds the scene and method options shared with `hairwarp simulate`.
"""

from __future__ import annotations

import argparse
import json
import os
import time

# Methods the command line offers; "auto" = the shipped network when present, else L-BFGS.
METHODS = ("auto", "static", "dynamic", "quaffure", "adam", "lbfgs", "reference", "rigid")
NETWORK_METHODS = ("static", "dynamic", "quaffure")
# `--data-units auto` reads a `.data` file as centimetres when its bounding box is larger than
# this many file units (a head of hair in metres spans < 1 m; PERM's, in cm, spans 20-100).
AUTO_CM_EXTENT = 3.0
# Body pose where the hairstyle's strands start: the rest pose is the body's T-pose.
REST_POSE = "rest"
# Most frames an animated GIF shows (rendering costs ~0.4-0.8 s a frame on a 2-core CPU).
GIF_FRAMES = 20


# ------------------------------------------------------------------------------ arguments


def add_scene_arguments(p: argparse.ArgumentParser, *, simulate: bool) -> None:
    """Hairstyle, body, pose/motion and size options (shared by drape and simulate)."""
    from hairwarp.scene.hairstyles import list_hairstyle_presets
    from hairwarp.scene.motion import list_motions

    g = p.add_argument_group("scene")
    g.add_argument("--hairstyle", default="long_straight", metavar="HAIR",
                   help=f"a preset ({', '.join(list_hairstyle_presets())}), a USC-HairSalon .data file, "
                        "or a hair latent .npy of 512 numbers (default: long_straight)")
    g.add_argument("--grow", choices=("body", "head"), default="body",
                   help="presets: grow the strands around the rest body (they fall over the shoulders and "
                        "back) or around the head proxy only (faster; long hair may pass through the torso) "
                        "(default: body)")
    g.add_argument("--data-units", choices=("auto", "m", "cm", "mm"), default="auto",
                   help=f".data: the file's length unit; auto = cm when the hair spans more than "
                        f"{AUTO_CM_EXTENT:g} units, else m (default: auto)")
    g.add_argument("--data-up", choices=("y", "z"), default="y", help=".data: the file's up axis (default: y)")
    g.add_argument("--align-roots", action="store_true",
                   help=".data: translate the hair so that its mean root meets the scalp's mean root")
    g.add_argument("--body", default="default",
                   help="'default' (the shipped body) or an SMPL-format model file (.npz or .pkl)")
    default_pose = "head_turn" if simulate else REST_POSE
    g.add_argument("--pose", default=default_pose, metavar="POSE",
                   help=f"'{REST_POSE}' (the body's rest pose), a procedural motion ({', '.join(list_motions())}) "
                        f"or an AMASS .npz (default: {default_pose})")
    g.add_argument("--duration", type=float, default=1.0 if simulate else None,
                   help="procedural motions: length [s] (default: " + ("1.0" if simulate else "the motion's own") + ")")
    if simulate:
        g.add_argument("--start", type=float, default=0.0, help="first time of the motion simulated [s] (default: 0)")
        g.add_argument("--frames", type=int, default=None, help="simulate at most this many frames (default: all)")
    else:
        when = g.add_mutually_exclusive_group()
        when.add_argument("--frame", type=int, default=None, help="frame of the motion to drape (default: 0)")
        when.add_argument("--time", type=float, default=None, help="time of the motion to drape [s]")
    g.add_argument("--strand-stride", type=int, default=1,
                   help="keep every K-th strand (presets: grow on every K-th scalp root) (default: 1)")
    g.add_argument("--num-vertices", type=int, default=100, help="vertices per strand (default: 100)")


def add_method_arguments(p: argparse.ArgumentParser, *, max_iterations: int) -> None:
    """--method, --checkpoint and the optimizers' options (shared by drape and simulate)."""
    g = p.add_argument_group("method")
    g.add_argument("--method", choices=METHODS, default="auto",
                   help="auto: the shipped network if this build has one, else lbfgs (default: auto)")
    g.add_argument("--checkpoint", default=None,
                   help="network methods: a checkpoint written by `hairwarp train` (default: the shipped one)")
    g.add_argument("--max-iterations", type=int, default=max_iterations,
                   help=f"adam/lbfgs/reference: iteration cap (default: {max_iterations})")
    g.add_argument("--patience", type=int, default=50,
                   help="adam/lbfgs: stop after this many iterations without decrease (default: 50)")
    g.add_argument("--no-hair-hair", action="store_true",
                   help="leave hair-hair contact out of the energy (3-4x faster evaluations on a CPU)")
    g.add_argument("--no-progress", action="store_true", help="no progress bars")


def add_parser(subparsers) -> None:
    from hairwarp.cli import add_common_arguments

    p = subparsers.add_parser(
        "drape", help="drape a hairstyle on a body pose; write USD, .data, pictures, metrics",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:3]),
    )
    add_scene_arguments(p, simulate=False)
    add_method_arguments(p, max_iterations=500)
    add_threads_argument(p)
    add_common_arguments(p)
    p.set_defaults(run=run)


def add_threads_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default: 1: Warp's CPU kernels run on one thread and torch's "
                        "small element-wise work here loses more to idle OpenMP threads than it gains; on a "
                        "busy 2-core CPU one thread ran an L-BFGS drape 5x faster than two)")


def set_threads(args) -> None:
    import torch

    torch.set_num_threads(positive_int("--threads", args.threads))


# ------------------------------------------------------------------------------ checks


def positive_int(name: str, value, minimum: int = 1) -> int:
    if value is None or int(value) < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def _existing_file(name: str, path: str) -> str:
    if not os.path.isfile(path):
        raise ValueError(f"{name}: no such file {path!r}")
    return path


# ------------------------------------------------------------------------------ scene


def load_body(args):
    """(body, scalp) from --body."""
    from hairwarp.scene.body import SMPLBody, default_body
    from hairwarp.scene.scalp import build_scalp

    if args.body == "default":
        body = default_body()
    else:
        _existing_file("--body", args.body)
        try:
            body = SMPLBody(args.body)
        except (ValueError, KeyError, OSError) as exc:
            raise ValueError(f"--body: {_first_line(exc)}") from None
    try:
        scalp = build_scalp(body)
    except ValueError as exc:
        raise ValueError(f"--body: cannot place a scalp on this body ({_first_line(exc)})") from None
    return body, scalp


def _subset_scalp(scalp, stride: int):
    import torch

    from hairwarp.scene.scalp import Scalp

    if stride == 1:
        return scalp
    keep = torch.arange(0, scalp.num_roots, stride)
    return Scalp(uv=scalp.uv[keep], positions=scalp.positions[keep], normals=scalp.normals[keep],
                 resolution=scalp.resolution)


def _subset_style(style, stride: int, num_vertices: int):
    import torch

    from hairwarp.scene.hairstyles import Hairstyle, resample_polylines

    keep = torch.arange(0, style.num_strands, stride)
    strands = style.strands[keep]
    if strands.shape[1] != num_vertices:
        strands = torch.as_tensor(resample_polylines(strands.double().numpy(), num_vertices), dtype=torch.float32)
    return Hairstyle(strands=strands.contiguous(), root_uv=style.root_uv[keep], root_normals=style.root_normals[keep],
                     root_index=style.root_index[keep], filtered=style.filtered, name=style.name, info=dict(style.info))


def data_units(path: str, units: str) -> str:
    """The unit of a `.data` file: `units`, or for "auto" cm/m by the hair's extent."""
    import numpy as np

    from hairwarp.io.hair_data import read_hair_data

    if units != "auto":
        return units
    strands = [s for s in read_hair_data(path) if len(s)]
    if not strands:
        return "m"
    points = np.concatenate(strands)
    return "cm" if float((points.max(0) - points.min(0)).max()) > AUTO_CM_EXTENT else "m"


def load_hairstyle(args, body, scalp):
    """A `Hairstyle` from --hairstyle (preset, .data, latent .npy) at the asked size."""
    import numpy as np
    import torch

    from hairwarp.scene.hairstyles import Hairstyle, generate_hairstyle, hairstyle_preset, list_hairstyle_presets

    stride = positive_int("--strand-stride", args.strand_stride)
    n = positive_int("--num-vertices", args.num_vertices, minimum=3)
    spec = args.hairstyle
    suffix = os.path.splitext(spec)[1].lower()
    if suffix == ".data":
        from hairwarp.io.hair_data import load_hairstyle as load_data

        _existing_file("--hairstyle", spec)
        try:
            units = data_units(spec, args.data_units)
            style = load_data(spec, scalp, units=units, up=args.data_up, num_vertices=n,
                              align="roots" if args.align_roots else "none")
        except ValueError as exc:
            raise ValueError(f"--hairstyle: {_first_line(exc)}") from None
        return _subset_style(style, stride, n)
    if suffix == ".npy":
        from hairwarp.scene.hair_latent import HairLatentBasis

        _existing_file("--hairstyle", spec)
        try:
            z = np.load(spec, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ValueError(f"--hairstyle: {spec!r} is not a readable .npy ({_first_line(exc)})") from None
        basis = HairLatentBasis.load_default()
        if not np.issubdtype(z.dtype, np.number) or z.size != basis.latent_dim:
            raise ValueError(f"--hairstyle: a latent .npy holds {basis.latent_dim} numbers; {spec!r} holds "
                             f"an array of shape {z.shape} and dtype {z.dtype}")
        if not np.isfinite(z).all():
            raise ValueError(f"--hairstyle: {spec!r} holds NaN or Inf")
        strands, uv = basis.decode(torch.as_tensor(z, dtype=torch.float64).reshape(-1), scalp)
        index = torch.cdist(uv.double(), scalp.uv.double()).argmin(dim=1)  # the scalp root of each strand
        style = Hairstyle(strands=strands.to(torch.float32), root_uv=uv.to(torch.float32),
                          root_normals=scalp.normals[index].to(torch.float32), root_index=index,
                          filtered=torch.zeros(0, dtype=torch.int64), name=os.path.basename(spec))
        return _subset_style(style, stride, n)
    if spec not in list_hairstyle_presets():
        raise ValueError(f"--hairstyle: expected a preset ({', '.join(list_hairstyle_presets())}), a .data file "
                         f"or a latent .npy, got {spec!r}")
    surface = (body.rest_vertices, body.faces) if args.grow == "body" else None
    style = generate_hairstyle(_subset_scalp(scalp, stride), hairstyle_preset(spec, seed=args.seed),
                               num_vertices=n, body=surface)
    style.name = spec
    return style


def _rest_pelvis(body):
    """(3,) rest position of the body's root joint [m], for the AMASS z-up conversion."""
    model = getattr(body, "model", None)
    if model is None or getattr(model, "J_regressor", None) is None:
        return None
    return (model.J_regressor[0].double() @ model.v_template.double()).numpy()


def load_motion(args, body):
    """The full `Motion` of --pose (one frame for the rest pose)."""
    import torch

    from hairwarp.scene.motion import list_motions, load_amass, procedural_motion
    from hairwarp.scene.scene import static_motion

    pose = args.pose
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if pose == REST_POSE:
        return static_motion(name=REST_POSE)
    if pose in list_motions():
        return procedural_motion(pose, duration=args.duration)
    if pose.lower().endswith(".npz"):
        _existing_file("--pose", pose)
        try:
            motion = load_amass(pose, root_joint=_rest_pelvis(body))
        except ValueError as exc:
            raise ValueError(f"--pose: {_first_line(exc)}") from None
        if args.body == "default" and bool(motion.betas.abs().sum() > 0):
            # AMASS betas are SMPL's shape space; the default body has its own.
            print("note: the motion's SMPL betas do not apply to the default body; using its mean shape")
            motion = motion.replace(betas=torch.zeros_like(motion.betas))
        return motion
    raise ValueError(f"--pose: expected '{REST_POSE}', a procedural motion ({', '.join(list_motions())}) "
                     f"or an AMASS .npz, got {pose!r}")


def frame_window(motion, start_frame: int, count: int | None, name: str):
    """The motion cut to frames [start_frame, start_frame + count)."""
    if not 0 <= start_frame < motion.num_frames:
        raise ValueError(f"{name}: the motion has {motion.num_frames} frames "
                         f"({motion.duration:.3f} s at {motion.fps:g} fps); frame {start_frame} is outside it")
    end = motion.num_frames if count is None else min(motion.num_frames, start_frame + count)
    return motion.replace(poses=motion.poses[start_frame:end].clone(), trans=motion.trans[start_frame:end].clone())


def build_scene(args, *, simulate: bool):
    """The `Scene` that --hairstyle, --body and --pose describe (drape: one frame)."""
    from hairwarp.scene.scene import Scene

    body, scalp = load_body(args)
    style = load_hairstyle(args, body, scalp)
    motion = load_motion(args, body)
    if simulate:
        start = int(round(args.start * motion.fps))
        count = None if args.frames is None else positive_int("--frames", args.frames)
        motion = frame_window(motion, start, count, "--start")
        where = f"from {args.start:g} s"
    else:
        frame = 0 if args.frame is None else args.frame
        name = "--frame"
        if args.time is not None:
            frame, name = int(round(args.time * motion.fps)), "--time"
        motion = frame_window(motion, frame, 1, name)
        where = f"frame {frame}"
    label = f"{style.name or 'hair'} on {'default body' if args.body == 'default' else os.path.basename(args.body)}, " \
            f"{args.pose if args.pose == REST_POSE else os.path.basename(args.pose)} {where}"
    return Scene(body=body, scalp=scalp, hairstyle=style, motion=motion, name=label)


def describe(scene, frames) -> str:
    return (f"scene {scene.name}: {scene.hairstyle.num_strands} strands x {scene.hairstyle.strands.shape[1]} vertices, "
            f"{scene.num_frames} frame(s) at {scene.motion.fps:g} fps, body {scene.body.num_vertices} vertices "
            f"({frames.body_mesh.num_faces} of {scene.body.num_faces} triangles within the hair's reach)")


# ------------------------------------------------------------------------------ methods


class Runner:
    """One method behind `drape(scene, frames)` / `simulate(scene, frames)`.

    Both return (positions (B or T, M, N, 3) [m], ms per frame or None, label, info dict).
    """

    def __init__(self, name: str, config, method=None, simulator=None, network: bool = False):
        self.name, self.config, self.method, self.simulator = name, config, method, simulator
        self.network = network or simulator is not None

    def drape(self, scene, frames):
        return self._run(scene, frames, dynamic=False)

    def simulate(self, scene, frames):
        return self._run(scene, frames, dynamic=True)

    def _run(self, scene, frames, *, dynamic: bool):
        try:
            if self.simulator is not None:
                positions, label, ms = _simulator_run(self.simulator, scene, frames, dynamic=dynamic)
                return positions, ms, label, {}
            self.method.prepare(scene)
            result = self.method.simulate(scene, frames=frames) if dynamic else self.method.drape(frames)
        except (ValueError, FileNotFoundError, OSError) as exc:
            if not self.network:
                raise
            # A network that cannot load its checkpoint: say which method, in one line.
            raise ValueError(f"--method {self.name}: {_first_line(exc)}") from None
        return result.positions, result.time_ms, self.name, dict(result.info)


def _simulator_run(simulator, scene, frames, *, dynamic: bool):
    if dynamic:
        return simulator.simulate_scene(scene, frames)
    from hairwarp.bench.timing import synchronize

    simulator.drape(scene, frames)  # warm-up
    device = frames.rigid.positions.device
    synchronize(device)
    start = time.perf_counter()
    positions = simulator.drape(scene, frames)
    synchronize(device)
    return positions, "HairFormer static network", (time.perf_counter() - start) * 1e3 / positions.shape[0]


def _registered_methods() -> list[str]:
    from hairwarp.evaluation.methods import list_methods

    try:  # the networks register themselves there when this build has them
        import hairwarp.evaluation.network_methods  # noqa: F401
    except ImportError:
        pass
    return list_methods()


def _load_simulator(path: str | None, device):
    """A `HairFormerSimulator` from a checkpoint file, or the shipped one; None when there is none."""
    from hairwarp.inference import HairFormerSimulator, load_default_simulator

    if path is None:
        return load_default_simulator(device)
    from hairwarp.models.checkpoint import load_checkpoint

    try:
        model = load_checkpoint(path, device=device).model
    except Exception as exc:  # a foreign or truncated file: say which and why, in one line
        raise ValueError(f"--checkpoint: cannot load {path!r} ({_first_line(exc)})") from None
    static = getattr(model, "static", None)
    return HairFormerSimulator(static, model) if static is not None else HairFormerSimulator(model)


def make_runner(args, device, *, fps: float, simulate: bool) -> Runner:
    """The method of --method (auto: the shipped network when present, else L-BFGS)."""
    from hairwarp.config import EnergyConfig
    from hairwarp.evaluation.methods import MethodOptions, make_method

    name = args.method
    config = EnergyConfig(time_step=1.0 / fps)
    if args.no_hair_hair:
        config = config.replace(hair_hair_weight=0.0)
    if args.checkpoint is not None:
        _existing_file("--checkpoint", args.checkpoint)
    if name == "auto":
        simulator = _load_simulator(args.checkpoint, device)
        if simulator is not None and (not simulate or simulator.dynamic is not None):
            return Runner("dynamic" if simulate else "static", config, simulator=simulator)
        name = "lbfgs"
    options = MethodOptions(energy_config=config,
                            max_iterations=positive_int("--max-iterations", args.max_iterations, minimum=0),
                            patience=positive_int("--patience", args.patience),
                            reference_max_iterations=max(1, args.max_iterations), progress=not args.no_progress)
    if name in NETWORK_METHODS:
        network_module = None
        if name in _registered_methods():
            import hairwarp.evaluation.network_methods as network_module
        if network_module is not None and (args.checkpoint is None or hasattr(network_module, "set_checkpoint")):
            try:
                if hasattr(network_module, "set_checkpoint"):
                    network_module.set_checkpoint(name, args.checkpoint)
                return Runner(name, config, method=make_method(name, options), network=True)
            except (ValueError, FileNotFoundError, OSError, RuntimeError) as exc:
                raise ValueError(f"--method {name}: {_first_line(exc)}") from None
        if name == "quaffure":
            raise ValueError("--method quaffure: no Quaffure model in this build "
                             "(train one with `hairwarp train quaffure`)")
        simulator = _load_simulator(args.checkpoint, device)
        if simulator is None:
            raise ValueError(f"--method {name}: no trained checkpoint is shipped with this build; "
                             f"pass --checkpoint FILE (written by `hairwarp train {name}`) or use --method lbfgs")
        if name == "dynamic" and simulator.dynamic is None:
            raise ValueError("--method dynamic: the checkpoint holds a static network only; use --method static")
        if name == "static" and simulate:
            simulator.dynamic = None  # frame by frame with the static network
        return Runner(name, config, simulator=simulator)
    return Runner(name, config, method=make_method(name, options))


# ------------------------------------------------------------------------------ outputs


def metrics_rows(frames, positions, rigid_label: str = "rigid placement (Eq. 1)"):
    """Per-frame penetration [%] and length change [%] of the rigid placement and of `positions`.

    Returns:
        (signed distances (T, M, N) of `positions` [m], {"rigid": {...}, "method": {...}}) with
        lists over frames.
    """
    from hairwarp.evaluation.metrics import length_change_percent
    from hairwarp.ops import hair_body_signed_distance

    rest = frames.inputs.rest_lengths
    out = {}
    sd_method = None
    for key, x in (("rigid", frames.rigid.positions), ("method", positions)):
        sd = hair_body_signed_distance(x.detach(), frames.body_mesh)
        pen = (sd[:, :, 2:] < 0).float().mean(dim=(1, 2)) * 100.0  # moving vertices (2..N-1), as Table 1
        out[key] = {"penetration_percent": pen.tolist(),
                    "length_change_percent": length_change_percent(x.detach(), rest).tolist()}
        if key == "method":
            sd_method = sd
        else:
            out[key]["signed_distance"] = sd
    return sd_method, out


def picture_distances(sd):
    """Signed distances for the pictures: vertices 0 and 1 (fixed on the scalp, |d| at float32
    noise, often a hair below zero) shown as outside, so red marks only what a method moved inside."""
    sd = sd.detach().clone()
    sd[..., :2] = sd[..., :2].clamp_min(0.0)
    return sd


def _mean(values) -> float:
    return float(sum(values) / len(values))


def markdown_table(rows: list[tuple[str, str, dict]]) -> str:
    """| method | ms/frame | penetration % | length change % | from (label, ms text, metrics)."""
    lines = ["| method | ms/frame | penetration % (mean over frames) | length change % (mean) |",
             "|---|---:|---:|---:|"]
    for label, ms, m in rows:
        lines.append(f"| {label} | {ms} | {_mean(m['penetration_percent']):.3f} | "
                     f"{_mean(m['length_change_percent']):.3f} |")
    return "\n".join(lines)


def write_metrics(out: str, stem: str, record: dict, table: str) -> list[str]:
    json_path = os.path.join(out, f"{stem}_metrics.json")
    md_path = os.path.join(out, f"{stem}_metrics.md")
    with open(json_path, "w") as f:
        json.dump(record, f, indent=1)
    with open(md_path, "w") as f:
        f.write(table + "\n")
    return [json_path, md_path]


def run(args) -> int:
    import torch

    from hairwarp.cli import resolve_device
    from hairwarp.energy import total_energy
    from hairwarp.io.hair_data import write_hair_data
    from hairwarp.io.usd import write_usd
    from hairwarp.render.preview import render_drape

    device = resolve_device(args.device)
    set_threads(args)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    scene = build_scene(args, simulate=False)
    runner = make_runner(args, device, fps=scene.motion.fps, simulate=False)
    os.makedirs(args.out, exist_ok=True)
    frames = scene.frames(device=device)
    print(describe(scene, frames))
    positions, ms, label, info = runner.drape(scene, frames)
    sd, metrics = metrics_rows(frames, positions)
    with torch.no_grad():
        for key, x in (("rigid", frames.rigid.positions), ("method", positions)):
            metrics[key]["energy"] = total_energy(x, frames.inputs, runner.config).total.tolist()
    rigid_sd = metrics["rigid"].pop("signed_distance")
    ms_text = "-" if ms is None else f"{ms:.1f}"
    table = markdown_table([("rigid placement (Eq. 1)", "-", metrics["rigid"]), (label, ms_text, metrics["method"])])
    print(table)

    hair = positions.detach().cpu()
    body_v = frames.posed.vertices.detach().cpu()
    faces = scene.body.faces.cpu()
    written = [write_usd(os.path.join(args.out, "drape.usda"), hair[0], body_v[0], faces, fps=scene.motion.fps)]
    data_path = os.path.join(args.out, "drape.data")
    write_hair_data(data_path, hair[0])
    written.append(data_path)
    written.append(render_drape(os.path.join(args.out, "drape.png"), hair[0], body_v[0], faces,
                                signed_distance=picture_distances(sd[0]).cpu(), title=f"{label}: red = inside the body"))
    written.append(render_drape(os.path.join(args.out, "drape_rigid.png"), frames.rigid.positions[0].cpu(),
                                body_v[0], faces, signed_distance=picture_distances(rigid_sd[0]).cpu(),
                                title="rigid placement (Eq. 1): red = inside the body"))
    record = {"command": "drape", "scene": scene.name, "method": label, "method_info": _jsonable(info),
              "ms_per_frame": ms, "device": str(device), "strands": scene.hairstyle.num_strands,
              "vertices": int(scene.hairstyle.strands.shape[1]), "rigid": metrics["rigid"], "result": metrics["method"]}
    written += write_metrics(args.out, "drape", record, table)
    print(f"wrote {', '.join(os.path.basename(p) for p in written)} into {args.out} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


def _jsonable(info: dict) -> dict:
    out = {}
    for k, v in info.items():
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[k] = v
        elif isinstance(v, (list, tuple)) and all(isinstance(x, (int, float, str, bool)) for x in v):
            out[k] = list(v)
        else:
            out[k] = str(v)
    return out
