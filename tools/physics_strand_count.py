"""Does a groom's physics depend on how many of its strands are simulated?

    python3 tools/physics_strand_count.py --device cpu --strides 16,4 --references 0,1024 --out OUT

For each comparison motion and strand stride (every k-th scalp root of the full groom), the
physics simulation with `EnergyConfig.reference_strand_count` R (0: the paper's means over the
M strands simulated; 1 024: every strand the energy it has in the full groom): the tip swing
(the tips' offset from the rigid placement minus its mean over the motion) and the tips of the
strands every stride shares (every `--common`-th root), so that runs at other sizes, machines
and sessions compare strand by strand (`--compare A.json,B.json`). Writes
OUT/physics_strand_count.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch


def _tip_distance_mm(a, b) -> list[float]:
    """Mean distance per frame [mm] between two runs' common tips, (T, K, 3) lists [m]."""
    ta, tb = torch.tensor(a), torch.tensor(b)
    frames = min(ta.shape[0], tb.shape[0])
    return [round(float(v), 2) for v in (ta[:frames] - tb[:frames]).norm(dim=-1).mean(dim=1) * 1000.0]


def compare(paths: list[str]) -> dict:
    """Every run of the files against every other run of the same motion: the common tips' mean
    distance [mm] over the frames (mean and max) and the swings side by side."""
    runs = []
    for path in paths:
        with open(path) as f:
            data = json.load(f)
        runs += [(f"{os.path.basename(path)}:{r['motion']}:stride{r['stride']}:R{r['reference_strand_count']}", r)
                 for r in data["runs"]]
    table = {}
    for i, (name_a, a) in enumerate(runs):
        for name_b, b in runs[i + 1:]:
            if a["motion"] != b["motion"] or a["common"] != b["common"]:
                continue
            d = _tip_distance_mm(a["common_tips"], b["common_tips"])
            table[f"{name_a} vs {name_b}"] = {"mean_mm": sum(d) / len(d), "max_mm": max(d),
                                              "swing_mm": [a["physics_swing_mm"], b["physics_swing_mm"]]}
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--motions", default="whiplash,torso_bend")
    parser.add_argument("--strides", default="16,4", help="strand strides (1: the full groom)")
    parser.add_argument("--references", default="0,1024", help="EnergyConfig.reference_strand_count values")
    parser.add_argument("--common", type=int, default=16, help="the common strands: every k-th root")
    parser.add_argument("--frames", type=int, default=0, help="frames per motion (0: all)")
    parser.add_argument("--settle-time", type=float, default=0.0, help="PhysicsConfig.settle_time [s]")
    parser.add_argument("--compare", default=None, help="comma-separated JSON files of this tool to compare")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    if args.compare:
        table = compare(args.compare.split(","))
        print(json.dumps(table, indent=1))
        with open(os.path.join(args.out, "physics_strand_count_compare.json"), "w") as f:
            json.dump(table, f, indent=1)
        return 0
    from hairwarp.config import EnergyConfig
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.metrics import motion_fidelity
    from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    runs = []
    for motion in args.motions.split(","):
        for stride in (int(s) for s in args.strides.split(",")):
            if args.common % stride:
                raise SystemExit(f"--common: {args.common} is not a multiple of the stride {stride}")
            scene = comparison_scene(motion, strand_stride=stride).scene
            frames = list(range(scene.num_frames if args.frames <= 0 else min(args.frames, scene.num_frames)))
            rigid = scene.frames(frames, device=device, build_body=False).rigid.positions
            for reference in (int(r) for r in args.references.split(",")):
                energy = EnergyConfig(reference_strand_count=reference,
                                      time_step=1.0 / float(scene.motion.fps))
                start = time.perf_counter()
                result = simulate_physics(scene, frames, device=device, energy_config=energy,
                                          config=PhysicsConfig(settle_time=args.settle_time))
                seconds = time.perf_counter() - start
                x = result.positions[:, 0]
                fidelity = motion_fidelity(rigid, x, rigid)
                common = x[:, :: args.common // stride, -1].cpu()
                run = {"motion": motion, "stride": stride, "strands": int(x.shape[1]), "frames": len(frames),
                       "reference_strand_count": reference, "seconds": seconds, "common": args.common,
                       "physics_swing_mm": fidelity["physics_swing_mm"],
                       "common_tips": [[[round(float(c), 5) for c in p] for p in f] for f in common]}
                runs.append(run)
                print(motion, stride, reference, f"{seconds:.0f} s", f"swing {fidelity['physics_swing_mm']:.1f} mm",
                      flush=True)
    machine = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    out = {"machine": machine, "command": "python3 tools/physics_strand_count.py " + " ".join(sys.argv[1:]), "runs": runs}
    with open(os.path.join(args.out, "physics_strand_count.json"), "w") as f:
        json.dump(out, f)
    for name, row in compare([os.path.join(args.out, "physics_strand_count.json")]).items():
        print(name, f"{row['mean_mm']:.1f} / {row['max_mm']:.1f} mm", row["swing_mm"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
