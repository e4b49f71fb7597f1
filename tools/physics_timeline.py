"""Where a physics frame's wall time goes: the graphs' device time against the host's wall, per step.

    python3 tools/physics_timeline.py --device cuda --motions whiplash,torso_bend --frames 16 --out OUT

For each motion (a comparison scene): the default `physics` drape of the first frame, then
`--frames` implicit-Euler steps with the default `PhysicsConfig` (one warm pass over the same
frames first: compiles and graph captures are not timed). Every call the solver makes through
its graphs (`PhysicsSolver._run`: "begin", "iterateK", "rebuild") is bracketed by CUDA events,
so each replay's device time is known; the step's host wall (synchronised) less those is what
the device spends outside the graphs or waits for the host (the chunks' reads of the stopping
rule, the frame's body update, the warm start and the result's copies). `set_frame` (body
update) is timed on its own. Writes OUT/physics_timeline.json and prints a table per motion.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections import defaultdict

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


class _Recorder:
    """Brackets `PhysicsSolver._run` and `set_frame` with timers (CUDA events on CUDA)."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.device = device
        self.events: list[tuple[str, object, object]] = []
        self.set_frame_ms: list[float] = []

    def clear(self):
        self.events = []
        self.set_frame_ms = []

    def _sync(self):
        if self.cuda:
            torch.cuda.synchronize(self.device)

    def wrap(self, solver_class):
        recorder = self
        run, set_frame = solver_class._run, solver_class.set_frame

        def timed_run(solver, name, fn):
            kind = name.rstrip("0123456789")
            if recorder.cuda:
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                run(solver, name, fn)
                end.record()
                recorder.events.append((kind, start, end))
            else:
                t0 = time.perf_counter()
                run(solver, name, fn)
                recorder.events.append((kind, t0, time.perf_counter()))

        def timed_set_frame(solver, *args, **kwargs):
            recorder._sync()
            t0 = time.perf_counter()
            set_frame(solver, *args, **kwargs)
            recorder._sync()
            recorder.set_frame_ms.append((time.perf_counter() - t0) * 1e3)

        solver_class._run, solver_class.set_frame = timed_run, timed_set_frame

    def device_ms(self) -> dict[str, list[float]]:
        self._sync()
        out: dict[str, list[float]] = defaultdict(list)
        for kind, start, end in self.events:
            out[kind].append(start.elapsed_time(end) if self.cuda else (end - start) * 1e3)
        return out


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--motions", default="whiplash,torso_bend")
    p.add_argument("--strand-stride", type=int, default=1)
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--variant", action="append", default=[],
                   help="NAME:FIELD=VALUE,... a PhysicsConfig variant (repeatable), as benchmarks/bm_physics.py")
    p.add_argument("--out", default="physics_timeline_out")
    args = p.parse_args(argv)
    from diagnose_networks import write_json

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
    from bm_physics import _variants

    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.runtime import machine_description, synchronize
    from hairwarp.solvers import physics
    from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

    device = torch.device(args.device)
    variants = _variants(args.variant, PhysicsConfig()) or {"default": PhysicsConfig()}
    recorder = _Recorder(device)
    recorder.wrap(physics.PhysicsSolver)
    record = {"machine": machine_description(device), "command": "python3 tools/physics_timeline.py "
              + " ".join(argv if argv is not None else sys.argv[1:]), "motions": {}}
    for name in args.motions.split(","):
        scene = comparison_scene(name, reduced=False, strand_stride=args.strand_stride).scene
        frames = list(range(min(args.frames, scene.num_frames)))
        x0 = simulate_physics(scene, frames[:1], device=device).positions[0]
        record["motions"][name] = {}
        for variant, config in variants.items():
            simulate_physics(scene, frames, device=device, config=config, initial=x0)  # warm: compiles, captures
            synchronize(device)
            recorder.clear()
            result = simulate_physics(scene, frames, device=device, config=config, initial=x0)
            graphs = recorder.device_ms()
            steps = len(frames) - 1
            wall = sum(result.frame_ms[1:])
            iterations = sum(result.iterations[1:])
            graph_total = sum(sum(v) for v in graphs.values())
            row = {
                "steps": steps,
                "iterations_per_step": iterations / steps,
                "wall_ms_per_step": wall / steps,
                "median_ms_per_step": statistics.median(result.frame_ms[1:]),
                "set_frame_ms_per_step": sum(recorder.set_frame_ms) / steps,
                "graph_device_ms_per_step": {k: sum(v) / steps for k, v in graphs.items()},
                "graph_calls_per_step": {k: len(v) / steps for k, v in graphs.items()},
                # a solver captures each graph at its first call: the later calls are the replays
                "graph_replay_median_ms": {k: statistics.median(v[1:]) for k, v in graphs.items() if len(v) > 1},
                "graph_first_call_ms": {k: v[0] for k, v in graphs.items()},
                "graph_device_us_per_iteration": graph_total * 1e3 / max(iterations, 1),
                "outside_graphs_ms_per_step": (wall - graph_total - sum(recorder.set_frame_ms)) / steps,
                "wall_us_per_iteration": wall * 1e3 / max(iterations, 1),
            }
            record["motions"][name][variant] = row
            calls = ", ".join(f"{k} {v:.1f}" for k, v in row["graph_calls_per_step"].items())
            device_ms = ", ".join(f"{k} {v:.2f}" for k, v in row["graph_device_ms_per_step"].items())
            print(f"{name} [{variant}]: {row['wall_ms_per_step']:.1f} ms a step (median "
                  f"{row['median_ms_per_step']:.1f}), {row['iterations_per_step']:.1f} iterations; "
                  f"graphs' device time {device_ms} ms ({calls} calls); set_frame {row['set_frame_ms_per_step']:.2f} ms; "
                  f"outside {row['outside_graphs_ms_per_step']:.2f} ms; device {row['graph_device_us_per_iteration']:.0f} "
                  f"us / wall {row['wall_us_per_iteration']:.0f} us an iteration; replays' median "
                  + ", ".join(f"{k} {v:.2f}" for k, v in row["graph_replay_median_ms"].items()) + " ms", flush=True)
    write_json(args.out, "physics_timeline.json", record)
    return record


if __name__ == "__main__":
    main()
