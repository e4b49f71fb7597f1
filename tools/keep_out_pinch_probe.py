"""The body pass with and without turning strands out of pinches, on the demo's scene.

The body pass (`hairwarp.methods.keep_out`) pushes along the signed distance's gradient; where
the arm meets the torso that push takes a vertex out of one part into the other, and a few stay
inside. Since the eighteenth session the pass then turns each strand's first such vertex about
its predecessor to the outside direction nearest its own (`_turn_out_of_pinches`, `turns`
rounds). Measured on the demo's scene (long straight hair grown around the body, a one-second
head turn), the inertial step's rollout, with `turns=0` and with `--rounds` (docs/network_diagnosis.md,
"Eighteenth session").

    python3 tools/keep_out_pinch_probe.py --strand-stride 4 --rounds 12     # ~1 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch


def main(argv=None) -> int:
    import hairwarp as hw
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import load_inertial_step
    from hairwarp.methods.keep_out import keep_out_of_body
    from hairwarp.methods.networks import NetworkMethod
    from hairwarp.metrics import frame_metrics_of

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--strand-stride", type=int, default=4)
    p.add_argument("--rounds", type=int, default=12)
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="keep_out_pinch_out")
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    scene = hw.default_scene("long_straight", "head_turn", duration=1.0, strand_stride=args.strand_stride,
                             grow_around_body=True)
    frames = scene.frames(device=device)
    rigid = frames.rigid.positions
    equilibrium = NetworkMethod("static", MethodOptions(keep_out=False)).simulate(frames)
    with torch.no_grad():
        rollout = load_inertial_step(None, device).rollout(equilibrium.positions.to(rigid.dtype), rigid)
    passed, probed = rollout.clone(), rollout.clone()
    seconds = {"pass without turns": 0.0, "pass": 0.0}
    start = 0
    for chunk in frames.chunks():
        rows = slice(start, start + chunk.num_frames)
        start = rows.stop
        t0 = time.perf_counter()
        passed[rows] = keep_out_of_body(rollout[rows].clone(), rigid[rows], chunk.body_mesh, turns=0)
        t1 = time.perf_counter()
        probed[rows] = keep_out_of_body(rollout[rows].clone(), rigid[rows], chunk.body_mesh, turns=args.rounds)
        seconds["pass without turns"] += t1 - t0
        seconds["pass"] += time.perf_counter() - t1
    record = {"size": list(rigid.shape), "rounds": args.rounds, "seconds": seconds, "rows": {}}
    for name, x in (("pass without turns", passed), ("pass", probed)):
        metrics = frame_metrics_of({"x": x}, frames)["x"][0]
        inside, length = metrics["penetration_percent"], metrics["length_change_percent"]
        record["rows"][name] = row = {"inside_percent_mean": sum(inside) / len(inside), "inside_percent_max": max(inside),
                                      "length_change_percent_max": max(length)}
        print(f"{name}: inside {row['inside_percent_mean']:.4f} / {row['inside_percent_max']:.4f} %, length change "
              f"{row['length_change_percent_max']:.4f} %", flush=True)
    print(f"without turns {seconds['pass without turns']:.1f} s, with {seconds['pass']:.1f} s for {rigid.shape[0]} frames")
    with open(os.path.join(args.out, "keep_out_pinch_probe.json"), "w") as f:
        json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
