"""Train the shipped HairFormer checkpoints within a wall-clock budget (run on a GPU machine).

    python tools/train_shipped.py static  --device cuda --minutes 6 --out OUT
    python tools/train_shipped.py dynamic --device cuda --minutes 6 --static OUT/static_run/checkpoint.pt --out OUT
    python tools/train_shipped.py dynamic --device cuda --minutes 4 --init src/hairwarp/assets/hairformer_dynamic.pt \
        --grown-hair-fraction 0.5 --long-hair-fraction 0.3 --out OUT
    python tools/train_shipped.py quaffure --device cuda --steps 1100 --out OUT
    python tools/train_shipped.py static --device cuda --steps 3000 --init src/hairwarp/assets/hairformer_dynamic.pt \
        --teacher-pool 64 --teacher-iterations 800 --bp-start 0.01 --lr 5e-5 --out OUT

The curriculum's length depends on its total step count (phase boundaries, the b_p anneal of
Section 4.2.1), so the step count is fixed before training: a short probe times a step of the
costliest phase and the budget is divided by it. The corpus latents of the hairstyle pool are
encoded up front on every CPU core (encoding a procedural hairstyle costs ~0.3 s, which would
otherwise starve the GPU). Writes into OUT:

- `<kind>_run/` (config.toml, log.jsonl, checkpoint.pt: float32 weights and optimizer state),
- `hairformer_<kind>.pt`: the float16 weights to ship in `src/hairwarp/assets/`,
- `train_<kind>.json`: sizes, steps, time per step, the loss at the start and the end.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import time

import numpy as np
import torch

# The shipped size: every other root of the 32 x 32 scalp (256 strands) x 100 vertices in the
# loss; the network still predicts the full 8 x 8 x N x 3 deformation map.
STRAND_STRIDE = 2
PHASE2_HAIRSTYLES = 128
PHASE3_HAIRSTYLES = 512
# Defaults of the flags per --recipe ("lr": static/quaffure, dynamic). "shipped" made the shipped
# checkpoint (docs/training_diagnosis.md, "What made the networks drape"); "paper" is Section 4.2.
RECIPES = {
    "shipped": {"bp_start": 0.1, "loss_normalization": "inverse", "grad_clip_norm": 1.0, "lr": (2e-4, 3e-5),
                "long_hair_fraction": 0.3, "model": {"length_projection": "follow_the_leader", "contact_samples": 16}},
    "paper": {"bp_start": 0.9, "loss_normalization": "none", "grad_clip_norm": 0.0, "lr": (1e-4, 1e-4),
              "long_hair_fraction": 0.0, "model": {"length_projection": "none", "contact_samples": 0}},
}
# DynamicConfig fields per --recipe (a dynamic run's --model overrides these). The shipped recipe
# weights Eq. 4's functional regularization so that the dynamic head's drift from the static
# head (~1e-3 m^2 after 400 steps at weight 1) counts as much as the energy (~3).
RECIPES_DYNAMIC_MODEL = {"shipped": {"func_reg_weight": 1000.0}, "paper": {}}
# Step cap of a dynamic run given only a time budget (the budget ends it first).
DYNAMIC_OPEN_STEPS = 100_000
# Share of the steps in each curriculum phase (0: rest, 1: head rotations, 2: one subject, 3: all).
PHASE_SHARES = (0.05, 0.15, 0.25, 0.55)


def data_config(long_hair_fraction: float = 0.0, motions: list | None = None, grown_hair_fraction: float = 0.0):
    from hairwarp.training.config import DataConfig

    # Every hairstyle of the pool stays decoded (256 x 100 x 3 float32: 0.3 MB each): decoding one
    # costs ~40 ms on the CPU, which at batch 32 would be most of a step.
    extra = {} if motions is None else {"motions": list(motions)}
    return DataConfig(strand_stride=STRAND_STRIDE, hairstyle_cache_size=PHASE3_HAIRSTYLES, pose_cache_size=4096,
                      long_hair_fraction=long_hair_fraction, grown_hair_fraction=grown_hair_fraction, **extra)


def _encode_chunk(job):
    indices, grown_hair_fraction = job
    torch.set_num_threads(1)
    from hairwarp.training.data import TrainingSampler

    sampler = TrainingSampler(data_config(grown_hair_fraction=grown_hair_fraction), device="cpu")
    out = []
    for i in indices:
        if sampler.is_grown(i):  # grown around the body: ~0.4-1 s each
            z, strands = sampler.grown_hairstyle(i)
            out.append((i, z.numpy(), strands.numpy()))
        else:
            out.append((i, sampler.latent(i).numpy(), None))
    return out


def precompute_latents(sampler, count: int, workers: int) -> float:
    """Fill the sampler's corpus-latent cache (and its grown hairstyles', when
    `grown_hair_fraction` > 0) for hairstyles 0..count-1 in parallel; seconds."""
    start = time.perf_counter()
    fraction = sampler.config.grown_hair_fraction
    chunks = [(list(range(count))[k::workers], fraction) for k in range(workers)]
    with mp.get_context("fork").Pool(workers) as pool:
        for part in pool.map(_encode_chunk, chunks):
            for i, z, strands in part:
                if strands is None:
                    sampler._latents[i] = torch.as_tensor(z, dtype=torch.float64)
                else:
                    sampler._grown[i] = (torch.as_tensor(z, dtype=torch.float64),
                                         torch.as_tensor(strands, dtype=torch.float64))
    return time.perf_counter() - start


def _time_steps(trainer, warmup: int, timed: int, device) -> float:
    for _ in range(warmup):
        trainer.train_step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(timed):
        trainer.train_step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / timed


def _loop(trainer, budget_s: float, start: float, device) -> None:
    from tqdm.auto import tqdm

    bar = tqdm(total=trainer.total_steps, initial=trainer.step, desc=f"train {trainer.kind}", mininterval=10)
    every = max(1, min(trainer.total_steps // 20, 50))
    trainer.record_curve()  # the learning curve (--curve-every), when due
    while trainer.step < trainer.total_steps and time.perf_counter() - start < budget_s:
        record = trainer.train_step()
        entry = trainer.record_curve()
        if entry is not None and "held_out" in entry:
            print(json.dumps({"step": entry["step"], **{k: [round(v["penetration_percent"], 2),
                              round(v["length_change_percent"], 2)] for k, v in entry["held_out"].items()}}),
                  flush=True)
        bar.update(1)
        if trainer.step % every == 0:
            print(json.dumps({k: record[k] for k in ("step", "loss", "phase", "bp") if k in record}), flush=True)
    bar.close()
    if device.type == "cuda":
        torch.cuda.synchronize()


def _finish(trainer, args, kind: str, info: dict, start: float) -> None:
    from hairwarp.models.checkpoint import parameter_count, save_checkpoint

    trainer.save()
    trainer.close()
    ship = os.path.join(args.out, f"hairformer_{kind}.pt")
    save_checkpoint(ship, trainer.model, step=trainer.step, extra={"training": kind,
                    "training_config": trainer.config.to_dict()}, dtype=torch.float16)
    history = trainer.history
    head = [r["loss"] for r in history[:20]]
    tail = [r["loss"] for r in history[-20:]]
    info.update({
        "steps_done": trainer.step, "wall_s": time.perf_counter() - start,
        "loss_first20_mean": float(np.mean(head)) if head else None,
        "loss_last20_mean": float(np.mean(tail)) if tail else None,
        "last_terms": history[-1]["terms"] if history else None,
        "parameters": parameter_count(trainer.model),
        "shipped_bytes": os.path.getsize(ship),
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu",
    })
    choices = getattr(getattr(trainer, "_teacher", None), "choices", None)
    if choices:
        # Which teacher start won per sample (teacher_start "lower", "lower_where_clean" or
        # "rigid_where_clean"), with what may decide it: the rigid placement's penetration and
        # the hair's length.
        chosen = [c for r in choices for c in r["rigid_chosen"]]
        inside = [p for r in choices for p in r["rigid_inside_percent"]]
        info["teacher_choices"] = {
            "samples": len(chosen), "rigid_chosen": int(sum(chosen)),
            "rigid_chosen_where_rigid_clean": int(sum(c for c, p in zip(chosen, inside) if p == 0)),
            "rigid_clean": int(sum(p == 0 for p in inside)), "batches": choices}
    with open(os.path.join(args.out, f"train_{kind}.json"), "w") as f:
        json.dump(info, f, indent=1)
    print(json.dumps(info, indent=1))


def _number_or_text(value: str):
    """An int, else a float, else the text itself (a `--model` field may be a name)."""
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    return value.strip()


def _overrides(flag: str, items, cast=float) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"{flag}: expected FIELD=VALUE, got {item!r}")
        out[key.strip()] = cast(value)
    return out


def train_static(args) -> None:
    from hairwarp.training.config import StaticTrainingConfig
    from hairwarp.training.data import TrainingSampler
    from hairwarp.training.static import StaticTrainer

    start = time.perf_counter()
    device = torch.device(args.device)
    data = data_config(args.long_hair_fraction, grown_hair_fraction=args.grown_hair_fraction)
    sampler = TrainingSampler(data, seed=args.seed, device=device)
    enc_s = precompute_latents(sampler, PHASE3_HAIRSTYLES, args.workers)
    print(f"encoded {PHASE3_HAIRSTYLES} corpus latents in {enc_s:.1f} s", flush=True)

    def config(steps):
        return StaticTrainingConfig(model_kind=args.kind, model_preset="shipped", phase_steps=steps,
                                    phase2_hairstyles=PHASE2_HAIRSTYLES,
                                    phase3_hairstyles=PHASE3_HAIRSTYLES, batch_size=args.batch,
                                    bp_schedule=args.bp_schedule, learning_rate=args.lr, bp_start=args.bp_start,
                                    loss_normalization=args.loss_normalization, grad_clip_norm=args.grad_clip_norm,
                                    energy=_overrides("--energy", args.energy),
                                    model=_overrides("--model", args.model, _number_or_text), checkpoint_every=0,
                                    data=data, curve_every=0, teacher_iterations=args.teacher_iterations,
                                    teacher_weight=args.teacher_weight, teacher_pool=args.teacher_pool,
                                    teacher_kind=args.teacher_kind, teacher_start=args.teacher_start,
                                    teacher_settle_time=args.teacher_settle_time,
                                    teacher_settle_time_step=args.teacher_settle_time_step)

    from hairwarp.evaluation.scenes import comparison_scene

    run = os.path.join(args.out, f"{args.kind}_run")
    if args.resume and os.path.isfile(os.path.join(run, "checkpoint.pt")):
        # Continue the run of an earlier call (same steps, schedule and batches): --minutes is
        # this call's budget.
        trainer = StaticTrainer(None, out=run, device=device, seed=args.seed, sampler=sampler, resume=run,
                                scene_factory=comparison_scene)
        print(f"resumed {run} at step {trainer.step} of {trainer.total_steps}", flush=True)
        _loop(trainer, args.minutes * 60 - 20, start, device)
        _finish(trainer, args, args.kind, {"phase_steps": list(trainer.config.phase_steps), "resumed": True,
                                          "batch": trainer.config.batch_size, "strand_stride": STRAND_STRIDE,
                                          "encode_s": enc_s}, start)
        return

    if args.steps:  # the probe overestimates: its hairstyles are all decoded for the first time
        s_step, total = float("nan"), args.steps
    else:
        # Phase-1 batches (one hairstyle, head rotations): the same sizes and energy as any step,
        # without the first decode of 32 new hairstyles per batch that made a phase-3 probe
        # 10x slower than a warm step (5.9 s against ~0.5 s measured on an H100).
        probe = StaticTrainer(config((0, 1000, 0, 0)), device=device, seed=args.seed, sampler=sampler)
        s_step = _time_steps(probe, 2, 5, device)
        del probe
        remaining = args.minutes * 60 - (time.perf_counter() - start) - 30
        total = max(20, int(remaining / s_step))
    if args.init:  # a fine-tune continues the curriculum's last phase (every motion, subject and shape)
        steps = (0, 0, 0, total)
    else:
        steps = tuple(int(round(total * share)) for share in PHASE_SHARES)
    print(f"probe: {s_step * 1e3:.0f} ms/step at batch {args.batch}; training {steps} steps", flush=True)
    if args.teachers_from and os.path.realpath(args.teachers_from).startswith(os.path.realpath(run)):
        raise SystemExit("--teachers-from: give another run's folder (this run's OUT/static_run is cleared at its start)")
    shutil.rmtree(run, ignore_errors=True)
    trainer = StaticTrainer(config(steps).replace(curve_every=args.curve_every, curve_scenes=args.curve_scenes.split(",")),
                            out=run, device=device, seed=args.seed, sampler=sampler, scene_factory=comparison_scene,
                            init=args.init or None, teachers_from=args.teachers_from)
    _loop(trainer, args.minutes * 60 - 20, start, device)
    _finish(trainer, args, args.kind, {"phase_steps": steps, "probe_ms_per_step": s_step * 1e3,
                                      "batch": args.batch, "strand_stride": STRAND_STRIDE,
                                      "encode_s": enc_s, "init": args.init}, start)


def train_dynamic(args) -> None:
    from hairwarp.training.config import DynamicTrainingConfig
    from hairwarp.training.data import TrainingSampler
    from hairwarp.training.dynamic import DynamicTrainer

    start = time.perf_counter()
    device = torch.device(args.device)
    # The dynamic data: the static run's sizes; --motions (repeat a name to draw it more often)
    # and --long-hair-fraction (share of the sequences given a long hairstyle) are the dynamic
    # run's own (both default to the shipped run's: every motion once, uniform hairstyles).
    motions = args.motions.split(",") if args.motions else None
    data = data_config(motions=motions, grown_hair_fraction=args.grown_hair_fraction)
    sampler = TrainingSampler(data, seed=args.seed, device=device)
    enc_s = precompute_latents(sampler, PHASE3_HAIRSTYLES, args.workers)
    print(f"encoded {PHASE3_HAIRSTYLES} corpus latents in {enc_s:.1f} s", flush=True)

    def config(steps):
        return DynamicTrainingConfig(static_checkpoint=args.static or "", model_preset="shipped", steps=steps,
                                     hairstyles=PHASE3_HAIRSTYLES, batch_size=args.batch, checkpoint_every=0,
                                     learning_rate=args.lr, grad_clip_norm=args.grad_clip_norm, data=data,
                                     long_hair_fraction=args.long_hair_fraction,
                                     model=_overrides("--model", args.model, _number_or_text))

    # The dynamic run has no schedule over its steps (one phase, constant b_p), so the
    # wall-clock budget alone ends it: no probe (a probe's first batches decode new hairstyles
    # and overestimated a warm step 6x on an H100: 1 650 against ~250 ms).
    s_step, total = float("nan"), (args.steps or DYNAMIC_OPEN_STEPS)
    print(f"training up to {total} steps within {args.minutes} minutes", flush=True)
    run = os.path.join(args.out, "dynamic_run")
    shutil.rmtree(run, ignore_errors=True)
    # --init: fine-tune the weights of a dynamic checkpoint (its own network config and frozen
    # static network; a fresh optimizer) instead of building a new network around --static.
    trainer = DynamicTrainer(config(total), out=run, device=device, seed=args.seed, sampler=sampler,
                             init=args.init or None)
    _loop(trainer, args.minutes * 60 - 20, start, device)
    _finish(trainer, args, "dynamic", {"steps": total, "probe_ms_per_step": s_step * 1e3, "batch": args.batch,
                                       "strand_stride": STRAND_STRIDE, "encode_s": enc_s, "init": args.init,
                                       "motions": data.motions, "long_hair_fraction": args.long_hair_fraction,
                                       "grown_hair_fraction": args.grown_hair_fraction},
            start)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("kind", choices=["static", "dynamic", "quaffure"])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--minutes", type=float, default=6.0, help="wall-clock budget, encoding included")
    parser.add_argument("--steps", type=int, default=0, help="total steps (0: from a timing probe and --minutes)")
    parser.add_argument("--batch", type=int, default=32)
    from hairwarp.training.config import (BP_SCHEDULES, LOSS_NORMALIZATIONS, TEACHER_KINDS, TEACHER_STARTS,
                                          StaticTrainingConfig)

    parser.add_argument("--bp-schedule", default=StaticTrainingConfig.bp_schedule, choices=BP_SCHEDULES,
                        help="static/quaffure: how b_p falls from 0.9 to 0.01 (geometric spends more steps "
                             "where the quadratic barrier's push-out force is strong)")
    parser.add_argument("--recipe", choices=sorted(RECIPES), default="shipped",
                        help="defaults of the flags below: 'shipped' (the recipe of the shipped checkpoint: "
                             "length projection, contact features, b_p 0.1 -> 0.01, inverse-energy weighting, "
                             "gradient clip 1, lr 2e-4 static / 3e-5 dynamic, 30 %% long hair) or 'paper' "
                             "(b_p 0.9 -> 0.01, lr 1e-4, no projection, no contact features, no clip)")
    parser.add_argument("--grad-clip-norm", type=float, default=None,
                        help="clip the gradient norm to this (0: off)")
    parser.add_argument("--loss-normalization", default=None,
                        choices=LOSS_NORMALIZATIONS,
                        help="static/quaffure: divide each sample's energy by its rigid placement's (rigid), "
                             "or weight it by 1 / (1 + |E|) (inverse)")
    parser.add_argument("--bp-start", type=float, default=None,
                        help="static/quaffure: b_p at the first step (0.9 in the paper; 0.01 = constant)")
    parser.add_argument("--energy", action="append", default=[], metavar="FIELD=VALUE",
                        help="override an EnergyConfig field in the training loss (repeatable), e.g. stretch_weight=1e10")
    parser.add_argument("--model", action="append", default=[], metavar="FIELD=VALUE",
                        help="static: override a network config field (repeatable), e.g. grid_height=16 "
                             "grid_width=16 length_projection=follow_the_leader")
    parser.add_argument("--long-hair-fraction", type=float, default=None,
                        help="static: share of phase-2/3 samples drawn from the pool's long hairstyles (>= 0.4 m); "
                             "dynamic: share of the sequences (default 0, the shipped dynamic run's)")
    parser.add_argument("--grown-hair-fraction", type=float, default=0.0,
                        help="share of the corpus hairstyles whose P_init are their strands grown around the rest "
                             "body (as the comparison scenes'), z their encoding, instead of decode(z) (default 0)")
    parser.add_argument("--motions", default=None,
                        help="dynamic: comma-separated procedural motions of the pool; a name repeated is drawn "
                             "that many times as often (default: every motion once)")
    parser.add_argument("--init", default=None,
                        help="dynamic: fine-tune this dynamic checkpoint (e.g. src/hairwarp/assets/"
                             "hairformer_dynamic.pt) with a fresh optimizer; --static is then not needed. "
                             "static: start from this checkpoint's static network (a dynamic checkpoint's "
                             "frozen one), every step in the curriculum's last phase")
    parser.add_argument("--lr", type=float, default=None, help="Adam step size")
    parser.add_argument("--teacher-iterations", type=int, default=StaticTrainingConfig.teacher_iterations,
                        help="static: distil from the physics, its static drape refining the network's in K "
                             "iterations per step (0: off)")
    parser.add_argument("--teacher-pool", type=int, default=StaticTrainingConfig.teacher_pool,
                        help="static: cycle through this many fixed batches, each one's teacher solved once to "
                             "convergence (up to --teacher-iterations) and kept (0: a K-iteration teacher per step)")
    parser.add_argument("--teacher-kind", default=StaticTrainingConfig.teacher_kind, choices=TEACHER_KINDS,
                        help="static: physics (the physics' static drape) or map (each sample's best deformation "
                             "map, which the network can reach)")
    parser.add_argument("--teacher-start", default=StaticTrainingConfig.teacher_start, choices=TEACHER_STARTS,
                        help="static: where the physics teacher's solve starts: the network's drape, the rigid "
                             "placement, or both with the lower energy per sample")
    parser.add_argument("--teacher-settle-time", type=float, default=StaticTrainingConfig.teacher_settle_time,
                        help="static, with --teacher-pool: hold each pool teacher's pose this long [s] of "
                             "implicit-Euler steps and polish it (the physics' drape at rest; 0: off)")
    parser.add_argument("--teacher-settle-time-step", type=float,
                        default=StaticTrainingConfig.teacher_settle_time_step,
                        help="static: the settling steps' time step [s]")
    parser.add_argument("--teachers-from", default=None,
                        help="static: take the pool's teachers another run solved (its OUT/static_run), same data, "
                             "seed, batch, pool and teacher settings: a variant of the run without solving them again")
    parser.add_argument("--teacher-weight", type=float, default=StaticTrainingConfig.teacher_weight,
                        help="static: weight of the distillation term [1/m^2]")
    parser.add_argument("--curve-every", type=int, default=250,
                        help="static/quaffure: learning curve every this many steps (0: off): "
                             "OUT/<kind>_run/learning_curve.json and .png")
    parser.add_argument("--curve-scenes", default="table1,short_rest,medium_rest,medium_poses",
                        help="held-out scenes of the curve")
    parser.add_argument("--resume", action="store_true",
                        help="static/quaffure: continue OUT/<kind>_run from its checkpoint (an earlier call's run)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2) - 2))
    parser.add_argument("--static", default=None, help="dynamic: the trained static checkpoint (float32 run file)")
    parser.add_argument("--out", default="hairwarp-train")
    args = parser.parse_args(argv)
    recipe = RECIPES[args.recipe]
    for name, value in recipe.items():
        if name == "model" and args.kind != "dynamic":  # a dynamic run takes its static's settings
            # Explicit --model wins; Quaffure's decoder reads no contact features.
            args.model = [f"{k}={v}" for k, v in value.items()
                          if not (args.kind == "quaffure" and k == "contact_samples")] + args.model
        elif name == "model":
            args.model = [f"{k}={v}" for k, v in RECIPES_DYNAMIC_MODEL[args.recipe].items()] + args.model
        elif name == "lr":
            args.lr = args.lr if args.lr is not None else value[args.kind == "dynamic"]
        elif name == "long_hair_fraction" and args.kind == "dynamic":
            args.long_hair_fraction = 0.0 if args.long_hair_fraction is None else args.long_hair_fraction
        elif getattr(args, name) is None:
            setattr(args, name, value)
    os.makedirs(args.out, exist_ok=True)
    if args.kind in ("static", "quaffure"):  # Quaffure (adapted): the static curriculum, Section 4.3.1
        if args.init and not os.path.isfile(args.init):
            raise SystemExit(f"--init: expected a checkpoint file, got {args.init!r}")
        train_static(args)
    else:
        if args.init:
            if not os.path.isfile(args.init):
                raise SystemExit(f"--init: expected a dynamic checkpoint file, got {args.init!r}")
        elif not args.static or not os.path.isfile(args.static):
            raise SystemExit(f"--static: expected the static checkpoint file, got {args.static!r}")
        train_dynamic(args)


if __name__ == "__main__":
    main()
