"""What the commands share: common flags, the scene and method options, outputs and metrics tables.

Commands sit on top of the library: scenes come from `hairwarp.builder`, methods from the
registry in `hairwarp.methods`, figures from `hairwarp.metrics`; this module only maps flags
onto them and writes what a command writes.
"""

from __future__ import annotations

import argparse
import json
import os

# Most frames an animated GIF shows by default (rendering costs ~0.4-0.8 s a frame on a 2-core CPU).
DEFAULT_GIF_FRAMES = 20


def add_common_arguments(parser: argparse.ArgumentParser, *, out_default: str = "hairwarp-out") -> None:
    """The flags every command shares: --device, --seed, --out."""
    parser.add_argument("--device", default="cpu", help="torch device: cpu or cuda[:N] (default: cpu)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--out", default=out_default, help=f"output folder (default: ./{out_default}/)")


def add_threads_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default: 1: Warp's CPU kernels run on one thread and torch's "
                        "small element-wise work here loses more to idle OpenMP threads than it gains; on a "
                        "busy 2-core CPU one thread ran an L-BFGS drape 5x faster than two). The two contact "
                        "terms still run side by side on two cores when torch's inter-op threads allow "
                        "(torch.get_num_interop_threads() > 1, its default on 2+ cores)")


def set_threads(args) -> None:
    import torch

    from hairwarp.builder import positive_int

    torch.set_num_threads(positive_int("--threads", args.threads))


def add_scene_arguments(p: argparse.ArgumentParser, *, simulate: bool) -> None:
    """Hairstyle, body, pose/motion and size options (`hairwarp.builder.build_scene`)."""
    from hairwarp.builder import AUTO_CM_EXTENT, REST_POSE
    from hairwarp.scene.hairstyles import list_hairstyle_presets
    from hairwarp.scene.motion import list_motions

    g = p.add_argument_group("scene")
    g.add_argument("--hairstyle", default="long_straight", metavar="HAIR",
                   help=f"a preset ({', '.join(list_hairstyle_presets())}), a USC-HairSalon .data file, "
                        "a USD groom (BasisCurves in .usd/.usda/.usdc), or a hair latent .npy of 512 numbers "
                        "(default: long_straight)")
    g.add_argument("--grow", choices=("body", "head"), default="body",
                   help="presets: grow the strands around the rest body (they fall over the shoulders and "
                        "back) or around the head proxy only (faster; long hair may pass through the torso) "
                        "(default: body)")
    g.add_argument("--data-units", choices=("auto", "m", "cm", "mm"), default="auto",
                   help=f".data: the file's length unit; auto = cm when the hair spans more than "
                        f"{AUTO_CM_EXTENT:g} units, else m (default: auto)")
    g.add_argument("--data-up", choices=("y", "z"), default="y", help=".data: the file's up axis (default: y)")
    fit = g.add_mutually_exclusive_group()
    fit.add_argument("--fit", choices=("auto", "similarity", "translate", "none"), default="auto",
                     help="grooms from files: auto = when the roots lie off the scalp (made on another head), fit a "
                          "similarity transform (scale, rotation, offset) of the roots onto the head by ICP, then "
                          "project them; similarity = always; translate = mean root onto the mean scalp root; "
                          "none = keep the file's placement (default: auto)")
    fit.add_argument("--no-fit", dest="fit", action="store_const", const="none", help="same as --fit none")
    g.add_argument("--body", default="default",
                   help="'default' (the shipped body), an SMPL-format model (.npz/.pkl), a mesh (.obj/.ply/.glb/...), "
                        "or an animated mesh (time-sampled .usd/.usda/.usdc, or an .npz of vertices (T, V, 3), "
                        "faces and fps); a mesh body plays its own frames and takes no --pose")
    default_pose = "head_turn" if simulate else REST_POSE
    g.add_argument("--pose", default=None, metavar="POSE",
                   help=f"'{REST_POSE}' (the body's rest pose), a procedural motion ({', '.join(list_motions())}) "
                        f"or an AMASS .npz (default: {default_pose}; a mesh body plays its own frames)")
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
                   help="keep every K-th strand of a groom file (presets: grow on one scalp root in K, spread over "
                        "the scalp) (default: 1)")
    g.add_argument("--num-vertices", type=int, default=100, help="vertices per strand (default: 100)")
    g.add_argument("--guides", type=int, default=None, metavar="K",
                   help="simulate the groom through K guide strands, the others following them (default: every "
                        "strand of a groom of at most 1024, else 1024 guides)")


def build_scene_from_args(args, *, simulate: bool):
    """The `Scene` of the scene flags (drape: one frame; simulate: a window of the motion)."""
    from hairwarp.builder import build_scene

    from hairwarp.builder import REST_POSE

    window = dict(start=args.start, num_frames=args.frames) if simulate else \
        dict(frame=args.frame if args.frame is not None or args.time is not None else 0, time=args.time)
    return build_scene(args.hairstyle, args.body, args.pose, duration=args.duration, grow=args.grow,
                       default_motion="head_turn" if simulate else REST_POSE,
                       data_units=args.data_units, data_up=args.data_up, fit=args.fit,
                       strand_stride=args.strand_stride, num_vertices=args.num_vertices, seed=args.seed,
                       guides=args.guides, **window)


def method_name(text: str) -> str:
    """Argparse type of --method: a registered name, NAME+refine or NAME+settle (else a usage error)."""
    from hairwarp.methods import available, split_composition

    base, suffix = text, "+"
    while suffix is not None:
        base, suffix = split_composition(base)
    if base not in available():
        raise argparse.ArgumentTypeError(f"unknown method {text!r}; expected one of {', '.join(available())}, "
                                         f"or any of them followed by '+refine' or '+settle'")
    return text


def add_method_arguments(p: argparse.ArgumentParser, *, max_iterations: int, default: str = "auto") -> None:
    """--method, --refine, --checkpoint and the optimizers' options."""
    from hairwarp.methods import AUTO_REFINE, available

    g = p.add_argument_group("method")
    g.add_argument("--method", default=default, metavar="METHOD", type=method_name,
                   help=f"one of {', '.join(available())}, or any of them followed by '+refine' (L-BFGS) or "
                        "'+settle' (damped physics steps); auto: a motion "
                        "runs the physics where it meets its speed goal (a CPU, up to 256 x 100 hair), else the "
                        f"shipped network (a drape: static, finished by {AUTO_REFINE} L-BFGS iterations; a motion: "
                        "the inertial step, or dynamic where the step cannot run), every frame left with more "
                        "vertices inside or a higher energy than the rigid placement redone by L-BFGS (default: "
                        f"{default})")
    g.add_argument("--refine", type=int, default=0, metavar="K",
                   help="finish a network method with K L-BFGS iterations of the same energy (default: 0; "
                        f"auto: {AUTO_REFINE})")
    g.add_argument("--checkpoint", default=None,
                   help="network methods: a checkpoint written by `hairwarp train` (default: the shipped one)")
    g.add_argument("--keep-out", action=argparse.BooleanOptionalAction, default=True,
                   help="network methods: push the output's vertices out of the body, rest lengths kept (the "
                        "inertial step's body pass; default: on)")
    g.add_argument("--settle", type=int, default=None, metavar="K",
                   help="damped physics steps with the pose held: the inertial step's settle of a motion's first "
                        "frame (default: the step's own, 20; 0: none; once a motion, ~35 s for 600 strands on a 2-core "
                        "CPU), and a network's finish per frame (NAME+settle, default 20; given with a network "
                        "method, it adds +settle)")
    g.add_argument("--max-iterations", type=int, default=max_iterations,
                   help=f"adam/lbfgs/reference: iteration cap (default: {max_iterations})")
    g.add_argument("--patience", type=int, default=50,
                   help="adam/lbfgs: stop after this many iterations without decrease (default: 50)")
    g.add_argument("--no-hair-hair", action="store_true",
                   help="leave hair-hair contact out of the energy (about 2x faster L-BFGS on a CPU)")
    g.add_argument("--no-progress", action="store_true", help="no progress bars")


def method_from_args(args):
    """The method of --method with the options of the method flags (a `hairwarp.methods.Method`)."""
    from hairwarp.builder import positive_int
    from hairwarp.config import EnergyConfig
    from hairwarp.methods import NETWORK_METHODS, MethodOptions, make

    config = EnergyConfig()
    if args.no_hair_hair:
        config = config.replace(hair_hair_weight=0.0)
    name = args.method
    refine = positive_int("--refine", args.refine, minimum=0)
    if refine > 0 and name not in ("auto",) and not name.endswith("+refine"):
        name = name + "+refine"
    settle = None if args.settle is None else positive_int("--settle", args.settle, minimum=0)
    if settle and name.split("+")[0] in NETWORK_METHODS and not name.endswith("+settle"):
        name = name + "+settle"
    options = MethodOptions(energy_config=config,
                            max_iterations=positive_int("--max-iterations", args.max_iterations, minimum=0),
                            patience=positive_int("--patience", args.patience),
                            reference_max_iterations=max(1, args.max_iterations), checkpoint=args.checkpoint,
                            refine=refine, keep_out=args.keep_out, progress=not args.no_progress,
                            settle=settle)
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        raise ValueError(f"--checkpoint: no such file {args.checkpoint!r}")
    return make(name, options), config


def describe(scene, frames) -> str:
    strands = f"{scene.hairstyle.num_strands} strands" if scene.guides is None else \
        f"{scene.guides.num_strands} strands through {scene.guides.num_guides} guides"
    return (f"scene {scene.name}: {strands} x {scene.hairstyle.strands.shape[1]} vertices, "
            f"{scene.num_frames} frame(s) at {scene.motion.fps:g} fps, body {scene.body.num_vertices} vertices "
            f"({frames.triangles_within_reach()} of {scene.body.num_faces} triangles within the hair's reach)")


def whole_groom(frames, label: str, positions, signed_distance, rigid_signed_distance):
    """For a scene simulated through guides: every strand of the method's result and its rows.

    Args:
        frames: the scene's frames; label: the method's name.
        positions: (B, K, N, 3) the method's guides [m]; signed_distance: (B, K, N) theirs [m];
        rigid_signed_distance: (B, K, N) the rigid placement's [m].

    Returns:
        None without guides; else {"positions": (B, M, N, 3), "signed_distance": (B, M, N),
        "rows": table rows of all strands (rigid, method), "metrics": {"rigid", "method"} per
        frame over all strands, "body_pass": the body pass's facts, "width": strand width [m]}.
    """
    from hairwarp.metrics import groom_metrics
    from hairwarp.scene.guides import strand_width

    guides = frames.scene.guides
    if guides is None:
        return None
    method = groom_metrics(frames, positions, signed_distance)
    rigid = groom_metrics(frames, frames.rigid.positions, rigid_signed_distance, body_pass=False)
    m = guides.num_strands
    return {"positions": method["positions"], "signed_distance": method["signed_distance"],
            "rows": [(f"rigid, all {m} strands", "-", rigid["per_frame"]),
                     (f"{label}, all {m} strands", "-", method["per_frame"])],
            "metrics": {"rigid": rigid["per_frame"], "method": method["per_frame"]}, "body_pass": method["body_pass"],
            "width": strand_width(m, guides.num_guides), "guides": guides.guide_indices}


def with_whole_groom(groom: dict, scene, rows: list, fidelity: dict | None, record: dict, metrics: dict):
    """The table rows, fidelity labels and record of a command once `whole_groom` ran: the whole
    groom's rows first, the guides' tagged "(K guides)"; the record's figures over all strands,
    the guides' beside them. Returns (rows, fidelity); `record` is updated in place.
    """
    tag = f" ({scene.guides.num_guides} guides)"
    record.update(strands=scene.guides.num_strands, guides=scene.guides.num_guides, guides_rigid=metrics["rigid"],
                  guides_result=metrics["method"], rigid=groom["metrics"]["rigid"], result=groom["metrics"]["method"],
                  body_pass=groom["body_pass"])
    return (groom["rows"] + [(name + tag, ms, m) for name, ms, m in rows],
            None if fidelity is None else {k + tag: v for k, v in fidelity.items()})


def picture_distances(sd):
    """Signed distances for the pictures: the fixed vertices 0 and 1 (on the scalp, |d| at
    float32 noise, often a hair below zero) shown as outside, so red marks only what a method
    moved inside.
    """
    from hairwarp.config import NUM_FIXED_VERTICES

    sd = sd.detach().clone()
    sd[..., :NUM_FIXED_VERTICES] = sd[..., :NUM_FIXED_VERTICES].clamp_min(0.0)
    return sd


def markdown_table(rows: list[tuple[str, str, dict]], fidelity: dict | None = None) -> str:
    """| method | ms/frame | penetration % | length change % | from (label, ms text, per-frame metrics);
    with `fidelity` (label -> `hairwarp.metrics.motion_fidelity`), the columns against the physics.
    """
    def mean(values) -> float:
        return float(sum(values) / len(values))

    def fmt(value, spec):
        return "-" if value is None else format(value, spec)

    head = "| method | ms/frame | penetration % (mean over frames) | length change % (mean) |"
    rule = "|---|---:|---:|---:|"
    if fidelity is not None:
        # The largest move a frame beyond the rigid placement: a strand flung out (a pinch the
        # body did not know of threw the physics' hair at 8.8 m/s; docs/physics.md).
        head += (" distance to physics mean / worst frame [mm] | worst strands (p99, worst frame) [mm] | tip swing [mm] |"
                 " swing ratio | swing correlation | largest move a frame [mm] |")
        rule += "---:|---:|---:|---:|---:|---:|"
    lines = [head, rule]
    for label, ms, m in rows:
        line = f"| {label} | {ms} | {mean(m['penetration_percent']):.3f} | {mean(m['length_change_percent']):.3f} |"
        if fidelity is not None:
            f = fidelity.get(label, {})
            line += (f" {fmt(f.get('mean_distance_mm'), '.1f')} / {fmt(f.get('max_distance_mm'), '.1f')} |"
                     f" {fmt(f.get('strand_distance_p99_mm'), '.1f')} | {fmt(f.get('swing_mm'), '.1f')} |"
                     f" {fmt(f.get('swing_amplitude_ratio'), '.2f')} |"
                     f" {fmt(f.get('swing_correlation'), '+.2f')} | {fmt(f.get('largest_step_mm'), '.1f')} |")
        lines.append(line)
    return "\n".join(lines)


def add_against_argument(p, stem: str) -> None:
    """`--against physics|reference`: run that method on the same frames and measure against it."""
    p.add_argument("--against", default=None, choices=("physics", "reference"),
                   help="also run the physics (or its tight setting) on the same frames and measure the method "
                        f"against it (columns in the table; {stem}_side_by_side.png beside it)")


def static_beside(out: str, stem: str, frames, drapes: dict, signed_distances: dict, optimum: str,
                  config) -> tuple[dict, str]:
    """Drapes against the optimum: `hairwarp.metrics.static_fidelity` per label and OUT/<stem>_side_by_side.png.

    Args:
        drapes: label -> (B, M, N, 3) positions [m], `optimum` among them.
        signed_distances: label -> (B, M, N) [m].
        config: the energy's config (the ratio E / E*).
    """
    from hairwarp.metrics import drape_fidelity
    from hairwarp.render.preview import render_side_by_side

    everything = {"rigid": frames.rigid.positions, **drapes}
    fidelity = {label: drape_fidelity(x, drapes[optimum], frames.inputs, config) for label, x in everything.items()}
    cpu = {label: x.detach().cpu()[:1] for label, x in drapes.items()}
    sds = {label: picture_distances(sd[:1]).cpu() for label, sd in signed_distances.items()}
    path = render_side_by_side(os.path.join(out, f"{stem}_side_by_side.png"), cpu,
                               frames.posed.vertices.detach().cpu()[:1], frames.scene.body.faces.cpu(), sds,
                               fps=float(frames.scene.motion.fps),
                               title="side by side: " + " | ".join(cpu) + "  (red = inside the body)")
    return fidelity, path


def static_table(rows: list[tuple[str, str, dict]], fidelity: dict) -> str:
    """`markdown_table` of drapes with the columns against the optimum (label -> static_fidelity)."""
    def fmt(value, spec):
        return "-" if value is None else format(value, spec)

    lines = markdown_table(rows).split("\n")
    lines[0] += " E / E* | distance to the optimum mean / p95 [mm] | tip height vs the optimum [mm] |"
    lines[1] += "---:|---:|---:|"
    for i, (label, _, _) in enumerate(rows):
        f = fidelity.get(label, {})
        lines[i + 2] += (f" {fmt(f.get('energy_ratio'), '.3f')} | {fmt(f.get('mean_distance_mm'), '.1f')} / "
                         f"{fmt(f.get('p95_distance_mm'), '.1f')} | {fmt(f.get('tip_height_difference_mm'), '+.1f')} |")
    return "\n".join(lines)


def beside_the_physics(out: str, stem: str, frames, motions: dict, signed_distances: dict, physics: str,
                       gif_frames: int = 20) -> tuple[dict, list[str]]:
    """Each motion against the physics: fidelity metrics, a swing plot and side-by-side pictures.

    Args:
        out: output folder.
        stem: file-name stem (OUT/<stem>_swing.png, <stem>_side_by_side.png and .gif).
        frames: the scene's frames (all, in order).
        motions: label -> (T, M, N, 3) positions [m], `physics` among them.
        signed_distances: label -> (T, M, N) signed distances [m] (red where negative).
        physics: the label of the physics simulation.
        gif_frames: most frames the GIF shows.

    Returns:
        (label -> `hairwarp.metrics.motion_fidelity` dict (rigid placement included), paths written).
    """
    from hairwarp.evaluation.charts import swing_plot
    from hairwarp.metrics import mean_tip_offset, motion_fidelity
    from hairwarp.render.preview import render_side_by_side

    rigid = frames.rigid.positions.detach().cpu()
    cpu = {label: x.detach().cpu() for label, x in motions.items()}
    fidelity = {label: motion_fidelity(x, cpu[physics], rigid) for label, x in {"rigid": rigid, **cpu}.items()}
    fps = float(frames.scene.motion.fps)
    curves = {label: mean_tip_offset(x, rigid) for label, x in {"rigid": rigid, **cpu}.items()}
    paths = [swing_plot(curves, os.path.join(out, f"{stem}_swing.png"), fps=fps, physics=physics,
                        title=f"{frames.scene.name}: mean tip offset from the rigid placement")]
    body_v = frames.posed.vertices.detach().cpu()
    faces = frames.scene.body.faces.cpu()
    sds = {label: picture_distances(sd).cpu() for label, sd in signed_distances.items()}
    title = "side by side: " + " | ".join(cpu) + "  (red = inside the body)"
    paths.append(render_side_by_side(os.path.join(out, f"{stem}_side_by_side.png"), cpu, body_v, faces, sds,
                                     fps=fps, title=title))
    stride = max(1, -(-rigid.shape[0] // gif_frames))
    paths.append(render_side_by_side(os.path.join(out, f"{stem}_side_by_side.gif"), cpu, body_v, faces, sds,
                                     fps=fps, stride=stride, title=title))
    return fidelity, paths


def write_metrics(out: str, stem: str, record: dict, table: str) -> list[str]:
    """OUT/<stem>_metrics.json and OUT/<stem>_metrics.md; returns both paths."""
    from hairwarp.runtime import jsonable

    json_path = os.path.join(out, f"{stem}_metrics.json")
    md_path = os.path.join(out, f"{stem}_metrics.md")
    with open(json_path, "w") as f:
        json.dump(jsonable(record), f, indent=1)
    with open(md_path, "w") as f:
        f.write(table + "\n")
    return [json_path, md_path]


def run_and_score(method, frames, config, *, simulate: bool):
    """Run `method` on `frames`; (result, metrics {"rigid", "method"} per frame, signed distances)."""
    from hairwarp.metrics import frame_metrics_of

    result = method.simulate(frames) if simulate else method.drape(frames)
    scored = frame_metrics_of({"rigid": frames.rigid.positions, "method": result.positions}, frames,
                              None if simulate else config)
    (rigid, rigid_sd), (ours, sd) = scored["rigid"], scored["method"]
    return result, {"rigid": rigid, "method": ours}, sd, rigid_sd


def write_animation(out: str, stem: str, frames, positions, signed_distance, label: str, gif_frames: int,
                    *, usd_format: str = "usdc", guides=None, width: float = 1e-3) -> list[str]:
    """USD animation, last frame as `.data`, a 6-frame strip PNG and a GIF; returns the paths.

    Args:
        out: output folder.
        stem: file-name stem.
        frames: the scene's frames (all frames, in order).
        positions: (T, M, N, 3) hair positions [m].
        signed_distance: (T, M, N) signed distances of `positions` to the body [m].
        label: the method's name, for the titles.
        gif_frames: most frames the GIF shows.
        usd_format: "usdc" (binary, the default: what DCC tools open fastest) or "usda" (text).
        guides: a groom's guide strand indices (drawn thick, the others thin), or None.
        width: the strands' width in the USD [m].
    """
    from hairwarp.io.hair_data import write_hair_data
    from hairwarp.io.usd import write_usd
    from hairwarp.render.preview import render_animation, render_sequence

    hair = positions.detach().cpu()
    body_v = frames.posed.vertices.detach().cpu()
    faces = frames.scene.body.faces.cpu()
    sd = picture_distances(signed_distance).cpu()
    fps = frames.scene.motion.fps
    written = [write_usd(os.path.join(out, f"{stem}.{usd_format}"), hair, body_v, faces, fps=fps, widths=width)]
    data_path = os.path.join(out, f"{stem}.data")
    write_hair_data(data_path, hair[-1])
    written.append(data_path)
    written.append(render_sequence(os.path.join(out, f"{stem}.png"), hair, body_v, faces, signed_distance=sd,
                                   frames=6, fps=fps, title=f"{label}: red = inside the body", guides=guides))
    stride = max(1, -(-hair.shape[0] // gif_frames))
    written.append(render_animation(os.path.join(out, f"{stem}.gif"), hair, body_v, faces, signed_distance=sd,
                                    fps=fps, stride=stride, title=label, guides=guides))
    return written
