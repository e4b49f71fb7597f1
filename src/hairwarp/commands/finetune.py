"""`hairwarp finetune`: fine-tune a dynamic network on one hard motion (HairFormer Fig. 4).

    hairwarp finetune --checkpoint dyn/checkpoint.pt --motion whiplash --iterations 300 --out whiplash/
    hairwarp finetune --checkpoint dyn/ --motion my_motion.npz --set learning_rate=5e-5

The checkpoint must come from `hairwarp train dynamic` (it stores the data settings). The output
folder receives config.toml, log.jsonl and the fine-tuned checkpoint.pt. Under torchrun the
ranks fine-tune data-parallel, as `hairwarp train` does (docs/distributed.md).
"""

from __future__ import annotations

import argparse
import os


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register `hairwarp finetune`."""
    from hairwarp.commands.common import add_common_arguments
    from hairwarp.commands.train import add_training_arguments

    parser = subparsers.add_parser(
        "finetune",
        help="fine-tune a dynamic network on one motion (whiplash)",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
    )
    parser.add_argument("--checkpoint", required=True, help="dynamic checkpoint (file or run folder)")
    parser.add_argument("--motion", default="whiplash",
                        help="procedural motion name or AMASS .npz file (default: whiplash)")
    parser.add_argument("--iterations", type=int, default=300, help="optimizer steps (default: 300)")
    add_training_arguments(parser)
    add_common_arguments(parser, out_default="hairwarp-finetune")
    parser.set_defaults(run=run)
    return parser


def run(args) -> int:
    """Fine-tune as asked; print one summary line."""
    from hairwarp.runtime import resolve_device
    from hairwarp.training.config import load_config
    from hairwarp.training.finetune import finetune

    device = resolve_device(args.device, argument="--device")
    if args.iterations < 1:
        raise ValueError(f"--iterations: expected a positive int, got {args.iterations}")
    overrides = list(args.overrides)
    if args.config is not None:
        # A file's settings become overrides on top of the checkpoint's (only those it sets).
        import tomllib

        if not os.path.isfile(args.config):
            raise FileNotFoundError(f"--config: no such file {args.config}")
        load_config(args.config, "dynamic")  # validates the file, naming a bad setting
        with open(args.config, "rb") as f:
            overrides = _flatten(tomllib.load(f)) + overrides
    trainer = finetune(args.checkpoint, args.motion, args.iterations, out=args.out, device=device,
                       seed=args.seed, overrides=overrides, progress=not args.no_progress)
    if not trainer.is_main:  # under torchrun rank 0 reports
        return 0
    last = trainer.history[-1]["loss"] if trainer.history else float("nan")
    print(f"finetune {args.motion}: {trainer.step} steps, last loss {last:.6g}; "
          f"checkpoint {os.path.join(args.out, 'checkpoint.pt')}")
    return 0


def _flatten(table: dict, prefix: str = "") -> list[str]:
    import json

    items = []
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            items += _flatten(value, name + ".")
        else:
            items.append(f"{name}={json.dumps(value)}")
    return items
