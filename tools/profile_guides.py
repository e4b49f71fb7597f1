"""Where the time of `Scene.full_groom` goes on a GPU: device kernels (torch.profiler) and the
host, for each body-pass schedule, on the foreign groom of `benchmarks/bm_guides.py`.

    python tools/profile_guides.py --device cuda --strands 10000,100000 --out OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--strands", default="10000,100000")
    p.add_argument("--schedules", default="walk,rounds")
    p.add_argument("--lbfgs-iterations", type=int, default=100)
    p.add_argument("--calls", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="profile_guides_out")
    args = p.parse_args(argv)
    import hairwarp as hw
    from foreign_grooms import write_data_groom
    from hairwarp.methods import MethodOptions, make
    from hairwarp.ops import hair_body_signed_distance

    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    record = {}
    for n in [int(s) for s in args.strands.split(",")]:
        scene = hw.build_scene(write_data_groom(os.path.join(args.out, f"groom_{n}.data"), n, args.seed),
                               pose="head_turn", time=0.5)
        frames = scene.frames([0], device=device)
        draped = make("lbfgs", MethodOptions(max_iterations=args.lbfgs_iterations, progress=False)).drape(frames).positions
        sd = hair_body_signed_distance(draped, frames.body_mesh)
        config = scene.guides.config
        for name in args.schedules.split(","):
            scene.guides.config = dataclasses.replace(config, body_schedule=name)
            for _ in range(3):
                scene.full_groom(draped, frames, guide_signed_distance=sd)
            if device.type == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            for _ in range(args.calls):
                scene.full_groom(draped, frames, guide_signed_distance=sd)
            host = (time.perf_counter() - t0) / args.calls * 1e3  # launch-side time, no sync
            if device.type == "cuda":
                torch.cuda.synchronize()
            wall = (time.perf_counter() - t0) / args.calls * 1e3
            activities = [torch.profiler.ProfilerActivity.CPU]
            if device.type == "cuda":
                activities.append(torch.profiler.ProfilerActivity.CUDA)
            with torch.profiler.profile(activities=activities) as prof:
                for _ in range(args.calls):
                    scene.full_groom(draped, frames, guide_signed_distance=sd)
                if device.type == "cuda":
                    torch.cuda.synchronize()
            table = prof.key_averages().table(sort_by="cuda_time_total" if device.type == "cuda" else "cpu_time_total",
                                              row_limit=14)
            events = [(e.key, e.count / args.calls, getattr(e, "device_time_total", 0.0) / args.calls)
                      for e in prof.key_averages()]
            kernels = sorted([e for e in events if e[2] > 0], key=lambda e: -e[2])[:14]
            # The Warp kernels of the last call, in launch order, each with its own device time.
            sequence = [(e.name.split("_cuda_kernel")[0], round(e.device_time_total, 1)) for e in prof.events()
                        if e.device_type == torch.autograd.DeviceType.CUDA and "_kernel" in e.name
                        and "at::" not in e.name]
            per_call = len(sequence) // args.calls
            row = {"host_ms_per_call": host, "wall_ms_per_call": wall,
                   "device_us_per_call": {k: round(t, 1) for k, _, t in kernels},
                   "last_call_kernels_us": sequence[-per_call:] if per_call else []}
            print("last call:", row["last_call_kernels_us"])
            record[f"{n}_{name}"] = row
            print(f"{n} strands, {name}: wall {wall:.2f} ms a call, host (launch side) {host:.2f} ms")
            print(table)
    scene.guides.config = config
    with open(os.path.join(args.out, "profile_guides.json"), "w") as f:
        json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
