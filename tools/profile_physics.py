"""Where a physics step's time goes on a GPU: device time per kernel per iteration (torch.profiler,
CUDA graphs as the solver replays them, or eager), at full size on a comparison motion.

    python tools/profile_physics.py --device cuda --motions whiplash,torso_bend --out OUT

For each motion: the tight static drape of frame 0, `--warm` steps, then `--steps` steps under
the profiler. Writes OUT/profile_physics.json: per motion and mode, the wall time and iterations
of the profiled steps, and each kernel's device time per iteration [us], largest first.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def _profile_steps(solver, posed, first: int, steps: int, device) -> dict:
    from hairwarp.runtime import kernel_device_times, synchronize

    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    iterations = 0
    synchronize(device)
    t0 = time.perf_counter()
    with torch.profiler.profile(activities=activities) as prof:
        for t in range(first, first + steps):
            solver.set_frame(posed.rigid.positions[t:t + 1], posed.rigid.normals[t:t + 1],
                             posed.posed.vertices[t:t + 1])
            iterations += solver.step().iterations
        synchronize(device)
    wall = time.perf_counter() - t0
    kernels = kernel_device_times(prof, per=max(iterations, 1))
    busy = sum(kernels.values())
    return {"steps": steps, "iterations": iterations, "wall_ms_per_step": wall * 1e3 / steps,
            "wall_us_per_iteration_under_profiler": wall * 1e6 / max(iterations, 1),
            "device_busy_us_per_iteration": busy,
            "kernels_us_per_iteration": dict(list(kernels.items())[:40])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--motions", default="whiplash,torso_bend")
    p.add_argument("--strand-stride", type=int, default=1)
    p.add_argument("--warm", type=int, default=3, help="steps before the profiled ones")
    p.add_argument("--steps", type=int, default=4, help="profiled steps")
    p.add_argument("--modes", default="graph,eager", help="graph (the default solver) and/or eager")
    p.add_argument("--out", default="profile_physics_out")
    args = p.parse_args(argv)
    from diagnose_networks import write_json

    from hairwarp.config import EnergyConfig
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.ops import BodyMesh
    from hairwarp.runtime import machine_description
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver, simulate_physics

    device = torch.device(args.device)
    record = {"machine": machine_description(device), "command": "python tools/profile_physics.py "
              + " ".join(argv if argv is not None else sys.argv[1:]), "motions": {}}
    for name in args.motions.split(","):
        scene = comparison_scene(name, reduced=False, strand_stride=args.strand_stride).scene
        frames = list(range(1 + args.warm + args.steps))
        x0 = simulate_physics(scene, frames[:1], device=device, config=PhysicsConfig().tight()).positions[0]
        posed = scene.frames(frames, device=device, build_body=False)
        body = BodyMesh(posed.posed.vertices[:1], scene.body.faces.to(device=device, dtype=torch.int32), bvh="lbvh")
        energy_config = EnergyConfig().replace(time_step=1.0 / float(scene.motion.fps))
        entry = {"strands": int(scene.hairstyle.strands.shape[0]), "vertices": int(scene.hairstyle.strands.shape[1])}
        for mode in args.modes.split(","):
            config = replace(PhysicsConfig(), cuda_graph=(mode == "graph"))
            solver = PhysicsSolver(scene.rest_lengths.to(device), posed.rigid.positions[:1],
                                   posed.rigid.normals[:1], body, energy_config, config)
            solver.set_state(x0)
            for t in range(1, 1 + args.warm):
                solver.set_frame(posed.rigid.positions[t:t + 1], posed.rigid.normals[t:t + 1],
                                 posed.posed.vertices[t:t + 1])
                solver.step()
            entry[mode] = _profile_steps(solver, posed, 1 + args.warm, args.steps, device)
            e = entry[mode]
            print(f"{name} {mode}: {e['wall_ms_per_step']:.1f} ms a step under the profiler, "
                  f"{e['iterations'] / args.steps:.1f} iterations, device busy "
                  f"{e['device_busy_us_per_iteration']:.0f} us an iteration", flush=True)
            for k, us in list(e["kernels_us_per_iteration"].items())[:15]:
                print(f"    {us:8.1f} us  {k[:110]}")
            del solver
        record["motions"][name] = entry
    write_json(args.out, "profile_physics.json", record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
