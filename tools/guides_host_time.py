"""Host time of `GuideSet.follow`'s per-call Python (`Scene.full_groom`, interpolation + body pass),
the device work stubbed out, so that it can be measured on a CPU-only machine.

Question it answers (issue 32, 10 000 strands in 2 ms on one H100): how many microseconds of
Python does a replayed `follow` spend around its launches? Two parts, each the best of five
means over `--calls` calls: the wrapper (`full_groom` -> `follow` with `_launches` returning a
stored result and the NaN/Inf scan off), and `_replayed` with its graph entry's replay a no-op
(the input copies and output clones run, on small CPU tensors: their host cost, not a copy's).
The CUDA scan and the replay themselves cannot run here (docs/guides.md, twelfth session).

    python tools/guides_host_time.py --strands 10000 --guides 32
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def per_call_us(fn, calls: int) -> float:
    """Host time [us] a call: the best of five means over `calls` calls, after 50 warm-ups."""
    for _ in range(50):
        fn()
    best = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best.append((time.perf_counter() - t0) / calls * 1e6)
    return min(best)


def main(argv=None) -> int:
    """Print both parts' host time per call (and, with --profile, the hottest functions)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--strands", type=int, default=10000)
    p.add_argument("--calls", type=int, default=2000)
    p.add_argument("--guides", type=int, default=32, help="guides K (few: the copies' host cost, not the CPU's)")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--out", default="guides_host_time_out", help="folder for the groom file")
    a = p.parse_args(argv)
    import hairwarp as hw
    from foreign_grooms import write_data_groom
    from hairwarp._validate import set_finite_checks
    from hairwarp.ops import hair_body_signed_distance
    from hairwarp.runtime import CapturedCall
    os.makedirs(a.out, exist_ok=True)
    path = write_data_groom(os.path.join(a.out, f"groom_{a.strands}.data"), a.strands, 0)
    scene = hw.build_scene(path, pose="head_turn", time=0.5, guides=a.guides)
    frames = scene.frames([0])
    pos = frames.rigid.positions
    body = frames.body_mesh
    sd = hair_body_signed_distance(pos, body)
    g = scene.guides
    x, facts = scene.full_groom(pos, frames, guide_signed_distance=sd)   # the real pass once
    real = (x, facts["pushed"])
    g._launches = lambda *args, **kw: real  # device work stubbed: what is left is the host's Python
    set_finite_checks(False)
    wrapper = per_call_us(lambda: scene.full_groom(pos, frames, guide_signed_distance=sd), a.calls)
    # The replay branch: a graph entry whose replay is a no-op on CPU buffers (copies and clones run).
    inputs = (pos, frames.posed.head_transform[:, :3, :3], sd)
    g.__dict__.pop("_graphs", None)
    g._replayed(inputs, body)
    (entry,) = g._graphs.values()
    shell = object.__new__(CapturedCall)
    shell.inputs = [t.detach().clone() for t in inputs]
    shell.output = tuple(t[:, :2].clone() for t in real)  # host cost of a clone, not the CPU's copy
    shell.graph = type("NoGraph", (), {"replay": staticmethod(lambda: None)})()
    entry["call"] = shell
    replay = per_call_us(lambda: g._replayed(inputs, body), a.calls)
    print(f"{a.strands} strands: full_groom wrapper (checks, no device work) {wrapper:.1f} us/call; "
          f"_replayed with a no-op replay {replay:.1f} us/call")
    if a.profile:
        pr = cProfile.Profile()
        pr.enable()
        for _ in range(a.calls):
            scene.full_groom(pos, frames, guide_signed_distance=sd)
            g._replayed(inputs, body)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(25)
    return 0


if __name__ == "__main__":
    sys.exit(main())
