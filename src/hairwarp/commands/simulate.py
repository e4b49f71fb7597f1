"""`hairwarp simulate`: simulate a hairstyle over a body motion with a chosen method.

    hairwarp simulate                                  # long straight hair, 1 s head turn
    hairwarp simulate --pose whiplash --duration 2 --method dynamic
    hairwarp simulate --pose walk.npz --start 1.5 --frames 120 --body my_smpl.npz --method reference
    hairwarp simulate --hairstyle bob --method rigid --strand-stride 4

Methods: the networks (dynamic: frame by frame with its recurrent state; static: every frame
on its own; quaffure), adam/lbfgs (every frame draped on its own: static baselines, no
dynamics), reference (implicit-Euler physics, the time step the motion's frame spacing), rigid
(Eq. 1). Writes into --out: simulate.usda (hair + body, one time sample a frame, at the
motion's fps), simulate.data (the last frame's strands, metres), simulate.png (a strip of 6
frames, front and side; red = inside the body), simulate.gif, simulate_metrics.json and
simulate_metrics.md (per-frame penetration and length change, against the rigid placement).
"""

from __future__ import annotations

import argparse
import os
import time


def add_parser(subparsers) -> None:
    from hairwarp.cli import add_common_arguments
    from hairwarp.commands.drape import add_method_arguments, add_scene_arguments, add_threads_argument

    p = subparsers.add_parser(
        "simulate", help="simulate a hairstyle over a motion; write USD, .data, pictures, GIF, metrics",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:3]),
    )
    add_scene_arguments(p, simulate=True)
    add_method_arguments(p, max_iterations=100)
    p.add_argument("--gif-frames", type=int, default=20,
                   help="frames shown in the GIF, evenly spaced (rendering costs ~0.5 s each) (default: 20)")
    add_threads_argument(p)
    add_common_arguments(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import torch

    from hairwarp.cli import resolve_device
    from hairwarp.commands.drape import (
        build_scene,
        describe,
        make_runner,
        markdown_table,
        metrics_rows,
        positive_int,
        set_threads,
        write_metrics,
        _jsonable,
    )

    device = resolve_device(args.device)
    set_threads(args)
    torch.manual_seed(args.seed)
    gif_frames = positive_int("--gif-frames", args.gif_frames)
    t0 = time.perf_counter()
    scene = build_scene(args, simulate=True)
    runner = make_runner(args, device, fps=scene.motion.fps, simulate=True)
    os.makedirs(args.out, exist_ok=True)
    frames = scene.frames(device=device)
    print(describe(scene, frames))
    positions, ms, label, info = runner.simulate(scene, frames)
    sd, metrics = metrics_rows(frames, positions)
    metrics["rigid"].pop("signed_distance")
    table = markdown_table([("rigid placement (Eq. 1)", "-", metrics["rigid"]),
                            (label, "-" if ms is None else f"{ms:.1f}", metrics["method"])])
    print(table)
    written = write_animation(args.out, "simulate", scene, frames, positions, sd, label, gif_frames)
    record = {"command": "simulate", "scene": scene.name, "method": label, "method_info": _jsonable(info),
              "ms_per_frame": ms, "device": str(device), "fps": scene.motion.fps, "frames": scene.num_frames,
              "strands": scene.hairstyle.num_strands, "vertices": int(scene.hairstyle.strands.shape[1]),
              "rigid": metrics["rigid"], "result": metrics["method"]}
    written += write_metrics(args.out, "simulate", record, table)
    print(f"wrote {', '.join(os.path.basename(p) for p in written)} into {args.out} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


def write_animation(out: str, stem: str, scene, frames, positions, signed_distance, label: str,
                    gif_frames: int) -> list[str]:
    """USD animation, last frame as `.data`, a 6-frame strip PNG and a GIF; returns the paths.

    Args:
        out: output folder.
        stem: file-name stem.
        scene, frames: the scene and its `SceneFrames` (all frames, in order).
        positions: (T, M, N, 3) hair positions [m].
        signed_distance: (T, M, N) signed distances of `positions` to the body [m].
        label: the method's name, for the titles.
        gif_frames: most frames the GIF shows.
    """
    from hairwarp.commands.drape import picture_distances
    from hairwarp.io.hair_data import write_hair_data
    from hairwarp.io.usd import write_usd
    from hairwarp.render.preview import render_animation, render_sequence

    hair = positions.detach().cpu()
    body_v = frames.posed.vertices.detach().cpu()
    faces = scene.body.faces.cpu()
    sd = picture_distances(signed_distance).cpu()
    fps = scene.motion.fps
    written = [write_usd(os.path.join(out, f"{stem}.usda"), hair, body_v, faces, fps=fps)]
    data_path = os.path.join(out, f"{stem}.data")
    write_hair_data(data_path, hair[-1])
    written.append(data_path)
    written.append(render_sequence(os.path.join(out, f"{stem}.png"), hair, body_v, faces, signed_distance=sd,
                                   frames=6, fps=fps, title=f"{label}: red = inside the body"))
    stride = max(1, -(-hair.shape[0] // gif_frames))
    written.append(render_animation(os.path.join(out, f"{stem}.gif"), hair, body_v, faces, signed_distance=sd,
                                    fps=fps, stride=stride, title=label))
    return written
