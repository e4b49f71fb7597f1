"""`hairwarp drape`: drape one hairstyle on one body pose with a chosen method.

    hairwarp drape                                     # long straight hair, rest pose, method auto
    hairwarp drape --hairstyle bob --pose head_turn --time 0.5 --method lbfgs
    hairwarp drape --hairstyle long_straight --method static --against reference   # shape against the optimum
    hairwarp drape --hairstyle my_hair.data --data-units cm --body my_smpl.npz --pose walk.npz --frame 40
    hairwarp drape --hairstyle z.npy --method static --refine 20 --checkpoint run/checkpoint.pt

Hairstyle: a procedural preset, a USC-HairSalon `.data` file, or a hair latent `.npy` (512
numbers, decoded through the shipped basis). Body: the default body or an SMPL-format model
(`.npz` / `.pkl`). Pose: the rest pose, a frame of a procedural motion, or a frame of an AMASS
`.npz`. Method: auto (the shipped static network finished by a few L-BFGS iterations, never
more vertices inside the body than the rigid placement), a network, an optimizer, the
reference, the rigid placement, NAME+refine or NAME+settle (damped physics steps). Writes into
--out: drape.usda (hair + body),
drape.data (strands in metres), drape.png and drape_rigid.png (front and side; red = inside
the body), drape_metrics.json and drape_metrics.md (penetration, length change, energy, time,
against the rigid placement of Eq. 1); with --against physics (or reference) also the energy ratio
E / E*, the distance and tip height against that drape, and drape_side_by_side.png.
"""

from __future__ import annotations

import argparse
import os
import time

from hairwarp.commands.common import (
    add_against_argument,
    add_common_arguments,
    add_method_arguments,
    add_scene_arguments,
    add_threads_argument,
)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "drape", help="drape a hairstyle on a body pose; write USD, .data, pictures, metrics",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:3]),
    )
    add_scene_arguments(p, simulate=False)
    add_method_arguments(p, max_iterations=500)
    add_against_argument(p, "drape")
    add_threads_argument(p)
    add_common_arguments(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import torch

    from hairwarp.commands.common import (
        build_scene_from_args,
        describe,
        markdown_table,
        method_from_args,
        picture_distances,
        run_and_score,
        set_threads,
        static_beside,
        static_table,
        whole_groom,
        with_whole_groom,
        write_metrics,
    )
    from hairwarp.io.hair_data import write_hair_data
    from hairwarp.io.usd import write_usd
    from hairwarp.render.preview import render_drape
    from hairwarp.runtime import resolve_device

    device = resolve_device(args.device, argument="--device")
    set_threads(args)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    scene = build_scene_from_args(args, simulate=False)
    method, config = method_from_args(args)
    os.makedirs(args.out, exist_ok=True)
    frames = scene.frames(device=device)
    print(describe(scene, frames))
    result, metrics, sd, rigid_sd = run_and_score(method, frames, config, simulate=False)
    label = method.name
    ms_text = "-" if result.time_ms is None else f"{result.time_ms:.1f}"
    rows = [("rigid", "-", metrics["rigid"]), (label, ms_text, metrics["method"])]
    fidelity, compared = None, []
    if args.against is not None and args.against != label:
        from hairwarp.methods import make

        optimum, optimum_metrics, optimum_sd, _ = run_and_score(make(args.against, method.options), frames, config,
                                                                simulate=False)
        rows.append((args.against, f"{optimum.time_ms:.1f}", optimum_metrics["method"]))
        fidelity, side = static_beside(args.out, "drape", frames, {label: result.positions, args.against:
                                                                   optimum.positions},
                                       {label: sd, args.against: optimum_sd}, args.against, config)
        compared = [side]
    groom = whole_groom(frames, label, result.positions, sd, rigid_sd)
    record = {"command": "drape", "scene": scene.name, "method": label, "method_info": result.info,
              "ms_per_frame": result.time_ms, "device": str(device), "strands": scene.hairstyle.num_strands,
              "vertices": int(scene.hairstyle.strands.shape[1]), "rigid": metrics["rigid"], "result": metrics["method"],
              "against": args.against}
    if groom is not None:  # the rows above are the guides'; the whole groom's come first
        rows, fidelity = with_whole_groom(groom, scene, rows, fidelity, record, metrics)
    record["fidelity"] = fidelity
    table = static_table(rows, fidelity) if fidelity is not None else markdown_table(rows)
    print(table)

    hair = result.positions.detach().cpu() if groom is None else groom["positions"].cpu()
    picture_sd = sd if groom is None else groom["signed_distance"]
    picture_guides = None if groom is None else groom["guides"]
    body_v = frames.posed.vertices.detach().cpu()
    faces = scene.body.faces.cpu()
    written = [write_usd(os.path.join(args.out, "drape.usda"), hair[0], body_v[0], faces, fps=scene.motion.fps,
                         widths=1e-3 if groom is None else groom["width"])]
    data_path = os.path.join(args.out, "drape.data")
    write_hair_data(data_path, hair[0])
    written.append(data_path)
    written.append(render_drape(os.path.join(args.out, "drape.png"), hair[0], body_v[0], faces,
                                signed_distance=picture_distances(picture_sd[0]).cpu(),
                                title=f"{label}: red = inside the body", guides=picture_guides))
    written.append(render_drape(os.path.join(args.out, "drape_rigid.png"), frames.rigid.positions[0].cpu(),
                                body_v[0], faces, signed_distance=picture_distances(rigid_sd[0]).cpu(),
                                title="rigid placement (Eq. 1) of the guides: red = inside the body"
                                if groom is not None else "rigid placement (Eq. 1): red = inside the body"))
    written += compared + write_metrics(args.out, "drape", record, table)
    print(f"wrote {', '.join(os.path.basename(p) for p in written)} into {args.out} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0
