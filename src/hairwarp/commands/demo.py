"""`hairwarp demo`: the embedded default, end to end, offline.

Default body, a procedural hairstyle grown around the rest body (it falls over the shoulders and
back), a short head-turn motion: drape and simulate with the best available method (the shipped
HairFormer checkpoint when the package has one, else direct L-BFGS optimization of the first
frame, carried rigidly with the head through the motion), then write the animation as USD,
preview pictures, a GIF, and print the metrics table. About a minute on a 2-core CPU.
"""

from __future__ import annotations

import json
import os
import time


def add_parser(subparsers) -> None:
    from hairwarp.cli import add_common_arguments
    from hairwarp.commands.drape import add_threads_argument

    p = subparsers.add_parser("demo", help="drape and simulate the embedded default scene; write USD, pictures, metrics",
                              description=__doc__.split("\n\n")[1])
    add_common_arguments(p)
    p.add_argument("--hairstyle", default="long_straight", help="procedural hairstyle preset (default: long_straight)")
    p.add_argument("--motion", default="head_turn", help="procedural motion (default: head_turn)")
    p.add_argument("--duration", type=float, default=1.0, help="motion length [s] (default: 1.0)")
    p.add_argument("--method", default="auto", choices=["auto", "network", "lbfgs"],
                   help="auto: the shipped network if present, else L-BFGS (default: auto)")
    p.add_argument("--max-iterations", type=int, default=40, help="L-BFGS iteration cap (default: 40)")
    p.add_argument("--strand-stride", type=int, default=2,
                   help="grow on every K-th root of the 32 x 32 scalp only (default: 2, 512 strands; 1: all 1024)")
    p.add_argument("--num-vertices", type=int, default=100, help="vertices per strand (default: 100)")
    add_threads_argument(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import torch

    from hairwarp.cli import resolve_device
    from hairwarp.commands.drape import picture_distances, set_threads
    from hairwarp.evaluation.metrics import length_change_percent
    from hairwarp.io.usd import write_usd
    from hairwarp.ops import hair_body_signed_distance
    from hairwarp.render.preview import render_animation, render_drape
    from hairwarp.scene.hairstyles import list_hairstyle_presets
    from hairwarp.scene.motion import list_motions
    from hairwarp.scene.scene import default_scene

    device = resolve_device(args.device)
    set_threads(args)
    torch.manual_seed(args.seed)
    if args.hairstyle not in list_hairstyle_presets():
        raise ValueError(f"--hairstyle: expected one of {list_hairstyle_presets()}, got {args.hairstyle!r}")
    if args.motion not in list_motions():
        raise ValueError(f"--motion: expected one of {list_motions()}, got {args.motion!r}")
    if not args.duration > 0:
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if args.max_iterations < 0:
        raise ValueError(f"--max-iterations: expected an integer >= 0, got {args.max_iterations}")
    if args.strand_stride < 1:
        raise ValueError(f"--strand-stride: expected an integer >= 1, got {args.strand_stride}")
    if args.num_vertices < 3:
        raise ValueError(f"--num-vertices: expected an integer >= 3, got {args.num_vertices}")
    os.makedirs(args.out, exist_ok=True)

    t0 = time.perf_counter()
    clock = {"start": t0}

    def lap(name):
        now = time.perf_counter()
        clock[name] = now - clock["start"]
        clock["start"] = now

    # Grown around the rest body, so the rest drape starts nearly free of penetration (grown
    # around the head alone, long hair hangs straight through the torso: ~37 % inside).
    scene = default_scene(args.hairstyle, args.motion, seed=args.seed, duration=args.duration,
                          grow_around_body=True, strand_stride=args.strand_stride, num_vertices=args.num_vertices)
    frames = scene.frames(device=device)
    print(f"scene {scene.name}: {scene.hairstyle.num_strands} strands x {scene.hairstyle.strands.shape[1]} "
          f"vertices, {scene.num_frames} frames at {scene.motion.fps:g} fps, body {scene.body.num_vertices} vertices "
          f"({frames.body_mesh.num_faces} of {scene.body.num_faces} triangles within the hair's reach)")
    lap("scene")

    positions, method, timing_ms = _simulate(scene, frames, args)
    lap("method")
    rigid = frames.rigid.positions
    rest = frames.inputs.rest_lengths
    # Signed distances of every frame, once: the metrics and the red in the pictures.
    sd_rigid = hair_body_signed_distance(rigid, frames.body_mesh)
    sd = hair_body_signed_distance(positions, frames.body_mesh)
    pen_rigid = (sd_rigid[:, :, 2:] < 0).float().mean(dim=(1, 2)) * 100.0  # moving vertices, as Table 1
    pen = (sd[:, :, 2:] < 0).float().mean(dim=(1, 2)) * 100.0
    lengths = length_change_percent(positions, rest)
    table = [
        "| method | ms/frame | penetration % (mean over frames) | length change % (mean) |",
        "|---|---:|---:|---:|",
        f"| rigid placement (Eq. 1) | - | {float(pen_rigid.mean()):.3f} | "
        f"{float(length_change_percent(rigid, rest).mean()):.3f} |",
        f"| {method} | {timing_ms:.1f} | {float(pen.mean()):.3f} | {float(lengths.mean()):.3f} |",
    ]
    print("\n".join(table))
    lap("metrics")

    body_v = frames.posed.vertices.detach().cpu()
    faces = scene.body.faces.cpu()
    hair = positions.detach().cpu()
    usd_path = write_usd(os.path.join(args.out, "demo.usda"), hair, body_v, faces, fps=scene.motion.fps)
    render_drape(os.path.join(args.out, "demo_rigid.png"), rigid[0].cpu(), body_v[0], faces,
                 signed_distance=picture_distances(sd_rigid[0]).cpu(), title="rigid placement (Eq. 1), frame 0: red = inside the body")
    render_drape(os.path.join(args.out, "demo_drape.png"), hair[0], body_v[0], faces,
                 signed_distance=picture_distances(sd[0]).cpu(), title=f"{_short(method)}, frame 0: red = inside the body")
    stride = max(1, -(-scene.num_frames // 20))
    render_animation(os.path.join(args.out, "demo.gif"), hair, body_v, faces, signed_distance=picture_distances(sd).cpu(),
                     fps=scene.motion.fps, stride=stride, title=_short(method))
    lap("outputs")
    with open(os.path.join(args.out, "demo_metrics.json"), "w") as f:
        json.dump({"scene": scene.name, "method": method, "ms_per_frame": timing_ms,
                   "strands": scene.hairstyle.num_strands, "vertices": int(scene.hairstyle.strands.shape[1]),
                   "frames": scene.num_frames, "fps": scene.motion.fps,
                   "penetration_percent": pen.tolist(), "length_change_percent": lengths.tolist(),
                   "rigid_penetration_percent": pen_rigid.tolist(), "device": str(device),
                   "wall_s": {k: round(v, 2) for k, v in clock.items() if k != "start"}}, f, indent=1)
    with open(os.path.join(args.out, "demo_metrics.md"), "w") as f:
        f.write("\n".join(table) + "\n")
    phases = ", ".join(f"{k} {v:.0f} s" for k, v in clock.items() if k != "start")
    print(f"wrote {usd_path}, demo_rigid.png, demo_drape.png, demo.gif, demo_metrics.json/.md into {args.out} "
          f"({time.perf_counter() - t0:.0f} s: {phases})")
    return 0


def _short(label: str) -> str:
    """A method label cut before its parenthesis, for picture titles."""
    return label.split(" (")[0] + (" carried with the head" if "carried" in label else "")


def _simulate(scene, frames, args):
    """(positions (T, M, N, 3), method label, ms per frame)."""
    import torch

    from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

    if args.method in ("auto", "network"):
        try:
            from hairwarp.inference import load_default_simulator
        except ImportError:
            load_default_simulator = None
        simulator = load_default_simulator(frames.rigid.positions.device) if load_default_simulator else None
        if simulator is not None:
            return simulator.simulate_scene(scene, frames)
        if args.method == "network":
            raise ValueError("--method network: no shipped network checkpoint in this installation; use --method lbfgs")

    # Fallback: L-BFGS drape of frame 0, carried rigidly with the head (M_head) through the motion.
    # Hair-hair contact is left out here: its broad phase costs ~0.5 s per evaluation on a 2-core
    # CPU at 1024 x 100, which would take the demo past its two minutes (the benchmarks and the
    # harness keep it).
    from hairwarp.config import EnergyConfig

    config = EnergyConfig(hair_hair_weight=0.0)
    first = frames.inputs
    one = type(first)(rest_lengths=first.rest_lengths, rigid=first.rigid[:1], scalp_normals=first.scalp_normals[:1],
                      body=scene.frames([0], device=frames.rigid.positions.device).body_mesh)
    result = optimize_drape(frames.rigid.positions[:1], one, config,
                            solver=DirectOptimizationConfig(method="lbfgs", max_iterations=args.max_iterations,
                                                            patience=20), progress=True)
    offset = result.positions[0] - frames.rigid.positions[0]  # (M, N, 3) drape offset at frame 0
    rot = frames.posed.head_transform[:, :3, :3] @ frames.posed.head_transform[0, :3, :3].T
    positions = frames.rigid.positions + torch.einsum("tij,mnj->tmni", rot, offset)
    label = (f"L-BFGS drape of frame 0 ({result.iterations} it., {result.stop_reason}, no hair-hair), "
             "carried with the head")
    return positions, label, result.time_s * 1e3
