"""The body pass's settings side by side on one motion: the inertial step's rollout through each.

Question it answers: how many vertices does each setting of `hairwarp.methods.keep_out` leave
inside the body, and how much does it stretch the strands? Settings: A, eight rounds pushing
vertices nearer than the margin, the rest left; B, four rounds pushing those nearer than half of
it, every vertex still inside pushed out without the projection; C (the default), eight rounds
at half the margin, only vertices less than a margin deep pushed out at the end.

    python3 tools/keep_out_settings.py --scene whiplash --strand-stride 4      # ~2 min on 2 cores
    python3 tools/keep_out_settings.py --scene demo --strand-stride 4          # the demo's scene
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

SETTINGS = {"A": dict(passes=8, trigger=1.0, turns=0, final_depth=0.0),
            "B": dict(passes=4, trigger=0.5, turns=0, final_depth=float("inf")),
            "C": dict(passes=8, trigger=0.5, turns=0, final_depth=1.0),
            "C + turns (the default)": dict(passes=8, trigger=0.5, turns=12, final_depth=1.0)}


def main(argv=None) -> int:
    import hairwarp as hw
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.keep_out import keep_out_of_body_in_frames
    from hairwarp.methods.inertial import load_inertial_step
    from hairwarp.methods.networks import NetworkMethod
    from hairwarp.metrics import frame_metrics_of

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="whiplash",
                   help="a comparison motion, or demo: the demo's (long straight hair grown around the body, a "
                        "one-second head turn) (default: whiplash)")
    p.add_argument("--strand-stride", type=int, default=4)
    p.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated names of SETTINGS (default: all)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="keep_out_settings_out")
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    if args.scene == "demo":
        scene = hw.default_scene("long_straight", "head_turn", duration=1.0, strand_stride=args.strand_stride,
                                 grow_around_body=True)
    else:
        scene = comparison_scene(args.scene, strand_stride=args.strand_stride).scene
    frames = scene.frames(device=device)
    rigid = frames.rigid.positions
    equilibrium = NetworkMethod("static", MethodOptions(keep_out=False)).simulate(frames)
    with torch.no_grad():
        rollout = load_inertial_step(None, device).rollout(equilibrium.positions.to(rigid.dtype), rigid)
    rows = {}
    chosen = args.settings.split(",")
    for name, settings in SETTINGS.items():
        if name not in chosen:
            continue
        t0 = time.perf_counter()
        x = keep_out_of_body_in_frames(rollout.clone(), frames, **settings)
        seconds = time.perf_counter() - t0
        metrics = frame_metrics_of({"x": x}, frames)["x"][0]
        inside, length = metrics["penetration_percent"], metrics["length_change_percent"]
        rows[name] = r = {**settings, "inside_percent_mean": sum(inside) / len(inside), "inside_percent_max": max(inside),
                          "length_change_percent_max": max(length), "ms_per_frame": seconds * 1e3 / x.shape[0]}
        print(f"{name}: inside {r['inside_percent_mean']:.3f} / {r['inside_percent_max']:.3f} %, length change "
              f"{r['length_change_percent_max']:.3f} %, {r['ms_per_frame']:.0f} ms/frame", flush=True)
    size = {"strands": int(rigid.shape[1]), "vertices": int(rigid.shape[2]), "frames": int(rigid.shape[0])}
    with open(os.path.join(args.out, "keep_out_settings.json"), "w") as f:
        json.dump({"scene": args.scene, "size": size, "device": str(device), "rows": rows}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
