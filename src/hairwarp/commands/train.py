"""`hairwarp train static|dynamic|quaffure`: train a network (HairFormer Section 4.2).

    hairwarp train static  --config cfg.toml --set batch_size=8 --set data.strand_stride=4 --out run/
    hairwarp train dynamic --static-checkpoint run/checkpoint.pt --out dyn/
    hairwarp train quaffure --out quaffure/
    hairwarp train static --resume run/            # continue where the run stopped
    torchrun --nproc_per_node 2 --no-python hairwarp train static --device cuda --out run/

The output folder receives config.toml (the full settings: `--config` it to repeat the run),
log.jsonl (one JSON record per step: loss, per-term breakdown, phase, b_p) and checkpoint.pt.
Under torchrun the ranks train data-parallel (DDP): batch_size is the global batch, each rank
builds its share, rank 0 writes the files; --resume takes a checkpoint of any world size
(docs/distributed.md).
"""

from __future__ import annotations

import argparse
import os

_KINDS = ("static", "dynamic", "quaffure")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register `hairwarp train`."""
    from hairwarp.commands.common import add_common_arguments

    parser = subparsers.add_parser(
        "train",
        help="train a static, dynamic or Quaffure network",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
    )
    parser.add_argument("kind", choices=_KINDS, help="which network to train")
    add_training_arguments(parser)
    parser.add_argument("--static-checkpoint", default=None,
                        help="dynamic: the trained static network (sets static_checkpoint)")
    parser.add_argument("--resume", default=None, help="continue from this checkpoint (file or run folder)")
    parser.add_argument("--steps", type=int, default=None,
                        help="run at most this many steps now (default: to the end of the schedule)")
    add_common_arguments(parser, out_default="hairwarp-train")
    parser.set_defaults(run=run)
    return parser


def add_training_arguments(parser: argparse.ArgumentParser) -> None:
    """--config, --set and --no-progress (shared with `hairwarp finetune`)."""
    parser.add_argument("--config", default=None,
                        help="TOML file of settings (fields of the training config)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help="override a setting, dotted keys for tables (e.g. data.num_vertices=20); "
                             "repeatable")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _summary(trainer, out: str) -> str:
    last = trainer.history[-1] if trainer.history else None
    loss = f", last loss {last['loss']:.6g}" if last else ""
    path = os.path.join(out, "checkpoint.pt")
    return f"{trainer.kind}: {trainer.step}/{trainer.total_steps} steps{loss}; checkpoint {path}"


def run(args) -> int:
    """Train as asked; print one summary line."""
    from hairwarp.runtime import resolve_device
    from hairwarp.training._common import checkpoint_config
    from hairwarp.training.config import apply_overrides, load_config
    from hairwarp.training.distributed import init_distributed
    from hairwarp.training.dynamic import DynamicTrainer
    from hairwarp.training.static import StaticTrainer

    device = resolve_device(args.device, argument="--device")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps: expected a positive int, got {args.steps}")
    if args.config is not None and not os.path.isfile(args.config):
        raise FileNotFoundError(f"--config: no such file {args.config}")
    overrides = list(args.overrides)
    if args.static_checkpoint is not None:
        if args.kind != "dynamic":
            raise ValueError("--static-checkpoint: only for train dynamic")
        overrides.append(f"static_checkpoint={_quoted(args.static_checkpoint)}")
    if args.resume is not None and args.config is None:
        # The checkpoint's own settings, with the --set overrides on top.
        config = apply_overrides(checkpoint_config(args.resume, args.kind), overrides)
    else:
        config = load_config(args.config, args.kind, overrides)
    cls = DynamicTrainer if args.kind == "dynamic" else StaticTrainer
    # Under torchrun: join the data-parallel run (each rank on its device); else one process.
    ctx = init_distributed(device)
    extra = {}
    if cls is StaticTrainer:  # the learning curve scores the held-out comparison scenes
        from hairwarp.evaluation.scenes import comparison_scene

        extra["scene_factory"] = comparison_scene
    trainer = cls(config, out=args.out, device=ctx.device, seed=args.seed, rank=ctx.rank,
                  world_size=ctx.world_size, resume=args.resume, **extra)
    if trainer.kind != args.kind:
        raise ValueError(f"--resume: the checkpoint trains a {trainer.kind} network, not {args.kind}")
    try:
        trainer.train(args.steps, progress=not args.no_progress)
    finally:
        trainer.close()
    if ctx.is_main:
        print(_summary(trainer, args.out))
    return 0


def _quoted(text: str) -> str:
    import json

    return json.dumps(os.fspath(text))
