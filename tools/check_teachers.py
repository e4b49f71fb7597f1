"""How far the distillation teachers move a static network's drapes, and whether they stay out of the body.

Builds a few pool batches of the shipped recipe's data (phase 3), solves each one's teacher
(`StaticTrainingConfig.teacher_kind` "map" and "physics") from the network's drape, and prints
and saves, per sample, the energy of the network's drape and of the teacher's, their share of
vertices inside the body, and the RMS distance between them:

    OMP_NUM_THREADS=2 python3 tools/check_teachers.py --out OUT     (256 strands, 2-core CPU: ~2 min)
    python3 tools/check_teachers.py --kinds physics --teacher-start rigid --settle-time 1 --out OUT
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> None:
    import train_shipped as ts

    from hairwarp.energy import total_energy
    from hairwarp.methods.networks import shipped_checkpoint
    from hairwarp.metrics import penetration_percent
    from hairwarp.training.config import StaticTrainingConfig, energy_config
    from hairwarp.training.data import TrainingSampler
    from hairwarp.training.static import StaticTrainer, static_loss

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", default=None, help="network to start from (default: the shipped one)")
    parser.add_argument("--batches", type=int, default=2)
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--map-iterations", type=int, default=150)
    parser.add_argument("--physics-iterations", type=int, default=800)
    parser.add_argument("--kinds", default="map,physics", help="teacher kinds to solve")
    parser.add_argument("--teacher-start", default="network", help="the physics teacher's start")
    parser.add_argument("--settle-time", type=float, default=0.0,
                        help="hold each physics teacher's pose this long [s] and polish it (0: off)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="check_teachers_out")
    args = parser.parse_args(argv)
    checkpoint = args.checkpoint or shipped_checkpoint("hairformer_dynamic.pt")
    model = ts._overrides("--model", [f"{k}={v}" for k, v in ts.RECIPES["shipped"]["model"].items()],
                          ts._number_or_text)
    data = ts.data_config(0.3)
    out = {"command": " ".join(sys.argv), "checkpoint": checkpoint, "samples": {}}
    iterations_of = {"map": args.map_iterations, "physics": args.physics_iterations}
    for kind in args.kinds.split(","):
        iterations = iterations_of[kind]
        physics_only = dict(teacher_start=args.teacher_start, teacher_settle_time=args.settle_time) \
            if kind == "physics" else {}
        cfg = StaticTrainingConfig(model_kind="static", model_preset="shipped", model=model, data=data,
                                   batch_size=args.batch, phase_steps=(0, 0, 0, args.batches), phase3_hairstyles=16,
                                   teacher_iterations=iterations, teacher_pool=args.batches, teacher_kind=kind,
                                   bp_start=0.01, loss_normalization="inverse", curve_every=0, **physics_only)
        sampler = TrainingSampler(data, seed=args.seed, device=args.device)
        trainer = StaticTrainer(cfg, sampler=sampler, device=args.device, init=checkpoint)
        physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
        for step in range(args.batches):
            start = time.perf_counter()
            batch = trainer.training_batch(step)
            with torch.no_grad():
                _, _, drape = static_loss(trainer.model, batch, physics)
                e_network = total_energy(drape, batch.inputs, physics).total
                e_teacher = total_energy(batch.teacher, batch.inputs, physics).total
            body = batch.inputs.body
            row = {"seconds": time.perf_counter() - start, "energy_network_J": e_network.tolist(),
                   "energy_teacher_J": e_teacher.tolist(),
                   "inside_rigid_percent": penetration_percent(batch.rigid, body).tolist(),
                   "inside_network_percent": penetration_percent(drape, body).tolist(),
                   "inside_teacher_percent": penetration_percent(batch.teacher, body).tolist(),
                   "rms_teacher_to_network_mm": float(((batch.teacher - drape) ** 2).sum(-1).mean().sqrt() * 1e3),
                   # mean tip height below the rigid placement's [mm] (+: lower)
                   "tip_drop_network_mm": _tip_drop(batch.rigid, drape),
                   "tip_drop_teacher_mm": _tip_drop(batch.rigid, batch.teacher)}
            out["samples"][f"{kind}_{step}"] = row
            print(kind, step, json.dumps(row), flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "check_teachers.json"), "w") as f:
        json.dump(out, f, indent=1)


def _tip_drop(rigid: torch.Tensor, x: torch.Tensor) -> list[float]:
    """Per sample, the tips' mean height below the rigid placement's [mm]."""
    return ((rigid[..., -1, 1] - x[..., -1, 1]).mean(dim=-1) * 1e3).tolist()


if __name__ == "__main__":
    main()
