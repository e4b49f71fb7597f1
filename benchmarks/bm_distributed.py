"""Samples/s of static and dynamic training on K ranks (DDP), for the scaling efficiency.

One measurement, K ranks (run under torchrun; rank 0 writes OUT/ddp_K.json):

    torchrun --standalone --nproc_per_node K benchmarks/bm_distributed.py --out OUT --device cuda

Several K in a row (this script starts torchrun for each, with NVLink multicast off, then
writes OUT/summary.json with efficiency_K = samples/s at K / (K x samples/s at 1)):

    python3 benchmarks/bm_distributed.py --launch 1,2 --out OUT --device cuda

Weak scaling: each rank holds --per-rank-batch samples (sequences for dynamic), so the global
batch is K times that. Static: phase-3 batches (every motion and subject, noisy shapes: the
sampler's full cost), the deformation clip on (a fresh network trained from phase 3 on would
otherwise push hair deep into the body). Dynamic: W + R frames per sequence on an untrained
static network. The hairstyle pool is decoded before timing; each timed step is the batch
(`next_batch`: posing, Eq. 1, body meshes) plus `train_step` (network, Warp energies,
backward, all-reduce, Adam), timed on rank 0 between synchronisations; samples/s counts the
global batch over the slowest rank's time.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import torch

# NVLink multicast stays off (NCCL, torch symmetric memory, NVSHMEM): see the device notes.
_MULTICAST_OFF = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for ddp_K.json (and summary.json)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--kind", choices=("static", "dynamic", "both"), default="both")
    parser.add_argument("--preset", choices=("paper", "shipped", "tiny"), default="shipped",
                        help="network sizes (default: shipped)")
    parser.add_argument("--per-rank-batch", type=int, default=8, help="static samples per rank per step")
    parser.add_argument("--per-rank-sequences", type=int, default=2, help="dynamic sequences per rank per step")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per kind")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first (Warp compiles, caches)")
    parser.add_argument("--strand-stride", type=int, default=1, help="1: all 1024 strands; 4: 64")
    parser.add_argument("--num-vertices", type=int, default=100, help="vertices per strand")
    parser.add_argument("--hairstyles", type=int, default=16, help="hairstyle pool (decoded before timing)")
    parser.add_argument("--launch", default=None,
                        help="comma-separated K: run torchrun --nproc_per_node K for each, then summarise")
    return parser


def _check(args) -> None:
    for name in ("per_rank_batch", "per_rank_sequences", "steps", "hairstyles", "strand_stride", "num_vertices"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive int, got {getattr(args, name)}")
    if args.warmup < 1:
        raise ValueError(f"--warmup: expected >= 1 (the first step compiles), got {args.warmup}")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_steps(trainer, steps: int, warmup: int) -> dict:
    """Run warmup + steps optimizer steps; per-step batch and train times of this rank [s]."""
    from hairwarp.training import distributed

    data_s, step_s, total = [], [], 0.0
    for i in range(warmup + steps):
        if i == warmup:
            distributed.barrier(trainer.device)  # every rank starts the timed steps together
            _sync(trainer.device)
            begin = time.perf_counter()
        t0 = time.perf_counter()
        batch = trainer.next_batch(trainer.step)
        _sync(trainer.device)
        t1 = time.perf_counter()
        record = trainer.train_step(batch)
        _sync(trainer.device)
        t2 = time.perf_counter()
        if i >= warmup:
            data_s.append(t1 - t0)
            step_s.append(t2 - t1)
    total = time.perf_counter() - begin
    return {"elapsed_s": total, "data_s": data_s, "step_s": step_s, "last_loss": record["loss"]}


def _summarise(kind: str, timing: dict, ctx, global_batch: int, steps: int, frames: int) -> dict:
    from hairwarp.training import distributed

    elapsed = timing["elapsed_s"]
    if ctx.is_distributed:  # the slowest rank sets the pace
        elapsed = max(distributed.all_reduce_sum(
            [elapsed if r == ctx.rank else 0.0 for r in range(ctx.world_size)], ctx.device))
    samples = global_batch * steps
    return {
        "kind": kind,
        "global_batch": global_batch,
        "frames_per_sample": frames,
        "timed_steps": steps,
        "elapsed_s": elapsed,
        "samples_per_s": samples / elapsed,
        "frames_per_s": samples * frames / elapsed,
        "rank0_batch_ms_median": 1e3 * statistics.median(timing["data_s"]),
        "rank0_train_step_ms_median": 1e3 * statistics.median(timing["step_s"]),
        "last_loss": timing["last_loss"],
    }


def measure(args) -> dict | None:
    """The worker: K = WORLD_SIZE ranks (1 without torchrun). Returns the result on rank 0."""
    from hairwarp.models import StaticNetwork, save_checkpoint
    from hairwarp.training import DataConfig, DynamicTrainer, DynamicTrainingConfig, StaticTrainer
    from hairwarp.training import StaticTrainingConfig, distributed
    from hairwarp.training.static import model_config

    _check(args)
    ctx = distributed.init_distributed(args.device)
    k = ctx.world_size
    if ctx.device.type == "cpu":
        # One thread per rank: K ranks use K cores, so K = 1 and K = 2 compare like for like
        # (and no OpenMP spin-waiting against the other rank).
        torch.set_num_threads(1)
    data = DataConfig(strand_stride=args.strand_stride, num_vertices=args.num_vertices)
    total = args.warmup + args.steps
    results = {}
    static_cfg = StaticTrainingConfig(
        model_preset=args.preset, phase_steps=(0, 0, 0, total), phase3_hairstyles=args.hairstyles,
        batch_size=args.per_rank_batch * k, clip_steps=total, checkpoint_every=0, data=data,
    )
    trainer = StaticTrainer(static_cfg, device=ctx.device, rank=ctx.rank, world_size=k)
    trainer.sampler.hairstyles(list(range(args.hairstyles)))  # the corpus pool, decoded once
    if args.kind in ("static", "both"):
        timing = _time_steps(trainer, args.steps, args.warmup)
        results["static"] = _summarise("static", timing, ctx, static_cfg.batch_size, args.steps, 1)
    if args.kind in ("dynamic", "both"):
        # Beside the results would send a large file back with them: the host's temp folder
        # (one host: every rank reads rank 0's file).
        path = os.path.join(tempfile.gettempdir(), f"hairwarp_bm_static_init_{k}.pt")
        if ctx.is_main:  # an untrained static network: speed does not depend on its weights
            torch.manual_seed(0)
            save_checkpoint(path, StaticNetwork(model_config(static_cfg, trainer.sampler.latent_dim)))
        distributed.barrier(ctx.device)
        dyn_cfg = DynamicTrainingConfig(
            static_checkpoint=path, model_preset=args.preset, steps=total, hairstyles=args.hairstyles,
            batch_size=args.per_rank_sequences * k, dynamic_candidates=100, checkpoint_every=0, data=data,
        )
        dyn = DynamicTrainer(dyn_cfg, device=ctx.device, rank=ctx.rank, world_size=k)
        dyn.sampler.hairstyles(list(range(args.hairstyles)))
        timing = _time_steps(dyn, args.steps, args.warmup)
        results["dynamic"] = _summarise("dynamic", timing, ctx, dyn_cfg.batch_size, args.steps,
                                        dyn_cfg.rollout_frames)
    if not ctx.is_main:
        return None
    import warp as wp

    device_name = torch.cuda.get_device_name(ctx.device) if ctx.device.type == "cuda" else platform.processor()
    report = {
        "world_size": k, "backend": ctx.backend, "device": device_name, "torch": torch.__version__,
        "warp": wp.__version__, "preset": args.preset, "strands": data.num_strands,
        "vertices": data.num_vertices, "per_rank_batch": args.per_rank_batch,
        "per_rank_sequences": args.per_rank_sequences, "warmup": args.warmup, "hairstyles": args.hairstyles,
        "nccl_nvls_enable": os.environ.get("NCCL_NVLS_ENABLE"), "results": results,
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, f"ddp_{k}.json"), "w", encoding="utf-8") as f:
        json.dump(report, f, indent=1)
    for kind, r in results.items():
        print(f"K={k} {kind}: {r['samples_per_s']:.2f} samples/s (global batch {r['global_batch']}, "
              f"{r['timed_steps']} steps in {r['elapsed_s']:.2f} s; rank 0 batch "
              f"{r['rank0_batch_ms_median']:.1f} ms + train step {r['rank0_train_step_ms_median']:.1f} ms)",
              flush=True)
    return report


def launch(args, argv) -> dict:
    """Run torchrun for each K of --launch in turn; write OUT/summary.json."""
    counts = [int(x) for x in args.launch.split(",") if x.strip()]
    if not counts or min(counts) < 1:
        raise ValueError(f"--launch: expected comma-separated positive ints, got {args.launch!r}")
    forwarded, skip = [], False
    for i, a in enumerate(argv):  # the same arguments, without --launch
        if skip:
            skip = False
            continue
        if a == "--launch":
            skip = True
            continue
        if a.startswith("--launch="):
            continue
        forwarded.append(a)
    env = {**os.environ, **_MULTICAST_OFF, "PYTHONUNBUFFERED": "1"}
    reports = {}
    for k in counts:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(k),
               os.path.abspath(__file__), *forwarded]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, env=env, check=True)
        with open(os.path.join(args.out, f"ddp_{k}.json"), encoding="utf-8") as f:
            reports[k] = json.load(f)
    summary = {"runs": {str(k): r for k, r in reports.items()}, "scaling": {}}
    base = reports.get(1)
    for kind in ("static", "dynamic"):
        rows = {}
        for k, r in reports.items():
            if kind not in r["results"]:
                continue
            sps = r["results"][kind]["samples_per_s"]
            row = {"samples_per_s": sps}
            if base is not None and kind in base["results"]:
                row["speedup"] = sps / base["results"][kind]["samples_per_s"]
                row["efficiency"] = row["speedup"] / k
            rows[str(k)] = row
        if rows:
            summary["scaling"][kind] = rows
    with open(os.path.join(args.out, "summary.json"), "w", encoding="utf-8") as f:
        json.dump(summary, f, indent=1)
    for kind, rows in summary["scaling"].items():
        for k, row in rows.items():
            extra = f", speedup {row['speedup']:.2f}, efficiency {100 * row['efficiency']:.0f}%" if "speedup" in row else ""
            print(f"{kind} K={k}: {row['samples_per_s']:.2f} samples/s{extra}")
    return summary


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    _check(args)
    if args.launch is not None:
        launch(args, argv)
    else:
        measure(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
