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
    """The `hairwarp` parser with every subcommand this build has."""
    parser = argparse.ArgumentParser(
        prog="hairwarp",
        description="Differentiable hair physics (NVIDIA Warp + PyTorch) and the HairFormer neural hair simulator.",
        epilog="Every command takes --help, --device, --seed and --out. Methods: `hairwarp drape --help`.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in _available_commands().items():
        module.add_parser(sub)
    return parser


def _as_flag(message: str, args) -> str:
    """A library error that names an argument ("strand_stride: ...") named as its flag ("--strand-stride: ...")."""
    name, sep, rest = message.partition(":")
    if sep and name.isidentifier() and hasattr(args, name):
        return f"--{name.replace('_', '-')}:{rest}"
    return message


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 failure, 2 usage, 130 interrupted)."""
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
        print(f"hairwarp {args.command}: error: {_as_flag(str(exc), args)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
