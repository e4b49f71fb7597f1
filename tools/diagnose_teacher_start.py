"""Where the distillation teacher of a static network rests, by where its solve starts.

The physics-pool teacher (`StaticTrainingConfig.teacher_pool`) is the physics' static drape
solved from the network's own drape, up to `teacher_iterations` (800). A static drape stops in
the resting state nearest its start, so a teacher started from a lifted drape may keep part of
the lift. Per scene, against the converged optimum E* (`reference`, from the rigid placement):
the network's drape, the teacher from it, and the same solve from the rigid placement. For each:
E / E*, the tips' height above E*'s [mm], the mean distance to E*'s drape [mm], the share of
vertices inside [%].

    OMP_NUM_THREADS=2 python3 tools/diagnose_teacher_start.py --out OUT   (256 strands, 2-core CPU)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    from diagnose_networks import load_scene, machine, write_json
    from static_rows import SCENES as STATIC_ROWS

    from hairwarp.energy import total_energy
    from hairwarp.methods import MethodOptions, make
    from hairwarp.methods.optimizers import PhysicsMethod, scene_energy_config
    from hairwarp.metrics import frame_metrics, static_fidelity
    from hairwarp.solvers.physics import PhysicsConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scenes", default="long_rest,bob_rest,medium_poses,table1",
                   help="comparison scenes, grown rest scenes, or tools/static_rows.py rows, comma-separated")
    p.add_argument("--strand-stride", type=int, default=4)
    p.add_argument("--teacher-iterations", type=int, default=800)
    p.add_argument("--checkpoint", default=None, help="the static network (default: the shipped one)")
    p.add_argument("--out", default="diagnose_teacher_start_out")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    record = {"machine": machine(args.device), "command": "python tools/diagnose_teacher_start.py "
              + " ".join(argv if argv is not None else sys.argv[1:]), "scenes": {}}
    options = MethodOptions(checkpoint=args.checkpoint, progress=False)
    teacher = PhysicsMethod(options, PhysicsConfig(static_max_iterations=args.teacher_iterations))
    for name in args.scenes.split(","):
        if name in STATIC_ROWS:  # the held-out rows of tools/static_rows.py (e.g. the curly nod)
            import hairwarp as hw

            scene = hw.build_scene(strand_stride=args.strand_stride, **STATIC_ROWS[name])
            size = {"strands": scene.hairstyle.num_strands, "strand_stride": args.strand_stride,
                    "made_by": f"hw.build_scene(strand_stride={args.strand_stride}, **{STATIC_ROWS[name]!r})"}
        else:
            scene, size = load_scene(name, args.strand_stride)
        frames = scene.frames([0], device=device)
        config = scene_energy_config(options, frames)

        def summary(x, optimum, e_star, seconds):
            with torch.no_grad():
                e = float(total_energy(x, frames.inputs, config).total.sum())
            fid = static_fidelity(x, optimum, e, e_star)
            inside = float(frame_metrics(x, frames)[0]["penetration_percent"][0])
            tips = float((x[..., -1, 1] - optimum[..., -1, 1]).mean()) * 1e3
            return {"energy": e, "energy_ratio": e / e_star, "tip_height_vs_optimum_mm": tips,
                    "mean_distance_mm": fid["mean_distance_mm"], "inside_percent": inside, "seconds": seconds}

        t0 = time.perf_counter()
        optimum = make("reference", options).drape(frames).positions.detach()
        t_ref = time.perf_counter() - t0
        with torch.no_grad():
            e_star = float(total_energy(optimum, frames.inputs, config).total.sum())
        rows = {"optimum (reference, from the rigid placement)": summary(optimum, optimum, e_star, t_ref)}
        t0 = time.perf_counter()
        network = make("static", options).drape(frames).positions.detach()
        rows["static network"] = summary(network, optimum, e_star, time.perf_counter() - t0)
        starts = {"teacher from the network's drape": network, "the same solve from the rigid placement": None}
        for label, start in starts.items():
            t0 = time.perf_counter()
            x = teacher.drape(frames, start=start).positions.detach()
            rows[label] = summary(x, optimum, e_star, time.perf_counter() - t0)
        rows["rigid placement"] = summary(frames.rigid.positions, optimum, e_star, 0.0)
        record["scenes"][name] = {"size": size, "rows": rows}
        print(f"{name} ({size['strands']} strands), E* {e_star:.4f} J")
        for label, r in rows.items():
            print(f"  {label:48s} E/E* {r['energy_ratio']:.4f}  tips {r['tip_height_vs_optimum_mm']:+7.1f} mm  "
                  f"mean {r['mean_distance_mm']:6.1f} mm  inside {r['inside_percent']:.3f} %  {r['seconds']:.1f} s",
                  flush=True)
    write_json(args.out, "teacher_start.json", record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
