"""How fast each variant of the physics solver converges within one implicit-Euler step.

    python3 tools/diagnose_physics.py --device cuda --motion whiplash --steps 6,12,18 --out OUT

From the tight trajectory's states (the `reference` setting) at the chosen frames, one step of
each variant (L-BFGS unscaled or on variables scaled by the diagonal stiffness per vertex; history sizes) for
several iteration caps, against the tight step: mean vertex distance [mm] and wall time per step.
Writes OUT/physics_diagnosis.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

import torch


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--motion", default="whiplash")
    parser.add_argument("--strand-stride", type=int, default=1)
    parser.add_argument("--steps", default="6,12,18", help="frames whose step is checked")
    parser.add_argument("--iterations", default="8,16,32,64,128")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)
    from hairwarp.config import EnergyConfig
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.ops import BodyMesh
    from hairwarp.runtime import synchronize
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver, simulate_physics

    device = torch.device(args.device)
    scene = comparison_scene(args.motion, reduced=False, strand_stride=args.strand_stride).scene
    steps = [int(s) for s in args.steps.split(",")]
    frames = list(range(max(steps) + 1))
    tight_config = PhysicsConfig().tight()
    tight = simulate_physics(scene, frames, device=device, config=tight_config)
    posed = scene.frames(frames, device=device, build_body=False)
    body = BodyMesh(posed.posed.vertices[:1], scene.body.faces.to(device=device, dtype=torch.int32), bvh="lbvh")
    energy_config = EnergyConfig().replace(time_step=1.0 / float(scene.motion.fps))
    rest = scene.rest_lengths.to(device)
    variants = {"unscaled": PhysicsConfig(stiffness_scaling=0.0), "scaled 1/16": PhysicsConfig(stiffness_scaling=0.0625),
                "scaled 1/8": PhysicsConfig(stiffness_scaling=0.125), "scaled 1/4": PhysicsConfig(stiffness_scaling=0.25),
                "scaled 1/8 h16": PhysicsConfig(stiffness_scaling=0.125, history=16)}
    rows = []
    for name, base in variants.items():
        for its in [int(i) for i in args.iterations.split(",")]:
            config = replace(base, max_iterations=its, tolerance=1e-12)
            solver = PhysicsSolver(rest, posed.rigid.positions[:1], posed.rigid.normals[:1], body, energy_config, config)
            distances, times = [], []
            for t in steps:
                for k in (t - 2, t - 1, t):  # the rigid placements' history too (the warm start reads it)
                    solver.set_frame(posed.rigid.positions[k:k + 1], posed.rigid.normals[k:k + 1],
                                     posed.posed.vertices[k:k + 1])
                solver.set_state(tight.positions[t - 1], tight.positions[t - 2])
                synchronize(device)
                t0 = time.perf_counter()
                solver.step()
                synchronize(device)
                times.append((time.perf_counter() - t0) * 1e3)
                distances.append(float((solver.prev - tight.positions[t]).norm(dim=-1)[..., 2:].mean()) * 1e3)
            row = {"variant": name, "iterations": its, "distance_mm": distances, "ms": times}
            rows.append(row)
            print(f"{name:10s} {its:4d} it.: distance {' '.join(f'{d:.3f}' for d in distances)} mm, "
                  f"{' '.join(f'{m:.1f}' for m in times)} ms", flush=True)
    moved = [float((tight.positions[t] - tight.positions[t - 1]).norm(dim=-1)[..., 2:].mean()) * 1e3 for t in steps]
    print(f"tight step moves {' '.join(f'{d:.2f}' for d in moved)} mm; tight iterations {tight.iterations}")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "physics_diagnosis.json"), "w") as f:
        json.dump({"motion": args.motion, "steps": steps, "rows": rows, "tight_step_moves_mm": moved,
                   "tight_iterations": tight.iterations}, f, indent=1)


if __name__ == "__main__":
    main()
