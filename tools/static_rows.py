"""Static drapes of scenes unlike the comparison scenes, every method against the converged optimum.

The rows of the physics issue's first table that the harness's scenes do not cover: long straight
hair grown on the body at rest (a clean placement: nothing inside), a bob at head_turn t = 0.5 s,
long curly hair grown on the head alone at nod t = 0.5 s; each at full size (1 024 strands x 100
vertices), each method through `hairwarp.drape`: penetration and length change, and against the
tight physics drape at rest (`reference`, solved once per scene) E / E*, the mean / p95 distance
to it and the tips' height against it (`hairwarp.metrics.drape_fidelity`).

    python tools/static_rows.py --device cuda --out OUT
    python tools/static_rows.py --device cuda --checkpoint static.pt --out OUT   # + that static network
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

import torch

# name -> build_scene arguments.
SCENES = {
    "long_straight_rest_grown_on_body": dict(hairstyle="long_straight", pose="rest", grow="body"),
    "bob_head_turn_0.5s": dict(hairstyle="bob", pose="head_turn", time=0.5),
    "long_curly_nod_0.5s_grown_on_head": dict(hairstyle="long_curly", pose="nod", time=0.5, grow="head"),
    # Limbs away from the rest pose (`--scenes`): both arms raised above the head, a walk's stride.
    "long_straight_arm_raise_1.6s_grown_on_body": dict(hairstyle="long_straight", pose="arm_raise", time=1.6,
                                                      grow="body"),
    "long_curly_sway_walk_1.0s": dict(hairstyle="long_curly", pose="sway_walk", time=1.0),
}
DEFAULT_SCENES = tuple(SCENES)[:3]
METHODS = ("rigid", "static", "dynamic", "lbfgs")


def main(argv=None) -> int:
    import hairwarp as hw

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--strand-stride", type=int, default=1)
    p.add_argument("--lbfgs-iterations", type=int, default=300)
    p.add_argument("--checkpoint", default=None, help="also run the static network of this checkpoint")
    p.add_argument("--scenes", default=",".join(DEFAULT_SCENES), help=f"comma-separated, of {', '.join(SCENES)}")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated method names (any of `hairwarp methods`, e.g. static+settle)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="static_rows_out")
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    torch.manual_seed(args.seed)
    names = [m for m in args.methods.split(",") if m]
    scenes = [s for s in args.scenes.split(",") if s]
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        p.error(f"--scenes: unknown {unknown}; expected of {list(SCENES)}")
    methods = [(m, {"max_iterations": args.lbfgs_iterations} if m == "lbfgs" else {}) for m in names]
    # The networks' rows as they run by default (through the body pass, `MethodOptions.keep_out`)
    # and as the network returns them.
    methods += [(m, {"keep_out": False}) for m in ("static", "dynamic") if m in names]
    if args.checkpoint:
        methods += [("static", {"checkpoint": args.checkpoint}),
                    ("static", {"checkpoint": args.checkpoint, "keep_out": False})]
    rows = []
    lines = ["| scene | method | ms | inside % | length change % | E / E* | distance mean / p95 [mm] | tips vs E* [mm] |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    from hairwarp import metrics as M
    from hairwarp.methods import MethodOptions

    energy = MethodOptions().config()
    for name in scenes:
        build = SCENES[name]
        scene = hw.build_scene(strand_stride=args.strand_stride, **build)
        # E* once per scene (the tight physics drape at rest), every method measured against it.
        optimum = hw.drape(scene, method="reference", device=args.device, progress=False)
        for method, options in methods + [("reference", {})]:
            r = optimum if method == "reference" else hw.drape(scene, method=method, device=args.device,
                                                               progress=False, **options)
            f = M.drape_fidelity(r.positions[None], optimum.positions[None], r.frames.inputs, energy)
            label = (method + (" (checkpoint)" if "checkpoint" in options else "")
                     + (" (raw)" if options.get("keep_out") is False else ""))
            row = {"scene": name, "method": label, "time_ms": r.time_ms, "strands": scene.hairstyle.num_strands,
                   "penetration_percent": r.metrics["penetration_percent"],
                   "length_change_percent": r.metrics["length_change_percent"], "fidelity": f,
                   "keep_out_ms": r.info.get("keep_out_ms")}
            rows.append(row)
            ratio = f.get("energy_ratio")
            lines.append(f"| {name} | {label} | {'-' if r.time_ms is None else f'{r.time_ms:.1f}'} | "
                         f"{row['penetration_percent']:.3f} | {row['length_change_percent']:.3f} | "
                         f"{'-' if ratio is None else f'{ratio:.3f}'} | {f['mean_distance_mm']:.1f} / "
                         f"{f['p95_distance_mm']:.1f} | {f['tip_height_difference_mm']:+.1f} |")
            print(lines[-1], flush=True)
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU ({os.cpu_count()} cores)"
    record = {"device": device, "machine": platform.node(),
              "command": "python tools/static_rows.py " + " ".join(sys.argv[1:] if argv is None else argv), "rows": rows}
    with open(os.path.join(args.out, "static_rows.json"), "w") as fh:
        json.dump(record, fh, indent=1, default=float)
    with open(os.path.join(args.out, "static_rows.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
