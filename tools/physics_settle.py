"""What settling the first pose (`PhysicsConfig.settle_time`) costs and changes, scene by scene.

    python3 tools/physics_settle.py --device cuda --frames 30 --settle-times 0,1 --out OUT

For each held-out scene of `tools/train_inertial.py evaluate` (and the comparison scenes), the
physics simulation of its first frames with the first pose held for up to each settle time:
the settling steps taken, the wall time, the mean tip offset from the rigid placement per frame
(its vertical part: a groom still falling when the motion starts sinks here), the static energy
(Eq. 5) of the state the motion starts from, how far the tips
drift over the frames, and the mean vertex distance of each setting to the unsettled one.
Writes OUT/physics_settle.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--strand-stride", type=int, default=1)
    parser.add_argument("--frames", type=int, default=30, help="frames simulated from each scene's start")
    parser.add_argument("--settle-times", default="0,1", help="comma-separated settle times [s]")
    parser.add_argument("--scenes", default=None, help="labels of tools/train_inertial.py's EVALUATION (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    from train_inertial import EVALUATION, _evaluation_scene

    from hairwarp.config import EnergyConfig
    from hairwarp.energy import total_energy
    from hairwarp.metrics import mean_tip_offset
    from hairwarp.runtime import synchronize
    from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    times = [float(s) for s in args.settle_times.split(",")]
    labels = args.scenes.split(",") if args.scenes else [e[0] for e in EVALUATION]
    records = []
    for label, style, pose, start, duration in EVALUATION:
        if label not in labels:
            continue
        scene = _evaluation_scene(label, style, pose, start, duration, args.strand_stride, args.out)
        indices = list(range(min(args.frames, scene.num_frames)))
        rigid = scene.frames(indices, device=device, build_body=False).rigid.positions
        first = scene.frames([0], device=device)
        energy_config = EnergyConfig(time_step=1.0 / float(scene.motion.fps))
        runs, unsettled = {}, None
        for settle in times:
            synchronize(device)
            t0 = time.perf_counter()
            result = simulate_physics(scene, indices, device=device, config=PhysicsConfig(settle_time=settle))
            synchronize(device)
            seconds = time.perf_counter() - t0
            x = result.positions[:, 0]
            tips = mean_tip_offset(x, rigid) * 1000.0
            row = {"settle_steps": result.settle_steps, "seconds": seconds,
                   "tip_offset_y_mm": [round(float(v), 1) for v in tips[:, 1]],
                   "tip_drift_mm": float((tips - tips[0]).norm(dim=-1).max())}
            with torch.no_grad():  # the static energy (Eq. 5) of the state the motion starts from
                row["start_energy"] = float(total_energy(x[:1], first.inputs, energy_config).total.sum())
            if unsettled is None:
                unsettled = x
            else:
                apart = (x - unsettled).norm(dim=-1).mean(dim=(1, 2)) * 1000.0
                row["to_unsettled_mean_mm"] = [round(float(v), 2) for v in apart]
            runs[str(settle)] = row
            print(label, settle, json.dumps({k: v for k, v in row.items() if k != "tip_offset_y_mm"}), flush=True)
        size = {"strands": int(rigid.shape[1]), "vertices": int(rigid.shape[2]), "frames": len(indices)}
        records.append({"scene": label, "hairstyle": style, "size": size, "runs": runs})
    machine = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    with open(os.path.join(args.out, "physics_settle.json"), "w") as f:
        json.dump({"machine": machine, "command": "python3 tools/physics_settle.py " + " ".join(sys.argv[1:]),
                   "records": records}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
