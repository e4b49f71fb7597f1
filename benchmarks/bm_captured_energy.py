"""Total energy forward+backward, eager vs replayed from a CUDA graph, and L-BFGS with each.

Sizes: the energy benchmark's scene (`hairwarp.bench.energy.build_energy_inputs`: 1024 x 100
hair on the default body cropped to the hair's reach, B frames of a head turn), every term of
Eq. 6 (inertia included). "eager" is `total_energy` + backward as a user calls it (one host read
of the hair-hair pair count); "graph" is `hairwarp.energy.CapturedEnergy` (the graph-safe energy
captured once, replayed). Then the L-BFGS baseline (`optimize_drape`) on the full-size table1
scene, with and without the graph. With `--profile`, a torch profile of one eager step per batch
(the ten costliest device kernels); with `--probe-kernels`, the contact kernels alone (hair-hair
with the boxes-in-cells broad phase at cell widths 1-1.5 x a typical box; hair-body one thread
per vertex in two passes vs one per strand). The midpoint grid these runs once compared is gone
(issue 30); its figures stay in docs/results/captured_energy_cells*_h100.json.

    python benchmarks/bm_captured_energy.py --device cuda --out OUT

Writes OUT/captured_energy.json and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

from hairwarp.runtime import machine_name, time_ms


def _energy_rows(device, batches, profile: bool, hairstyle: str = "long_straight",
                 mixed_lengths: float | None = None) -> tuple[list, dict]:
    from hairwarp import set_finite_checks
    from hairwarp.bench.energy import build_energy_inputs
    from hairwarp.energy import CapturedEnergy, total_energy

    rows, profiles = [], {}
    previous = set_finite_checks(False)
    try:
        for batch in batches:
            x, inputs, _, _ = build_energy_inputs(batch, device, hairstyle=hairstyle, mixed_lengths=mixed_lengths)
            x = x.detach()

            def eager():
                xe = x.requires_grad_(True)
                xe.grad = None
                total_energy(xe, inputs, dynamic=True).total.sum().backward()

            eager_ms = time_ms(eager, device, warmup=3, repeats=10, min_time_s=0.3)
            captured = CapturedEnergy(x.detach(), inputs, dynamic=True)
            graph_ms = time_ms(lambda: captured(x.detach()), device, warmup=3, repeats=20, min_time_s=0.3)
            e_graph, g_graph = captured(x.detach())
            xe = x.detach().requires_grad_(True)
            e_eager = total_energy(xe, inputs, dynamic=True).total
            e_eager.sum().backward()
            row = {"batch": batch, "eager_ms": eager_ms, "graph_ms": graph_ms, "captured": captured.captured,
                   "max_rel_energy_diff": float(((e_graph - e_eager.detach()).abs() / e_eager.detach().abs()).max()),
                   "max_abs_grad_diff": float((g_graph - xe.grad).abs().max()),
                   "hair_hair_pairs": int(captured._info.pair_count) if captured._info is not None else None}
            rows.append(row)
            print(f"B={batch:<3d} eager {eager_ms:8.3f} ms  graph {graph_ms:8.3f} ms  "
                  f"(rel. energy diff {row['max_rel_energy_diff']:.1e})", flush=True)
            if profile and device.type == "cuda":
                from torch.profiler import ProfilerActivity, profile as torch_profile

                with torch_profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                    eager()
                    torch.cuda.synchronize()
                events = sorted(prof.key_averages(), key=lambda e: -getattr(e, "device_time_total", 0.0))
                profiles[str(batch)] = [{"name": e.key[:90], "device_ms": getattr(e, "device_time_total", 0.0) / 1e3,
                                         "calls": e.count} for e in events[:10]]
                for p in profiles[str(batch)]:
                    print(f"    {p['device_ms']:8.3f} ms  x{p['calls']:<3d} {p['name']}")
    finally:
        set_finite_checks(previous)
    return rows, profiles


def _kernel_probe(device, batches) -> dict:
    """Hair-hair with the device broad phase (boxes in cells at several cell widths) and hair-body
    per vertex vs per strand, each term alone, forward+backward."""
    import importlib

    from hairwarp import set_finite_checks
    from hairwarp.bench.energy import build_energy_inputs
    from hairwarp.config import EnergyConfig
    from hairwarp.energy import CapturedEnergy
    from hairwarp.ops import hair_hair_contact_energy
    from hairwarp.ops.barrier import barrier_variant_id

    hh = importlib.import_module("hairwarp.ops.hair_hair_contact")
    hb = importlib.import_module("hairwarp.ops.hair_body_contact")
    c, out = EnergyConfig(), {}
    previous, chosen, kind_of = set_finite_checks(False), hh._CELL_FACTOR, hh._broad_phase_kind
    try:
        for batch in batches:
            x, inputs, _, _ = build_energy_inputs(batch, device)
            x = x.detach().requires_grad_(True)
            for kind, factor in (("cells", 1.0), ("cells", 1.25), ("cells", 1.5)):
                hh._CELL_FACTOR = factor
                hh._broad_phase_kind = lambda d, k=kind: k

                def hair_hair():
                    x.grad = None
                    hair_hair_contact_energy(x, c.hair_diameter, c.hair_hair_dhat, c.barrier_join_fraction,
                                             weight=c.hair_hair_weight)[0].sum().backward()

                out[f"hair_hair B={batch} {kind} cell={factor}"] = time_ms(hair_hair, device, warmup=2, repeats=10,
                                                                             min_time_s=0.2)
                if device.type == "cuda":
                    # The whole energy replayed from a CUDA graph: the figure the goals name.
                    captured = CapturedEnergy(x.detach(), inputs, dynamic=True)
                    out[f"total graph B={batch} {kind} cell={factor}"] = time_ms(
                        lambda: captured(x.detach()), device, warmup=3, repeats=20, min_time_s=0.3)
            for strategy in ("vertex", "strand"):
                def hair_body():
                    x.grad = None
                    hb._HairBodyContactEnergy.apply(x, inputs.body, c.hair_body_xi, c.hair_body_dhat,
                                                    c.barrier_join_fraction, c.hair_body_weight,
                                                    barrier_variant_id(c.barrier_variant), strategy).sum().backward()

                out[f"hair_body B={batch} {strategy}"] = time_ms(hair_body, device, warmup=2, repeats=10, min_time_s=0.2)
            for key in [k for k in out if f"B={batch} " in k]:
                print(f"  {key:<32s} {out[key]:8.3f} ms", flush=True)
    finally:
        hh._CELL_FACTOR = chosen
        hh._broad_phase_kind = kind_of
        set_finite_checks(previous)
    return out


def _lbfgs_rows(device, iterations: int, repeats: int = 3) -> list:
    """L-BFGS on the full-size Table 1 scene: torch's strong-Wolfe line search and the
    device-resident backtracking one (`hairwarp.solvers.device_lbfgs`), each run `repeats` times
    after one untimed warm-up. The backtracking rows record penetration every 10 iterations
    (recording time excluded) and give the time at which they first matched the strong-Wolfe
    run's final penetration and loss."""
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.metrics import length_change_percent, penetration_percent
    from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

    frames = comparison_scene("table1").frames(device=device)

    def penetration(x):
        return {"penetration": float(penetration_percent(x, frames.body_mesh).mean())}

    variants = [("strong_wolfe", False), ("strong_wolfe", True), ("backtracking", False), ("backtracking", True)]
    if device.type != "cuda":
        variants = [("strong_wolfe", False), ("backtracking", False)]
    rows, target = [], None
    for line_search, graph in variants:
        # The backtracking runs get half as many iterations more: the row says when they matched.
        cap = iterations if line_search == "strong_wolfe" else iterations * 3 // 2
        solver = DirectOptimizationConfig(method="lbfgs", max_iterations=cap, patience=50, cuda_graph=graph,
                                          lbfgs_line_search=line_search,
                                          record_every=10 if line_search == "backtracking" else 0)
        metrics = penetration if line_search == "backtracking" else None
        optimize_drape(frames.rigid.positions, frames.inputs, solver=DirectOptimizationConfig(
            **{**solver.__dict__, "max_iterations": 20, "record_every": 0}))
        for run in range(repeats if graph or device.type != "cuda" else 1):
            result = optimize_drape(frames.rigid.positions, frames.inputs, solver=solver, metrics=metrics)
            x = result.positions
            row = {"scene": "table1", "line_search": line_search, "cuda_graph": graph, "run": run,
                   "iterations": result.iterations, "evaluations": result.evaluations, "time_s": result.time_s,
                   "stop": result.stop_reason, "loss": result.loss,
                   "penetration_percent": float(penetration_percent(x, frames.body_mesh).mean()),
                   "length_change_percent": float(length_change_percent(x, frames.inputs.rest_lengths).mean())}
            if line_search == "strong_wolfe" and target is None:
                target = (row["penetration_percent"], row["loss"])
            if target is not None and result.history and "penetration" in result.history[-1]:
                reached = [h for h in result.history
                           if "penetration" in h and h["penetration"] <= target[0] and h["loss"] <= target[1]]
                row["time_to_strong_wolfe_accuracy_s"] = reached[0]["time_s"] if reached else None
                row["iterations_to_strong_wolfe_accuracy"] = reached[0]["iteration"] if reached else None
            rows.append(row)
            print(f"L-BFGS table1 {line_search} graph={graph}: {row['time_s']:.3f} s, {row['iterations']} it., "
                  f"{row['evaluations']} evaluations, loss {row['loss']:.4f}, {row['penetration_percent']:.2f} % inside, "
                  f"{row['length_change_percent']:.3f} % length; strong-Wolfe's accuracy at "
                  f"{row.get('time_to_strong_wolfe_accuracy_s')} s", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batch", default="1,32", help="comma-separated batch sizes")
    parser.add_argument("--lbfgs-iterations", type=int, default=300, help="0: skip the L-BFGS rows")
    parser.add_argument("--profile", action="store_true", help="torch profile of one eager step per batch")
    parser.add_argument("--probe-kernels", action="store_true",
                        help="also time the contact kernels alone: hair-hair broad phases and cell widths, "
                             "hair-body per vertex (two passes) / per strand")
    parser.add_argument("--hairstyle", default="long_straight", help="the energy rows' hairstyle preset")
    parser.add_argument("--mixed-lengths", type=float, default=None,
                        help="every other strand cut to this fraction of its length (0.1: half the segments "
                             "1.8x the mean; docs/contact.md 11)")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    os.makedirs(args.out, exist_ok=True)
    rows, profiles = _energy_rows(device, [int(b) for b in args.batch.split(",")], args.profile, args.hairstyle,
                                  args.mixed_lengths)
    batches = [int(b) for b in args.batch.split(",")]
    probe = _kernel_probe(device, batches) if args.probe_kernels else {}
    lbfgs = _lbfgs_rows(device, args.lbfgs_iterations) if args.lbfgs_iterations else []
    record = {"machine": machine_name(device), "device": str(device), "hairstyle": args.hairstyle,
              "mixed_lengths": args.mixed_lengths, "energy": rows, "profiles": profiles,
              "kernel_probe": probe, "lbfgs": lbfgs,
              "command": "python benchmarks/bm_captured_energy.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    with open(os.path.join(args.out, "captured_energy.json"), "w") as f:
        json.dump(record, f, indent=1)
    print(f"\n{record['machine']}\n\n| batch | eager fwd+bwd (ms) | graph replay (ms) |\n|---:|---:|---:|")
    for r in rows:
        print(f"| {r['batch']} | {r['eager_ms']:.3f} | {r['graph_ms']:.3f} |")


if __name__ == "__main__":
    main()
