"""How large a settling step a static-training teacher can take: one pool batch's teacher (the
static solve from the rigid placement) settled with its pose held (`drape_at_rest`) for the same
time at several time steps; prints and saves each one's energy, tips' drop and cost.

    OMP_NUM_THREADS=2 python3 tools/teacher_settle_steps.py --step 1 --out OUT   (2-core CPU: ~8 min)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> None:
    import train_shipped as ts
    from check_teachers import _tip_drop

    from hairwarp.energy import total_energy
    from hairwarp.methods.networks import shipped_checkpoint
    from hairwarp.solvers.physics import PhysicsSolver, drape_at_rest, settling_solver
    from hairwarp.training.config import StaticTrainingConfig, energy_config
    from hairwarp.training.data import TrainingSampler
    from hairwarp.training.static import StaticTrainer

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--step", type=int, default=1, help="the pool batch (phase 3)")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--time-steps", default="0.016667,0.05,0.1", help="settling time steps [s]")
    parser.add_argument("--settle-time", type=float, default=1.0, help="[s]")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="teacher_settle_steps_out")
    args = parser.parse_args(argv)
    model = ts._overrides("--model", [f"{k}={v}" for k, v in ts.RECIPES["shipped"]["model"].items()],
                          ts._number_or_text)
    data = ts.data_config(0.3)
    cfg = StaticTrainingConfig(model_kind="static", model_preset="shipped", model=model, data=data,
                               batch_size=args.batch, phase_steps=(0, 0, 0, args.step + 1), phase3_hairstyles=16,
                               teacher_iterations=800, teacher_pool=args.step + 1, teacher_start="rigid",
                               bp_start=0.01, loss_normalization="inverse", curve_every=0)
    trainer = StaticTrainer(cfg, sampler=TrainingSampler(data, seed=args.seed, device=args.device),
                            device=args.device, init=shipped_checkpoint("hairformer_dynamic.pt"))
    batch = trainer.training_batch(args.step)  # its teacher: the static solve alone
    solver = trainer._teacher.solver or trainer._teacher._make_solver(batch, batch.inputs.body)
    physics = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
    x0 = batch.teacher.detach().clone()
    out = {"command": " ".join(sys.argv), "static_solve": {"energy_J": total_energy(x0, batch.inputs, physics)
                                                           .total.tolist()}}
    print("static solve", out["static_solve"], flush=True)
    for dt in (float(v) for v in args.time_steps.split(",")):
        config = replace(solver.config, settle_time=args.settle_time)
        energy = solver.energy_config.replace(time_step=dt)
        common = (solver.inputs.rest_lengths, solver.rigid, solver.normals, solver.body, energy)
        static = PhysicsSolver(*common, config, dynamic=False)
        dynamic = settling_solver(*common, config)
        t0 = time.perf_counter()
        drape = drape_at_rest(static, dynamic, x0, config)
        row = {"seconds": time.perf_counter() - t0, "settle_steps": drape.settle_steps,
               "iterations": drape.report.iterations,
               "energy_J": total_energy(drape.positions, batch.inputs, physics).total.tolist(),
               "tip_drop_mm": _tip_drop(batch.rigid, drape.positions)}
        out[f"time_step={dt:g}"] = row
        print(f"time_step={dt:g}", json.dumps(row), flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "teacher_settle_steps.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
