"""The physics simulation's speed and accuracy against its tight setting, side by side.

    python3 benchmarks/bm_physics.py --device cuda --out OUT                 # full size (1024 x 100)
    python3 benchmarks/bm_physics.py --device cpu --strand-stride 4 --frames 12 --out OUT   # 256 x 100

For each motion (`--motions`: comparison scenes, or the held-out motions of
`tools/train_inertial.py evaluate`: bob_nod, curly_sway_walk, long_arm_raise, wavy_amass): the
hair starts at the converged static drape
of the first frame (the `reference` drape: tight tolerance); then
- `physics` (`PhysicsConfig()`) simulates `--frames` frames: ms per frame (each step's wall
  time, synchronised: posing, body update, solve), iterations per step;
- the tight setting (`PhysicsConfig().tight()`: tolerance / 100) simulates the same frames:
  the trajectory distance of `physics` to it per frame (mean vertex distance [mm]);
- per step: from the tight trajectory's states, one `physics` step against the tight step
  (mean vertex distance [mm]): every step's own error, without the drift.
With `--variant NAME:FIELD=VALUE,...` (repeatable) each variant of the fast setting runs in turn,
`--rounds` times alternated, against the same start and tight trajectory (speed compared within
one run); without, the one fast setting the flags give.
Writes OUT/physics.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from dataclasses import replace

import torch


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--motions", default="whiplash,torso_bend",
                        help="comparison scenes, held-out motions (tools/train_inertial.py's EVALUATION labels) "
                             "or LABEL=HAIRSTYLE:POSE:START:DURATION")
    parser.add_argument("--strand-stride", type=int, default=1, help="every k-th strand of the full groom")
    parser.add_argument("--frames", type=int, default=0, help="frames per motion (0: all)")
    parser.add_argument("--per-step", type=int, default=10, help="steps checked one by one from the tight states")
    parser.add_argument("--tolerance", type=float, default=None,
                        help="the fast setting's tolerance [m] (default: PhysicsConfig's)")
    parser.add_argument("--max-iterations", type=int, default=None, help="the fast setting's iteration cap per step")
    parser.add_argument("--stiffness-scaling", type=float, default=None,
                        help="the fast setting's PhysicsConfig.stiffness_scaling (0: unscaled variables)")
    parser.add_argument("--variant", action="append", default=[],
                        help="NAME:FIELD=VALUE,... a PhysicsConfig variant of the fast setting (repeatable), "
                             "e.g. list3mm:hair_hair_list=1,hair_hair_list_skin=0.003")
    parser.add_argument("--rounds", type=int, default=1, help="with --variant: alternated rounds of the variants")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="hairwarp-out")
    return parser


def _mean_distance_mm(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm(dim=-1)[..., 2:].mean()) * 1e3


def _motion_scene(name: str, strand_stride: int, out: str):
    """The scene of a `--motions` name: a comparison scene, else a held-out motion of
    `tools/train_inertial.py evaluate` (the same scene it scores the networks on).
    """
    import sys

    from hairwarp.evaluation.scenes import SCENE_NAMES, comparison_scene

    if name in SCENE_NAMES:
        return comparison_scene(name, reduced=False, strand_stride=strand_stride).scene
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tools"))
    from train_inertial import _evaluation_scene, evaluation_specs

    try:
        (spec,) = evaluation_specs(name)
    except ValueError as error:
        raise SystemExit(f"--motions: {name!r} is not a comparison scene ({', '.join(SCENE_NAMES)}); {error}") from None
    return _evaluation_scene(*spec, strand_stride, out)


def _variants(specs: list[str], base) -> dict:
    """{name: PhysicsConfig} of `--variant` specs (values parsed as numbers or booleans)."""
    from hairwarp.solvers.physics import PhysicsConfig

    fields = {f for f in PhysicsConfig.__dataclass_fields__}
    variants = {}
    for spec in specs:
        name, _, body = spec.partition(":")
        changes = {}
        for item in filter(None, body.split(",")):
            key, _, value = item.partition("=")
            if key not in fields:
                raise SystemExit(f"--variant {spec!r}: {key!r} is not a PhysicsConfig field")
            kind = type(getattr(base, key))
            if kind is bool or getattr(base, key) is None:
                changes[key] = value.lower() in ("1", "true", "on")
            elif kind is str:
                changes[key] = value
            else:
                changes[key] = kind(float(value)) if kind is int else float(value)
        variants[name or f"variant{len(variants)}"] = replace(base, **changes)
    return variants


def _per_step(solver, posed, tight, steps) -> tuple[list[float], list[int]]:
    """From the tight states, one step of `solver` at each of `steps` against the tight step."""
    distances, iterations = [], []
    for t in steps:
        solver.set_frame(posed.rigid.positions[t:t + 1], posed.rigid.normals[t:t + 1], posed.posed.vertices[t:t + 1])
        solver.set_state(tight.positions[t - 1], tight.positions[t - 2])
        report = solver.step()
        distances.append(_mean_distance_mm(solver.prev, tight.positions[t]))
        iterations.append(report.iterations)
    return distances, iterations


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    from hairwarp.config import EnergyConfig
    from hairwarp.ops import BodyMesh
    from hairwarp.runtime import machine_description, synchronize
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver, simulate_physics

    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    # the default's tight setting, whatever the fast one, on the diagonal scaling (the yardstick of
    # the earlier result files; the strand preconditioner is measured against it)
    tight_config = replace(PhysicsConfig(), strand_preconditioner=False).tight()
    changes = {"tolerance": args.tolerance, "max_iterations": args.max_iterations,
               "stiffness_scaling": args.stiffness_scaling}
    fast_config = replace(PhysicsConfig(), **{k: v for k, v in changes.items() if v is not None})
    variants = _variants(args.variant, fast_config)
    record = {"machine": machine_description(device), "physics": fast_config.__dict__,
              "tight": tight_config.__dict__, "motions": {}}
    if variants:
        record["variants"] = {name: config.__dict__ for name, config in variants.items()}
    for name in args.motions.split(","):
        scene = _motion_scene(name, args.strand_stride, args.out)
        frames = list(range(scene.num_frames if args.frames <= 0 else min(args.frames, scene.num_frames)))
        strands, vertices = scene.hairstyle.strands.shape[:2]
        print(f"{name}: {strands} x {vertices}, {len(frames)} frames on {device}", flush=True)
        start = simulate_physics(scene, frames[:1], device=device, config=tight_config)
        x0 = start.positions[0]
        tight = simulate_physics(scene, frames, device=device, config=tight_config, initial=x0)
        energy_config = EnergyConfig().replace(time_step=1.0 / float(scene.motion.fps))
        posed = scene.frames(frames, device=device, build_body=False)
        rest = scene.rest_lengths.to(device)
        steps = range(2, min(len(frames), 2 + args.per_step))
        if variants:
            runs = {variant: [] for variant in variants}
            for _ in range(max(1, args.rounds) + 1):  # the first round warms up (compiles, captures)
                for variant, config in variants.items():
                    runs[variant].append(simulate_physics(scene, frames, device=device, config=config, initial=x0))
            entry = {"strands": strands, "vertices": vertices, "frames": len(frames), "variants": {}}
            for variant, config in variants.items():
                timed = runs[variant][1:]
                body = BodyMesh(posed.posed.vertices[:1], scene.body.faces.to(device=device, dtype=torch.int32),
                                bvh="lbvh")
                solver = PhysicsSolver(rest, posed.rigid.positions[:1], posed.rigid.normals[:1], body, energy_config,
                                       config)
                per_step, per_step_iterations = _per_step(solver, posed, tight, steps)
                medians = [statistics.median(run.frame_ms[1:]) for run in timed]
                trajectory = [_mean_distance_mm(a, b) for a, b in zip(timed[-1].positions, tight.positions)]
                entry["variants"][variant] = {
                    "ms_per_frame_median_by_round": medians,
                    "iterations": [run.iterations[1:] for run in timed],
                    "rebuilds": [[r.rebuilds for r in run.reports[1:]] for run in timed],
                    "stop_reasons": timed[-1].stop_reasons[1:],
                    "trajectory_distance_mm": trajectory, "per_step_distance_mm": per_step,
                    "per_step_iterations": per_step_iterations,
                }
                rebuilds = statistics.mean(r.rebuilds for run in timed for r in run.reports[1:])
                its = statistics.mean(i for run in timed for i in run.iterations[1:])
                print(f"  {variant}: {' / '.join(f'{m:.1f}' for m in medians)} ms/frame (median by round), "
                      f"{its:.1f} iterations, {rebuilds:.2f} rebuilds a step; 10 frames max "
                      f"{max(trajectory[:10]):.3f} mm, all max {max(trajectory):.3f} mm, per step max "
                      f"{max(per_step):.3f} mm", flush=True)
            entry["tight_ms_median"] = statistics.median(tight.frame_ms[1:]) if len(frames) > 1 else None
            entry["tight_iterations"] = tight.iterations[1:]
            record["motions"][name] = entry
            continue
        fast = simulate_physics(scene, frames, device=device, config=fast_config, initial=x0)
        fast_again = simulate_physics(scene, frames, device=device, config=fast_config, initial=x0)  # warm
        trajectory = [_mean_distance_mm(a, b) for a, b in zip(fast_again.positions, tight.positions)]
        # Each step on its own: from the tight states, one fast step against the tight step.
        body = BodyMesh(posed.posed.vertices[:1], scene.body.faces.to(device=device, dtype=torch.int32), bvh="lbvh")
        solver = PhysicsSolver(rest, posed.rigid.positions[:1], posed.rigid.normals[:1], body, energy_config, fast_config)
        per_step, per_step_iterations = _per_step(solver, posed, tight, steps)
        synchronize(device)
        motion = [_mean_distance_mm(tight.positions[t], tight.positions[0]) for t in range(len(frames))]
        entry = {
            "strands": strands, "vertices": vertices, "frames": len(frames),
            "physics_ms_per_frame": fast_again.frame_ms[1:], "physics_iterations": fast_again.iterations[1:],
            "physics_stop_reasons": fast_again.stop_reasons[1:],
            "physics_first_run_ms_per_frame": fast.frame_ms[1:],
            "tight_ms_per_frame": tight.frame_ms[1:], "tight_iterations": tight.iterations[1:],
            "tight_stop_reasons": tight.stop_reasons[1:],
            "static_drape_ms": start.frame_ms[0], "static_drape_iterations": start.iterations[0],
            "trajectory_distance_mm": trajectory, "per_step_distance_mm": per_step,
            "per_step_iterations": per_step_iterations, "tight_motion_mm": motion,
        }
        steady = fast_again.frame_ms[1:]
        entry["physics_ms_median"] = statistics.median(steady) if steady else None
        entry["tight_ms_median"] = statistics.median(tight.frame_ms[1:]) if len(frames) > 1 else None
        record["motions"][name] = entry
        iterations = statistics.mean(fast_again.iterations[1:])
        print(f"  physics {entry['physics_ms_median']:.1f} ms/frame (median; max {max(steady):.1f}), "
              f"iterations {iterations:.1f}; tight {entry['tight_ms_median']:.1f} ms/frame", flush=True)
        print(f"  trajectory distance to tight: first 10 frames max {max(trajectory[:10]):.3f} mm, "
              f"all frames max {max(trajectory):.3f} mm; per step max {max(per_step):.3f} mm "
              f"(tight motion up to {max(motion):.1f} mm)", flush=True)
    os.makedirs(args.out, exist_ok=True)
    tag = "".join(f"_{k}{v:g}" for k, v in changes.items() if v is not None)
    path = os.path.join(args.out, f"physics{tag}.json")
    with open(path, "w") as f:
        json.dump(record, f, indent=1, default=str)
    print(path)
    return record


if __name__ == "__main__":
    t0 = time.perf_counter()
    main()
    print(f"{time.perf_counter() - t0:.0f} s")
