"""The `hairwarp` command line.

Each subcommand lives beside the code it drives and registers itself here through
`add_parser(subparsers)` / `run(args)`. Errors are one line naming the bad argument or file,
exit status 2 (usage) or 1 (failure); `--debug` shows the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> module that defines add_parser(subparsers) and run(args)
_COMMANDS = {
    "demo": "hairwarp.commands.demo",
    "drape": "hairwarp.commands.drape",
    "simulate": "hairwarp.commands.simulate",
    "bench": "hairwarp.commands.bench",
    "train": "hairwarp.commands.train",
    "finetune": "hairwarp.commands.finetune",
    "compare": "hairwarp.commands.compare",
    "export": "hairwarp.commands.export",
}


def _available_commands():
    found = {}
    for name, module in _COMMANDS.items():
        try:
            found[name] = importlib.import_module(module)
        except ModuleNotFoundError as exc:  # a command whose module is not part of this build
            if exc.name != module:
                raise
    return found


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hairwarp",
        description="Differentiable hair physics (NVIDIA Warp + PyTorch) and the HairFormer neural hair simulator.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in _available_commands().items():
        module.add_parser(sub)
    return parser


def add_common_arguments(parser: argparse.ArgumentParser, *, out_default: str = "hairwarp-out") -> None:
    """The flags every command shares: --device, --seed, --out."""
    parser.add_argument("--device", default="cpu", help="torch device: cpu or cuda[:N] (default: cpu)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--out", default=out_default, help=f"output folder (default: ./{out_default}/)")


def resolve_device(name: str):
    """A torch device from a --device string, with a clear error when it is unavailable."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"--device: {exc}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device: cuda was asked for but this machine has no CUDA device")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"--device: expected cpu or cuda, got {name}")
    return device


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.run(args) or 0)
    except (ValueError, FileNotFoundError, OSError) as exc:
        if args.debug:
            raise
        print(f"hairwarp {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
