"""`hairwarp simulate`: simulate a hairstyle over a body motion with a chosen method.

    hairwarp simulate                                  # long straight hair, 1 s head turn, method auto
    hairwarp simulate --pose whiplash --duration 2 --method dynamic
    hairwarp simulate --pose walk.npz --start 1.5 --frames 120 --body my_smpl.npz --method reference
    hairwarp simulate --hairstyle bob --method rigid --strand-stride 4

Methods: auto (the physics where it meets its speed goal, a CPU up to 256 x 100 hair; else the
inertial step, its motion's start settled by `--settle` physics steps; never more vertices
inside than the rigid placement), inertial, the networks (dynamic: frame by frame
with its recurrent state; static: every frame on its own; quaffure), NAME+refine, NAME+settle, adam/lbfgs
(every frame draped on its own: static baselines, no dynamics), physics (implicit-Euler steps on
the device L-BFGS, the time step the motion's frame spacing), reference (the physics at a
tolerance 100x tighter), rigid (Eq. 1). --against physics runs the physics beside the method. Writes into --out:
simulate.usdc (binary USD, hair + body, one time sample a frame, at the motion's fps; --usda
for text), simulate.data (the
last frame's strands, metres), simulate.png (a strip of 6 frames, front and side; red = inside
the body), simulate.gif, simulate_metrics.json and simulate_metrics.md (per-frame penetration
and length change, against the rigid placement).
"""

from __future__ import annotations

import argparse
import os
import time

from hairwarp.commands.common import (
    DEFAULT_GIF_FRAMES,
    add_against_argument,
    add_common_arguments,
    add_method_arguments,
    add_scene_arguments,
    add_threads_argument,
)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate a hairstyle over a motion; write USD, .data, pictures, GIF, metrics",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:3]),
    )
    add_scene_arguments(p, simulate=True)
    add_method_arguments(p, max_iterations=100)
    p.add_argument("--gif-frames", type=int, default=DEFAULT_GIF_FRAMES,
                   help="frames shown in the GIF, evenly spaced (rendering costs ~0.5 s each) "
                        f"(default: {DEFAULT_GIF_FRAMES})")
    p.add_argument("--usda", action="store_true",
                   help="write the animation as text USD (.usda, about 6x larger) instead of binary .usdc")
    add_against_argument(p, "simulate")
    add_threads_argument(p)
    add_common_arguments(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import torch

    from hairwarp.builder import positive_int
    from hairwarp.commands.common import (
        beside_the_physics,
        build_scene_from_args,
        describe,
        markdown_table,
        method_from_args,
        run_and_score,
        set_threads,
        whole_groom,
        with_whole_groom,
        write_animation,
        write_metrics,
    )
    from hairwarp.methods import make
    from hairwarp.runtime import resolve_device

    device = resolve_device(args.device, argument="--device")
    set_threads(args)
    torch.manual_seed(args.seed)
    gif_frames = positive_int("--gif-frames", args.gif_frames)
    t0 = time.perf_counter()
    scene = build_scene_from_args(args, simulate=True)
    if not scene.body.has_smpl_pose and scene.num_frames < 2:
        raise ValueError(f"--body: {args.body} has one frame (no time samples); simulate needs an animated body "
                         "(or an SMPL-format body with --pose)")
    method, config = method_from_args(args)
    os.makedirs(args.out, exist_ok=True)
    frames = scene.frames(device=device)
    print(describe(scene, frames))
    result, metrics, sd, rigid_sd = run_and_score(method, frames, config, simulate=True)
    label = method.name
    rows = [("rigid", "-", metrics["rigid"]), (label, "-" if result.time_ms is None else f"{result.time_ms:.1f}",
                                               metrics["method"])]
    fidelity, compared = None, []
    if args.against is not None and args.against != label:
        truth_method = make(args.against, method.options)
        truth, truth_metrics, truth_sd, _ = run_and_score(truth_method, frames, config, simulate=True)
        rows.append((args.against, f"{truth.time_ms:.1f}", truth_metrics["method"]))
        fidelity, compared = beside_the_physics(args.out, "simulate", frames,
                                                {label: result.positions, args.against: truth.positions},
                                                {label: sd, args.against: truth_sd}, args.against, gif_frames)
    groom = whole_groom(frames, label, result.positions, sd, rigid_sd)
    record = {"command": "simulate", "scene": scene.name, "method": label, "method_info": result.info,
              "ms_per_frame": result.time_ms, "device": str(device), "fps": scene.motion.fps,
              "frames": scene.num_frames, "strands": scene.hairstyle.num_strands,
              "vertices": int(scene.hairstyle.strands.shape[1]), "rigid": metrics["rigid"], "result": metrics["method"],
              "against": args.against}
    if groom is not None:  # the rows above are the guides'; the whole groom's come first
        rows, fidelity = with_whole_groom(groom, scene, rows, fidelity, record, metrics)
    record["fidelity"] = fidelity
    table = markdown_table(rows, fidelity)
    print(table)
    hair, hair_sd, drawn = (result.positions, sd, {}) if groom is None else \
        (groom["positions"], groom["signed_distance"], {"guides": groom["guides"], "width": groom["width"]})
    written = write_animation(args.out, "simulate", frames, hair, hair_sd, label, gif_frames,
                              usd_format="usda" if args.usda else "usdc", **drawn) + compared
    usd = written[0]
    print(f"{os.path.basename(usd)}: {os.path.getsize(usd) / 2**20:.1f} MiB "
          f"({scene.num_frames} frames x {scene.num_strands} strands x {scene.hairstyle.strands.shape[1]} vertices)")
    written += write_metrics(args.out, "simulate", record, table)
    print(f"wrote {', '.join(os.path.basename(p) for p in written)} into {args.out} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0
