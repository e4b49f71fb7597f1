"""`hairwarp demo`: the embedded default, end to end, offline.

Default body, a procedural hairstyle grown around the rest body (it falls over the shoulders
and back), a one-second head turn, simulated by one method of the registry; writes the
animation as USD (binary .usdc; --usda for text), preview pictures, a GIF, and prints the
metrics table. The default, auto, runs the physics simulation where it meets its speed goal (on
a CPU up to 256 x 100 hair: the demo's default size), else the shipped inertial step, never
leaving more vertices inside the body than the rigid placement. The method is shown beside the
physics simulation of the same frames (side-by-side pictures and GIF, the tips' swing plotted
over time) with the distance to it and the swing's amplitude ratio and correlation in the table;
when auto ran the physics itself, the inertial step is run and shown beside it instead. The
demo's energy leaves hair-hair contact out unless --hair-hair is given.
"""

from __future__ import annotations

import os
import time

from hairwarp.commands.common import add_common_arguments, add_threads_argument, method_name

# L-BFGS iterations after the network over the whole motion (each costs about 3 s for 61 frames
# of 512 x 100 hair on the 2-core CPU without hair-hair).
DEMO_REFINE = 5


def add_parser(subparsers) -> None:
    from hairwarp.methods import AUTO_REFINE
    from hairwarp.solvers.physics import PhysicsConfig

    p = subparsers.add_parser("demo", help="simulate the embedded default scene with one method; write USD, "
                                           "pictures, a GIF, metrics",
                              description=__doc__.split("\n\n")[1])
    add_common_arguments(p)
    p.add_argument("--hairstyle", default="long_straight", help="procedural hairstyle preset (default: long_straight)")
    p.add_argument("--motion", default="head_turn", help="procedural motion (default: head_turn)")
    p.add_argument("--duration", type=float, default=1.0, help="motion length [s] (default: 1.0)")
    p.add_argument("--method", default="auto", type=method_name,
                   help="a method of `hairwarp.methods.available()` or NAME+refine (default: auto)")
    p.add_argument("--refine", type=int, default=DEMO_REFINE, metavar="K",
                   help=f"L-BFGS iterations after a network (default: {DEMO_REFINE}; the API's auto: {AUTO_REFINE})")
    p.add_argument("--hair-hair", action="store_true", help="keep hair-hair contact in the energy (slow on a CPU)")
    p.add_argument("--physics-iterations", type=int, default=None, metavar="K",
                   help="L-BFGS iterations a frame at most of the physics beside the method (default: the physics "
                        f"method's own, {PhysicsConfig().max_iterations} at its tolerance; 0: no physics)")
    p.add_argument("--usda", action="store_true", help="write text USD (demo.usda) instead of binary demo.usdc")
    p.add_argument("--max-iterations", type=int, default=40, help="adam/lbfgs iteration cap (default: 40)")
    p.add_argument("--strand-stride", type=int, default=4,
                   help="grow on one root in K of the 32 x 32 scalp, spread over it (default: 4, 256 strands; 1: all 1024)")
    p.add_argument("--num-vertices", type=int, default=100, help="vertices per strand (default: 100)")
    add_threads_argument(p)
    p.set_defaults(run=run)


def run(args) -> int:
    import torch

    from hairwarp.builder import positive_int
    from hairwarp.commands.common import (beside_the_physics, markdown_table, picture_distances, run_and_score,
                                          set_threads, write_metrics)
    from hairwarp.methods.optimizers import PhysicsMethod
    from hairwarp.solvers.physics import PhysicsConfig
    from hairwarp.config import EnergyConfig
    from hairwarp.io.usd import write_usd
    from hairwarp.methods import MethodOptions, make
    from hairwarp.render.preview import render_animation, render_drape
    from hairwarp.runtime import resolve_device
    from hairwarp.scene.hairstyles import list_hairstyle_presets
    from hairwarp.scene.motion import list_motions
    from hairwarp.scene.scene import default_scene

    device = resolve_device(args.device, argument="--device")
    set_threads(args)
    torch.manual_seed(args.seed)
    if args.hairstyle not in list_hairstyle_presets():
        raise ValueError(f"--hairstyle: expected one of {list_hairstyle_presets()}, got {args.hairstyle!r}")
    if args.motion not in list_motions():
        raise ValueError(f"--motion: expected one of {list_motions()}, got {args.motion!r}")
    if not args.duration > 0:
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration}")
    config = EnergyConfig() if args.hair_hair else EnergyConfig(hair_hair_weight=0.0)
    options = MethodOptions(energy_config=config,
                            max_iterations=positive_int("--max-iterations", args.max_iterations, minimum=0),
                            patience=20, refine=positive_int("--refine", args.refine, minimum=0), progress=True)
    method = make(args.method, options)
    stride = positive_int("--strand-stride", args.strand_stride)
    num_vertices = positive_int("--num-vertices", args.num_vertices, minimum=3)
    os.makedirs(args.out, exist_ok=True)

    t0 = time.perf_counter()
    clock = {"start": t0}

    def phase(name, next_step: str | None = None):
        now = time.perf_counter()
        clock[name] = now - clock["start"]
        clock["start"] = now
        if next_step:
            print(f"[{now - t0:5.1f} s] {next_step}", flush=True)

    print(f"[  0.0 s] building the scene: {args.hairstyle} grown around the default body, {args.motion} "
          f"{args.duration:g} s", flush=True)
    # Grown around the rest body, so the rest drape starts nearly free of penetration (grown
    # around the head alone, long hair hangs straight through the torso: ~37 % inside).
    scene = default_scene(args.hairstyle, args.motion, seed=args.seed, duration=args.duration,
                          grow_around_body=True, strand_stride=stride, num_vertices=num_vertices)
    frames = scene.frames(device=device)
    phase("scene", f"simulating {scene.hairstyle.num_strands} strands x {num_vertices} vertices over "
                   f"{scene.num_frames} frames with {method.name}")
    result, metrics, sd, sd_rigid = run_and_score(method, frames, options.config(), simulate=True)
    chose_physics = str(result.info.get("chosen", "")).startswith("physics")
    physics_iterations = positive_int("--physics-iterations", PhysicsConfig().max_iterations
                                      if args.physics_iterations is None else args.physics_iterations, minimum=0)
    physics = physics_metrics = physics_sd = None
    beside = None  # (label, result, metrics, signed distances) of the other method when auto ran the physics
    if chose_physics:
        # Auto ran the physics itself: it is the yardstick; the motion's network (the inertial step,
        # as auto runs it elsewhere) goes beside it.
        physics, physics_metrics, physics_sd = result, metrics, sd
        phase("method", "the inertial step beside it")
        network = make("inertial", options)
        net_result, net_metrics, net_sd, _ = run_and_score(network, frames, options.config(), simulate=True)
        beside = ("inertial", net_result, net_metrics, net_sd)
    elif physics_iterations:
        phase("method", f"the physics beside it: {physics_iterations} iterations a frame at most")
        physics_method = PhysicsMethod(options, PhysicsConfig(max_iterations=physics_iterations))
        physics, physics_metrics, physics_sd, _ = run_and_score(physics_method, frames, options.config(),
                                                               simulate=True)
    phase("network beside" if beside is not None else "physics" if physics is not None else "method",
          "writing USD and drawing the pictures")

    def ms(r):
        return "-" if r.time_ms is None else f"{r.time_ms:.1f}"

    rows = [("rigid", "-", metrics["rigid"]), (method.name, ms(result), metrics["method"])]
    fidelity, compared = None, []
    if beside is not None:
        label, other, other_metrics, other_sd = beside
        rows.append((label, ms(other), other_metrics["method"]))
        fidelity, compared = beside_the_physics(args.out, "demo", frames, {label: other.positions,
                                                                           "physics": physics.positions},
                                                {label: other_sd, "physics": physics_sd}, "physics")
        fidelity[method.name] = fidelity["physics"]  # auto's row: the physics itself
    elif physics is not None:
        rows.append(("physics", ms(physics), physics_metrics["method"]))
        fidelity, compared = beside_the_physics(args.out, "demo", frames, {method.name: result.positions,
                                                                           "physics": physics.positions},
                                                {method.name: sd, "physics": physics_sd}, "physics")
    table = markdown_table(rows, fidelity)
    body_v = frames.posed.vertices.detach().cpu()
    faces = scene.body.faces.cpu()
    hair = result.positions.detach().cpu()
    usd_path = write_usd(os.path.join(args.out, "demo.usda" if args.usda else "demo.usdc"), hair, body_v, faces,
                         fps=scene.motion.fps)
    render_drape(os.path.join(args.out, "demo_rigid.png"), frames.rigid.positions[0].cpu(), body_v[0], faces,
                 signed_distance=picture_distances(sd_rigid[0]).cpu(),
                 title="rigid placement (Eq. 1), frame 0: red = inside the body")
    render_drape(os.path.join(args.out, "demo_drape.png"), hair[0], body_v[0], faces,
                 signed_distance=picture_distances(sd[0]).cpu(), title=f"{method.name}, frame 0: red = inside the body")
    stride_gif = max(1, -(-scene.num_frames // 20))
    render_animation(os.path.join(args.out, "demo.gif"), hair, body_v, faces, signed_distance=picture_distances(sd).cpu(),
                     fps=scene.motion.fps, stride=stride_gif, title=method.name)
    phase("outputs")
    record = {"scene": scene.name, "method": method.name, "method_info": result.info, "ms_per_frame": result.time_ms,
              "strands": scene.hairstyle.num_strands, "vertices": num_vertices, "frames": scene.num_frames,
              "fps": scene.motion.fps, "device": str(device), "rigid": metrics["rigid"], "result": metrics["method"],
              "beside": None if beside is None else {"method": beside[0], "ms_per_frame": beside[1].time_ms,
                                                     "info": beside[1].info, "metrics": beside[2]["method"]},
              "physics": None if physics is None else {"iterations_cap": physics_iterations,
                                                       "ms_per_frame": physics.time_ms, "info": physics.info,
                                                       "metrics": physics_metrics["method"]},
              "against_physics": fidelity,
              "wall_s": {k: round(v, 2) for k, v in clock.items() if k != "start"}}
    write_metrics(args.out, "demo", record, table)
    print(table)
    phases = ", ".join(f"{k} {v:.0f} s" for k, v in clock.items() if k != "start")
    extra = "".join(f", {os.path.basename(p)}" for p in compared)
    print(f"wrote {os.path.basename(usd_path)}, demo_rigid.png, demo_drape.png, demo.gif{extra}, demo_metrics.json/.md "
          f"into {args.out} ({time.perf_counter() - t0:.0f} s: {phases})")
    return 0
