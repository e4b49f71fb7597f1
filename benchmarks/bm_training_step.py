"""Static training steps replayed from a CUDA graph against eager ones (docs/contact.md 16).

    python3 benchmarks/bm_training_step.py --device cuda --batch 32,8 --out OUT

The shipped run's sizes (256 x 100 hair, the `shipped` network with 16 contact samples, the
`inverse` loss, gradient clipping), phase 3 (every motion and subject, noisy shapes) with a pool
of `--hairstyles` hairstyles decoded before timing. For each batch size, trainers with
`cuda_graph` off and on alternate (`--rounds` each), starting from the same weights and drawing
the same batches; each times `--steps` steps (`train_step`: the batch, the network, the Warp
energies, backward, Adam), synchronised, and reports the median and minimum of all but the first
`--warmup` and the first step (the capture), with every step's loss. Writes OUT/training_step.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="cuda (the graph needs it) or cpu (both eager)")
    parser.add_argument("--batch", default="32,8", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=24, help="timed steps per trainer")
    parser.add_argument("--warmup", type=int, default=4, help="steps left out of the statistics")
    parser.add_argument("--rounds", type=int, default=2, help="trainers per mode, in alternation")
    parser.add_argument("--hairstyles", type=int, default=8, help="the phase-3 hairstyle pool")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="hairwarp-out")
    return parser


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    from tqdm.auto import tqdm

    from hairwarp.training.config import DataConfig, StaticTrainingConfig
    from hairwarp.training.data import TrainingSampler
    from hairwarp.training.static import StaticTrainer

    device = torch.device(args.device)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    data = DataConfig(strand_stride=2, hairstyle_cache_size=args.hairstyles, long_hair_fraction=0.3)
    sampler = TrainingSampler(data, seed=args.seed, device=device)
    for index in tqdm(range(args.hairstyles), desc="decoding hairstyles"):
        sampler.latent(index)
    record = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "torch": torch.__version__, "args": vars(args)}
    for batch_size in (int(b) for b in args.batch.split(",")):
        row = {"eager": [], "graph": []}
        for graph in [False, True] * args.rounds:
            config = StaticTrainingConfig(
                model_kind="static", model_preset="shipped", phase_steps=(0, 0, 0, 100_000),
                phase2_hairstyles=args.hairstyles, phase3_hairstyles=args.hairstyles, batch_size=batch_size,
                loss_normalization="inverse", grad_clip_norm=1.0, learning_rate=2e-4, bp_start=0.1,
                model={"length_projection": "follow_the_leader", "contact_samples": 16}, checkpoint_every=0,
                data=data, curve_every=0, cuda_graph=graph)
            torch.manual_seed(args.seed)
            trainer = StaticTrainer(config, device=device, seed=args.seed, sampler=sampler)
            times, losses = [], []
            for _ in tqdm(range(args.steps), desc=f"batch {batch_size} {'graph' if graph else 'eager'}"):
                sync()
                start = time.perf_counter()
                losses.append(trainer.train_step()["loss"])
                sync()
                times.append(time.perf_counter() - start)
            kept = times[max(args.warmup, 1):]
            row["graph" if graph else "eager"].append({
                "median_ms": round(1e3 * statistics.median(kept), 2), "min_ms": round(1e3 * min(kept), 2),
                "first_ms": round(1e3 * times[0], 1), "losses": losses})
            del trainer
        record[f"batch {batch_size}"] = row
        for mode in ("eager", "graph"):
            runs = row[mode]
            print(f"batch {batch_size:3d} {mode:5s}: median " + " / ".join(f"{r['median_ms']:.1f}" for r in runs)
                  + " ms, min " + " / ".join(f"{r['min_ms']:.1f}" for r in runs)
                  + " ms, first step " + " / ".join(f"{r['first_ms']:.0f}" for r in runs) + " ms")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "training_step.json"), "w") as f:
        json.dump(record, f, indent=1)
    return record


if __name__ == "__main__":
    main()
