"""ms per drape of the body pass (`hairwarp.methods.keep_out.keep_out_of_body`) at batch 1.

The pass runs after every network drape by default (`MethodOptions.keep_out`). Its input here is
the shipped static network's raw drape (`keep_out=False`) of the scenes of tools/static_rows.py
that the networks leave partly inside the body: long straight hair grown on the body at rest, a
bob at head_turn t = 0.5 s (the rounds stop early at full size) and long curly hair grown on the
head at nod t = 0.5 s (at full size the long hair's rounds all push, then the pinch turns run).
Full size is 1 024 strands x 100 vertices; on the CPU the default keeps every 8th strand.

    python benchmarks/bm_keep_out.py --device cuda --out OUT
    python benchmarks/bm_keep_out.py --device cpu --out OUT          # --strand-stride 8

Prints one row per scene (ms per drape, the rounds the pass ran where the library reports them)
and writes OUT/keep_out.json. On CUDA each row also times the pass launched eagerly against the
pass replayed from CUDA graphs (`keep_out.KEEP_OUT_GRAPHS`, alternated in one process; their
results must agree bit for bit), and the static method's drape of the frame as the method times
it (`MethodResult.time_ms`: network and pass, both replayed): the batch-1 latency.
`--profile` adds, per scene, the time of the pushing rounds alone
(`pushed_out_of_body`), each kernel's device time per drape under `torch.profiler` (the largest
25) and the host's Python functions' own time per drape under `cProfile` (the largest 20, the
waits for the device among them), to tell the device's work from the host's launches and reads.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

import torch

# name -> build_scene arguments (tools/static_rows.py's scenes).
SCENES = {
    "long_straight_rest_grown_on_body": dict(hairstyle="long_straight", pose="rest", grow="body"),
    "bob_head_turn_0.5s": dict(hairstyle="bob", pose="head_turn", time=0.5),
    "long_curly_nod_0.5s_grown_on_head": dict(hairstyle="long_curly", pose="nod", time=0.5, grow="head"),
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--strand-stride", type=int, default=None, help="default: 1 on CUDA, 8 on the CPU")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--profile", action="store_true",
                        help="also time the rounds alone and record each kernel's device time per drape")
    parser.add_argument("--turn-rounds-per-replay", default="",
                        help="on CUDA, also time the replayed pass with these many pinch-turn rounds per replay "
                             "(comma-separated, alternated in one process; the library's default is "
                             "keep_out._TURN_ROUNDS_PER_REPLAY)")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)

    import hairwarp as hw
    from hairwarp.methods import keep_out
    from hairwarp.runtime import machine_description, machine_name, time_ms, time_ms_interleaved

    device = torch.device(args.device)
    stride = args.strand_stride or (1 if device.type == "cuda" else 8)
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for name in args.scenes.split(","):
        scene = hw.build_scene(strand_stride=stride, **SCENES[name])
        raw = hw.drape(scene, method="static", device=device, keep_out=False, progress=False)
        x = raw.positions[None].float().contiguous()
        rigid = raw.frames.rigid.positions.float().contiguous()
        body = raw.frames.body_mesh
        with torch.no_grad():
            ms = time_ms(lambda: keep_out.keep_out_of_body(x, rigid, body), device, repeats=args.repeats)
            rounds = getattr(keep_out, "pushed_out_of_body", None)
            rounds = None if rounds is None else rounds(x, rigid, body)[1]
        row = {"scene": name, "strands": x.shape[1], "vertices": x.shape[2], "keep_out_ms": ms,
               "push_rounds": rounds}
        if device.type == "cuda":
            row.update(_replayed_against_eager(keep_out, x, rigid, body, raw.frames, device, time_ms_interleaved))
            if args.turn_rounds_per_replay:
                row["replayed_ms_by_turn_rounds_per_replay"] = _turn_rounds_per_replay(
                    keep_out, x, rigid, body, [int(v) for v in args.turn_rounds_per_replay.split(",")], device,
                    time_ms_interleaved)
        if args.profile:
            with torch.no_grad():
                row["rounds_alone_ms"] = time_ms(lambda: keep_out.pushed_out_of_body(x, rigid, body), device,
                                                 repeats=args.repeats)
                row["kernels_us_per_drape"], row["wall_ms_under_profiler"] = _kernel_profile(
                    lambda: keep_out.keep_out_of_body(x, rigid, body), device)
                row["host_python_us_per_drape"] = _host_profile(lambda: keep_out.keep_out_of_body(x, rigid, body),
                                                                device)
            print(f"  rounds alone {row['rounds_alone_ms']:.2f} ms; device busy "
                  f"{sum(row['kernels_us_per_drape'].values()) / 1e3:.2f} ms of "
                  f"{row['wall_ms_under_profiler']:.2f} ms under the profiler", flush=True)
        rows.append(row)
        print(f"{name}: {x.shape[1]} x {x.shape[2]}, {ms:.2f} ms per drape"
              + ("" if rounds is None else f", {rounds} pushing rounds"), flush=True)
    record = {"device": machine_name(device), "machine": machine_description(device),
              "command": "python benchmarks/bm_keep_out.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "strand_stride": stride, "rows": rows}
    with open(os.path.join(args.out, "keep_out.json"), "w") as fh:
        json.dump(record, fh, indent=1, default=float)
    return 0


def _replayed_against_eager(keep_out, x, rigid, body, frames, device, time_ms_interleaved) -> dict:
    """The pass eager against replayed from graphs, alternated; the static method's drape of
    `frames` (network and pass) against the network alone. Returns the row's entries."""
    from hairwarp.methods.networks import NetworkMethod

    def pass_with(graphs: bool):
        def call():
            previous, keep_out.KEEP_OUT_GRAPHS = keep_out.KEEP_OUT_GRAPHS, graphs
            try:
                return keep_out.keep_out_of_body(x, rigid, body)
            finally:
                keep_out.KEEP_OUT_GRAPHS = previous
        return call

    with torch.no_grad():
        eager, replayed = pass_with(False), pass_with(True)
        difference = max(float((replayed() - eager()).abs().max()) for _ in range(3))
        times = time_ms_interleaved({"eager": eager, "replayed": replayed}, device)
        # The method times its own work (`MethodResult.time_ms`: one synchronised call after a
        # warm-up call, network and pass): the medians of that over repeated drapes.
        whole = NetworkMethod("static")
        results = [whole.drape(frames) for _ in range(12)][2:]
        drape_ms = statistics.median(r.time_ms for r in results)
        pass_ms = statistics.median(r.info["keep_out_ms"] for r in results)
    print(f"  pass eager {times['eager']:.2f} ms, replayed {times['replayed']:.2f} ms (largest difference "
          f"{difference:.1e} m); the static method's drape {drape_ms:.2f} ms, of it the pass {pass_ms:.2f} ms",
          flush=True)
    return {"eager_ms": times["eager"], "replayed_ms": times["replayed"], "replayed_minus_eager_max_m": difference,
            "static_drape_ms": drape_ms, "static_drape_pass_ms": pass_ms}


def _turn_rounds_per_replay(keep_out, x, rigid, body, values, device, time_ms_interleaved) -> dict:
    """The replayed pass (its own instances, called directly: no argument check) with each number
    of pinch-turn rounds per replay, alternated; every one must give the same positions."""
    settings = dict(margin=keep_out.KEEP_OUT_MARGIN, passes=keep_out.KEEP_OUT_PASSES,
                    trigger=keep_out.KEEP_OUT_TRIGGER, turns=keep_out.KEEP_OUT_TURNS,
                    final_depth=keep_out.KEEP_OUT_FINAL_DEPTH)
    calls, results = {}, []
    with torch.no_grad():
        for value in values:
            replayed = keep_out._ReplayedPass(x, rigid, body, settings)
            replayed.turn_rounds_per_replay = value
            calls[str(value)] = lambda p=replayed: p(x, rigid)
            results.append(calls[str(value)]())
        if any(not torch.equal(r, results[0]) for r in results):
            raise RuntimeError("the replayed pass's positions depend on its turn rounds per replay")
        times = time_ms_interleaved(calls, device)
    print("  turn rounds per replay: " + ", ".join(f"{k}: {v:.2f} ms" for k, v in times.items()), flush=True)
    return times


def _kernel_profile(fn, device: torch.device, repeats: int = 5) -> tuple[dict[str, float], float]:
    """Each kernel's device time per call of `fn` [us] (the 25 largest) and the wall time per
    call under the profiler [ms]."""
    import time

    from hairwarp.runtime import kernel_device_times, synchronize

    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    fn()
    synchronize(device)
    with torch.profiler.profile(activities=activities) as prof:
        start = time.perf_counter()
        for _ in range(repeats):
            fn()
        synchronize(device)
        wall = (time.perf_counter() - start) * 1e3 / repeats
    top = kernel_device_times(prof, per=repeats, top=25) if device.type == "cuda" else {}
    return top, wall


def _host_profile(fn, device: torch.device, repeats: int = 5) -> dict[str, float]:
    """The host's Python functions by their own time per call of `fn` [us] (`cProfile`, the 20
    largest; a wait for the device shows as the function that waits)."""
    import cProfile
    import pstats

    from hairwarp.runtime import synchronize

    fn()
    synchronize(device)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(repeats):
        fn()
    synchronize(device)
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    own = {f"{os.path.basename(path)}:{line}({name})": entry[2] * 1e6 / repeats
           for (path, line, name), entry in stats.items()}
    return dict(sorted(own.items(), key=lambda kv: -kv[1])[:20])


if __name__ == "__main__":
    sys.exit(main())
