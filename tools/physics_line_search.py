"""How often the physics' line search rejects its trial step, by strand count.

Question it answers (docs/physics.md, twelfth session, "left to test"): a full-size step needs
more iterations than a reduced groom's, and neither contact, one shared memory nor the trial
cap explains it. Every strand takes the one step length the L-BFGS line search accepts; with
more strands, is a first trial (t = 1) rejected more often, each rejection an iteration spent
on an energy evaluation that moves nothing?

Counts, per implicit-Euler step of `simulate_physics` (the default `PhysicsConfig`, eager, so
each iteration's outcome is read at once): iterations, rejected trials (the loss unchanged by an
iteration: `DeviceLBFGS` keeps x on a rejection), and the runs of rejections in a row. The start
is a short static drape (no settling): the steps are a falling, moving groom, the same at every
strand count.

    python3 tools/physics_line_search.py --device cpu --strand-strides 8,4,2 --frames 6 --out OUT

Writes OUT/physics_line_search.json and prints one row per strand count.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace

import torch


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0, help="unused (the scenes are fixed); the command line's habit")
    parser.add_argument("--motion", default="whiplash", help="a comparison scene (hairwarp.evaluation.scenes)")
    parser.add_argument("--strand-strides", default="8,4,2", help="every k-th scalp root, one run each")
    parser.add_argument("--frames", type=int, default=6, help="frames simulated (the first is the drape)")
    parser.add_argument("--static-iterations", type=int, default=300, help="the first frame's static drape cap")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)

    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.runtime import machine_description
    from hairwarp.solvers import device_lbfgs
    from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

    device = torch.device(args.device)
    outcomes: list[bool] = []  # True: the iteration's trial was accepted
    original = device_lbfgs.DeviceLBFGS.iterate

    def counted(self):
        before = float(self.f)
        original(self)
        outcomes.append(float(self.f) != before)

    # Eager (no CUDA graph): each iteration's outcome is read as it happens.
    config = replace(PhysicsConfig(), settle_time=0.0, static_max_iterations=args.static_iterations,
                     cuda_graph=False)
    rows = []
    device_lbfgs.DeviceLBFGS.iterate = counted
    try:
        for stride in (int(s) for s in args.strand_strides.split(",")):
            scene = comparison_scene(args.motion, reduced=False, strand_stride=stride).scene
            frames = list(range(min(args.frames, scene.num_frames)))
            outcomes.clear()
            start = simulate_physics(scene, frames[:1], device=device, config=config)
            drape_iterations = len(outcomes)
            outcomes.clear()
            result = simulate_physics(scene, frames, device=device, config=config, initial=start.positions[0])
            steps = [r.iterations for r in result.reports[1:]]
            row = _row(outcomes, stride, scene.hairstyle.strands.shape[0], drape_iterations, steps)
            rows.append(row)
            print(f"{row['strands']} strands: {row['iterations']} iterations over {len(frames) - 1} steps, "
                  f"{row['rejected']} rejected ({100 * row['rejected_share']:.1f} %), longest run of "
                  f"rejections {row['longest_rejection_run']}", flush=True)
    finally:
        device_lbfgs.DeviceLBFGS.iterate = original
    os.makedirs(args.out, exist_ok=True)
    record = {"machine": machine_description(device), "motion": args.motion,
              "command": "python3 tools/physics_line_search.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "rows": rows}
    with open(os.path.join(args.out, "physics_line_search.json"), "w") as f:
        json.dump(record, f, indent=1)
    return 0


def _row(outcomes: list[bool], stride: int, strands: int, drape_iterations: int, steps) -> dict:
    runs, run = [], 0
    for accepted in outcomes:
        if accepted:
            if run:
                runs.append(run)
            run = 0
        else:
            run += 1
    if run:
        runs.append(run)
    rejected = sum(not a for a in outcomes)
    return {"strand_stride": stride, "strands": strands, "drape_iterations": drape_iterations,
            "iterations": len(outcomes), "rejected": rejected, "rejected_share": rejected / max(len(outcomes), 1),
            "rejection_runs": {str(k): runs.count(k) for k in sorted(set(runs))},
            "longest_rejection_run": max(runs, default=0), "iterations_per_step": steps}


if __name__ == "__main__":
    sys.exit(main())
