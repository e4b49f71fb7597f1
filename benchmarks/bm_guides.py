"""Guides and followers at production sizes (issue 32): speed of the followers, and what the whole
groom looks like after the guides are draped.

For each groom size it writes a groom "made outside the project" (`tools/foreign_grooms.py`:
another head, centimetres, 40-80 vertices a strand, a third wavy or curly), builds the scene
through `hairwarp.build_scene(..., guides=K)` (the loader's ICP fit onto the default body), drapes
the K guides with L-BFGS at one frame of a motion, then measures, side by side in one run:

- the interpolation alone and the interpolation + body pass (`Scene.full_groom`) [ms], the
  median of `--repeats` timed runs after a warm-up (device synchronised);
- the share of vertices inside the body and the length change of the guides, of the followers
  and of all strands, after the drape and for the rigid placement;
- with `--schedules walk,rounds`, the same two timings, the share inside and the deepest follower
  vertex for each body-pass schedule (`GuideConfig.body_schedule`), and with `--settles 0,0.0005`
  for the walk with each `GuideConfig.body_settle`, and `--face-hints 0,1` crossed with those
  (alternated in three rounds);
- on CUDA the interpolation + body pass also without its CUDA graph (`GuideConfig.cuda_graph`:
  the timed calls reuse one body, so from the second call on they replay a graph);
- with `--rounds-hints 0,1 --rounds-skips 0,1`, the rounds with their face hint
  (`ROUNDS_FACE_HINT`) and their skip of settled strands (`ROUNDS_SKIP_SETTLED`) off and on
  (crossed), and
  with `--rounds-passes 2` with that many rounds (`GuideConfig.body_passes`);
- with `--walk-block-dims 32,64,128,256`, the interpolation + body pass with the walk's CUDA
  threads per block (`WALK_THREADS_PER_BLOCK`), without the graph, alternated in three rounds;
- the followers' curl: per wavy or curly follower, the mean |turning angle - rest turning angle|
  over the mean rest turning angle (the curvature profile's relative change), median and p90,
  beside the same figure of the guide it follows most and the follower's excess over it (the
  physics uncurls the guides themselves; the excess is what the interpolation adds).

With `--commands` (CPU) it also runs the two commands of the issue and reads their wall time,
peak memory and output sizes: `hairwarp drape` of the largest groom, and `hairwarp simulate` of
`--simulate-seconds` of motion at the smallest.

    python benchmarks/bm_guides.py --device cuda --strands 10000,100000 --out docs/results
    python benchmarks/bm_guides.py --device cpu --strands 10000,100000 --lbfgs-iterations 100 --commands --out /tmp/g
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tools"))

# A follower is "wavy or curly" when its mean rest turning angle exceeds this [rad] (the straight
# ones of the generator turn by ~0.01 rad a segment; their relative change would be noise).
CURLY_TURNING = 0.05


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device, repeats: int) -> float:
    """Median wall time [ms] of `repeats` calls after two warm-ups."""
    for _ in range(2):
        fn()
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def turning_angles(x: torch.Tensor) -> torch.Tensor:
    """(..., N, 3) polylines -> (..., N-2) turning angles [rad]."""
    d = x[..., 1:, :] - x[..., :-1, :]
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.arccos(((d[..., 1:, :] * d[..., :-1, :]).sum(-1)).clamp(-1.0, 1.0))


def _inside(sd: torch.Tensor, strands: torch.Tensor) -> float:
    """Share [%] of the moving vertices (2 .. N-1) of `strands` with a negative signed distance."""
    from hairwarp.config import NUM_FIXED_VERTICES

    if strands.numel() == 0:
        return 0.0
    return float((sd[:, strands, NUM_FIXED_VERTICES:] < 0).double().mean() * 100.0)


def _length_change(x: torch.Tensor, rest: torch.Tensor, strands: torch.Tensor) -> float:
    from hairwarp.metrics import length_change_percent

    r = rest[strands]
    return float(length_change_percent(x[:, strands], (r[:, 1:] - r[:, :-1]).norm(dim=-1))[0])


def measure_groom(num_strands: int, args, device: torch.device) -> dict:
    import hairwarp as hw
    from foreign_grooms import write_data_groom
    from hairwarp.methods import MethodOptions, make
    from hairwarp.ops import hair_body_signed_distance

    path = write_data_groom(os.path.join(args.out, f"groom_{num_strands}.data"), num_strands, args.seed)
    t0 = time.perf_counter()
    scene = hw.build_scene(path, pose=args.pose, time=args.time, guides=args.guides)
    build_s = time.perf_counter() - t0
    guides = scene.guides
    frames = scene.frames([0], device=device)
    lbfgs = make("lbfgs", MethodOptions(max_iterations=args.lbfgs_iterations, progress=False))
    draped = lbfgs.drape(frames).positions
    row = {"strands": guides.num_strands, "guides": guides.num_guides, "file": os.path.basename(path),
           "file_mib": os.path.getsize(path) / 2**20, "build_s": build_s, "bundles": guides.describe(),
           "lbfgs_iterations": args.lbfgs_iterations}
    rest = guides.groom.strands.to(device)
    followers = torch.ones(guides.num_strands, dtype=torch.bool)
    followers[guides.guide_indices] = False
    follower_index = followers.nonzero().squeeze(1).to(device)
    guide_index = guides.guide_indices.to(device)
    everyone = torch.arange(guides.num_strands, device=device)
    for name, positions, body_pass in (("rigid", frames.rigid.positions, False), ("lbfgs", draped, True)):
        sd_guides = hair_body_signed_distance(positions, frames.body_mesh)
        x, facts = scene.full_groom(positions, frames, body_pass=body_pass, guide_signed_distance=sd_guides)
        sd = guides.signed_distance(x, positions, sd_guides, frames.body_mesh)
        row[name] = {
            "inside_percent": {"guides": _inside(sd, guide_index), "followers": _inside(sd, follower_index),
                               "all": _inside(sd, everyone)},
            "length_change_percent": {"guides": _length_change(x, rest, guide_index),
                                      "followers": _length_change(x, rest, follower_index),
                                      "all": _length_change(x, rest, everyone)},
            "body_pass": {"pushed_vertices": int(facts["pushed"].sum()), "pushed_strands": int((facts["pushed"] > 0).sum())}
            if "pushed" in facts else {},
        }
        if name == "lbfgs":
            # The curl: each wavy or curly follower's turning-angle profile against its rest one,
            # beside the same change of the guide it follows most (the physics itself uncurls
            # hair under gravity; what the interpolation adds is the difference).
            def profile_change(rest_strands, now_strands):
                k0, k1 = turning_angles(rest_strands.double()), turning_angles(now_strands.double())
                return (k1 - k0).abs().mean(1) / k0.mean(1).clamp_min(1e-12), k0.mean(1)

            change, k0_mean = profile_change(rest[follower_index], x[0, follower_index])
            own_guide = guides.follower_guides[follower_index.cpu(), 0].to(device)
            guide_change, _ = profile_change(rest[guide_index], positions[0])
            curly = k0_mean > CURLY_TURNING
            follower_change, excess = change[curly], (change - guide_change[own_guide])[curly]

            def q(t, level):
                return float(torch.quantile(t, level)) if t.numel() else None

            row["curl"] = {"followers": int(curly.sum()), "median_change": q(follower_change, 0.5),
                           "p90_change": q(follower_change, 0.9),
                           "their_guides_median_change": q(guide_change[own_guide][curly], 0.5),
                           "their_guides_p90_change": q(guide_change[own_guide][curly], 0.9),
                           "median_excess_over_guide": q(excess, 0.5), "p90_excess_over_guide": q(excess, 0.9),
                           "share_excess_within_10_percent": float((excess <= 0.10).double().mean())
                           if excess.numel() else None}
            sd_draped = sd_guides
    row["interpolation_ms"] = _timed(lambda: scene.full_groom(draped, frames, body_pass=False), device, args.repeats)
    row["interpolation_and_body_pass_ms"] = _timed(
        lambda: scene.full_groom(draped, frames, guide_signed_distance=sd_draped), device, args.repeats)
    row["schedule"] = guides.body_schedule(device)
    if device.type == "cuda":
        # The same call with every launch made from Python (no CUDA graph), beside the replay.
        config = guides.config
        guides.config = dataclasses.replace(config, cuda_graph=False)
        row["interpolation_and_body_pass_eager_ms"] = _timed(
            lambda: scene.full_groom(draped, frames, guide_signed_distance=sd_draped), device, args.repeats)
        guides.config = config
    variants = [(name, {"body_schedule": name}) for name in filter(None, args.schedules.split(","))]
    variants += [(f"walk, settle {float(v) * 1e3:g} mm", {"body_schedule": "walk", "body_settle": float(v)})
                 for v in filter(None, args.settles.split(","))]
    # "hint": the module's `WALK_FACE_HINT` (not a config field: the graph is dropped on a switch).
    variants += [(f"walk, face hint {int(v)}" + (f", settle {float(t) * 1e3:g} mm" if t else ""),
                  {"body_schedule": "walk", "body_settle": float(t or 0.0), "hint": bool(int(v))})
                 for v in filter(None, args.face_hints.split(","))
                 for t in (filter(None, args.settles.split(",")) if args.settles else [None])]
    # "rounds_hint", "rounds_skip": the module's `ROUNDS_FACE_HINT`, `ROUNDS_SKIP_SETTLED`.
    if args.rounds_hints or args.rounds_skips:
        import hairwarp.ops.guide_interpolation as ops_guides

        def listed(text, default):
            return [bool(int(v)) for v in filter(None, text.split(","))] or [default]

        variants += [(f"rounds, face hint {int(h)}, skip settled {int(k)}",
                      {"body_schedule": "rounds", "rounds_hint": h, "rounds_skip": k})
                     for h in listed(args.rounds_hints, ops_guides.ROUNDS_FACE_HINT)
                     for k in listed(args.rounds_skips, ops_guides.ROUNDS_SKIP_SETTLED)]
    variants += [(f"rounds, {int(v)} passes", {"body_schedule": "rounds", "body_passes": int(v)})
                 for v in filter(None, args.rounds_passes.split(","))]
    if variants:
        # Each body-pass variant on the same drape; the timings alternated in three rounds (the
        # median round), so that a machine's drift within the run falls on all of them alike.
        import hairwarp.ops.guide_interpolation as ops_guides

        switches = {"hint": "WALK_FACE_HINT", "rounds_hint": "ROUNDS_FACE_HINT", "rounds_skip": "ROUNDS_SKIP_SETTLED"}
        config, kept = guides.config, {key: getattr(ops_guides, name) for key, name in switches.items()}
        row["schedules"] = {}

        def use(change):
            change = dict(change)
            for key, name in switches.items():
                value = change.pop(key, kept[key])
                if value != getattr(ops_guides, name):
                    setattr(ops_guides, name, value)
                    guides.__dict__.pop("_graphs", None)
            guides.config = dataclasses.replace(config, **change)

        for name, change in variants:
            use(change)
            x, facts = scene.full_groom(draped, frames, guide_signed_distance=sd_draped)
            sd = guides.signed_distance(x, draped, sd_draped, frames.body_mesh)
            row["schedules"][name] = {
                "config": change, "interpolation_and_body_pass_rounds_ms": [],
                "inside_percent": {"followers": _inside(sd, follower_index), "all": _inside(sd, everyone)},
                "deepest_follower_mm": float(sd[:, follower_index, 2:].min()) * 1e3,
                "length_change_percent_all": _length_change(x, rest, everyone),
                "pushed_vertices": int(facts["pushed"].sum())}
        for _ in range(3):
            for name, change in variants:
                use(change)
                row["schedules"][name]["interpolation_and_body_pass_rounds_ms"].append(_timed(
                    lambda: scene.full_groom(draped, frames, guide_signed_distance=sd_draped), device, args.repeats))
        for name, change in variants:
            o = row["schedules"][name]
            o["interpolation_and_body_pass_ms"] = sorted(o["interpolation_and_body_pass_rounds_ms"])[1]
            use(change)
            o["interpolation_ms"] = _timed(lambda: scene.full_groom(draped, frames, body_pass=False), device,
                                           args.repeats)
        use(kept)
        guides.config = config
    if args.walk_block_dims:
        # The walk's CUDA threads per block, alternated in rounds on the same drape.
        import hairwarp.ops.guide_interpolation as ops_guides

        kept, config = ops_guides.WALK_THREADS_PER_BLOCK, guides.config
        guides.config = dataclasses.replace(config, cuda_graph=False)  # a graph keeps its launch's block size
        sizes = [int(v) for v in args.walk_block_dims.split(",")]
        times = {v: [] for v in sizes}
        for _ in range(3):
            for v in sizes:
                ops_guides.WALK_THREADS_PER_BLOCK = v
                times[v].append(_timed(lambda: scene.full_groom(draped, frames, guide_signed_distance=sd_draped),
                                       device, args.repeats))
        ops_guides.WALK_THREADS_PER_BLOCK, guides.config = kept, config
        row["walk_block_dims"] = {str(v): {"interpolation_and_body_pass_ms": sorted(t)[1], "rounds_ms": t}
                                  for v, t in times.items()}
    return row


def _run_command(argv: list[str]) -> dict:
    """Wall time [s] and the peak resident memory [GiB] of a command (a child of its own)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"command": " ".join(argv), "returncode": done.returncode, "wall_s": wall,
            "peak_rss_gib": max(peak, before) / 2**20, "output_tail": (done.stdout + done.stderr)[-1500:]}


def commands(args, sizes: list[int]) -> dict:
    out = {}
    big, small = max(sizes), min(sizes)
    drape_out = os.path.join(args.out, "drape_big")
    out["drape"] = _run_command(["hairwarp", "drape", "--hairstyle", os.path.join(args.out, f"groom_{big}.data"),
                                 "--pose", args.pose, "--time", str(args.time), "--no-progress", "--out", drape_out])
    sim_out = os.path.join(args.out, "simulate_small")
    out["simulate"] = _run_command(["hairwarp", "simulate", "--hairstyle", os.path.join(args.out, f"groom_{small}.data"),
                                    "--pose", args.pose, "--duration", str(args.simulate_seconds), "--method",
                                    args.simulate_method, "--no-progress", "--out", sim_out])
    usd = os.path.join(sim_out, "simulate.usdc")
    out["simulate"]["usdc_mib"] = os.path.getsize(usd) / 2**20 if os.path.exists(usd) else None
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--strands", default="10000,100000", help="groom sizes, comma-separated (default: 10000,100000)")
    p.add_argument("--guides", type=int, default=1024, help="guides K (default: 1024)")
    p.add_argument("--pose", default="head_turn", help="motion whose frame is draped (default: head_turn)")
    p.add_argument("--time", type=float, default=0.5, help="time of that frame [s] (default: 0.5)")
    p.add_argument("--lbfgs-iterations", type=int, default=300, help="L-BFGS iterations of the guides' drape")
    p.add_argument("--repeats", type=int, default=10, help="timed runs per measurement (default: 10)")
    p.add_argument("--commands", action="store_true", help="also run hairwarp drape / simulate on the grooms")
    p.add_argument("--simulate-seconds", type=float, default=2.0, help="--commands: seconds of motion simulated")
    p.add_argument("--simulate-method", default="dynamic", help="--commands: the simulate command's method")
    p.add_argument("--schedules", default="", help="also time these body-pass schedules, comma-separated "
                   "(walk,rounds), each on the same drape")
    p.add_argument("--settles", default="", help="also time the walk with these `GuideConfig.body_settle` [m], "
                   "comma-separated (e.g. 0,0.0005), each on the same drape")
    p.add_argument("--face-hints", default="", help="also time the walk with its face hint off / on "
                   "(`WALK_FACE_HINT`), comma-separated 0,1; crossed with --settles")
    p.add_argument("--rounds-hints", default="", help="also time the rounds with their face hint off / on "
                   "(`ROUNDS_FACE_HINT`), comma-separated 0,1; crossed with --rounds-skips (default: the module's)")
    p.add_argument("--rounds-skips", default="", help="also time the rounds with the settled strands walked "
                   "again / skipped (`ROUNDS_SKIP_SETTLED`), comma-separated 0,1")
    p.add_argument("--rounds-passes", default="", help="also time the rounds with these `GuideConfig.body_passes`, "
                   "comma-separated (e.g. 2,3)")
    p.add_argument("--walk-block-dims", default="", help="also time the walk's CUDA threads per block, "
                   "comma-separated (e.g. 32,64,128,256), alternated in three rounds on the same drape")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="bm_guides_out", help="folder for the grooms, outputs and bm_guides_<device>.json")
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    sizes = [int(s) for s in args.strands.split(",")]
    rows = []
    for n in sizes:
        row = measure_groom(n, args, device)
        rows.append(row)
        print(json.dumps(row, indent=1))
    record = {"machine": platform.node(), "device": torch.cuda.get_device_name(device) if device.type == "cuda"
              else f"CPU, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads",
              "command": "python benchmarks/bm_guides.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "rows": rows}
    if args.commands:
        record["commands"] = commands(args, sizes)
    print("| strands | guides | build [s] | interpolation [ms] | + body pass [ms] | inside % guides / followers / all "
          "| length change % all | curl change median / p90 (guides') | excess over the guide median / p90 |")
    print("|---:|---:|---:|---:|---:|---|---:|---|---|")
    for r in rows:
        inside, curl = r["lbfgs"]["inside_percent"], r["curl"]
        print(f"| {r['strands']} | {r['guides']} | {r['build_s']:.1f} | {r['interpolation_ms']:.2f} | "
              f"{r['interpolation_and_body_pass_ms']:.2f} | {inside['guides']:.3f} / {inside['followers']:.3f} / "
              f"{inside['all']:.3f} | {r['lbfgs']['length_change_percent']['all']:.3f} | "
              f"{curl['median_change']:.3f} / {curl['p90_change']:.3f} ({curl['their_guides_median_change']:.3f} / "
              f"{curl['their_guides_p90_change']:.3f}) | {curl['median_excess_over_guide']:+.3f} / "
              f"{curl['p90_excess_over_guide']:+.3f} |")
    for r in rows:
        if "interpolation_and_body_pass_eager_ms" in r:
            print(f"{r['strands']} strands: + body pass {r['interpolation_and_body_pass_ms']:.2f} ms replayed from its "
                  f"CUDA graph, {r['interpolation_and_body_pass_eager_ms']:.2f} ms launched from Python")
        for name, sch in r.get("schedules", {}).items():
            print(f"{r['strands']} strands, {name}: interpolation {sch['interpolation_ms']:.2f} ms, + body pass "
                  f"{sch['interpolation_and_body_pass_ms']:.2f} ms, inside % followers / all "
                  f"{sch['inside_percent']['followers']:.4f} / {sch['inside_percent']['all']:.4f}, deepest follower "
                  f"{sch['deepest_follower_mm']:.2f} mm, pushed {sch['pushed_vertices']}")
        for name, o in r.get("walk_block_dims", {}).items():
            print(f"{r['strands']} strands, walk in blocks of {name}: + body pass {o['interpolation_and_body_pass_ms']:.2f} "
                  f"ms (median of three rounds: {', '.join(f'{t:.2f}' for t in o['rounds_ms'])})")
    for name, c in record.get("commands", {}).items():
        print(f"{name}: {c['wall_s']:.0f} s, peak {c['peak_rss_gib']:.2f} GiB, rc {c['returncode']}"
              + (f", usdc {c['usdc_mib']:.0f} MiB" if c.get("usdc_mib") else ""))
    path = os.path.join(args.out, f"bm_guides_{device.type}.json")
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
