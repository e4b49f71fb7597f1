"""`hairwarp bench energy`: the energy benchmark (Warp vs plain torch)."""

from __future__ import annotations

import os


def add_parser(subparsers) -> None:
    from hairwarp.commands.common import add_common_arguments

    p = subparsers.add_parser("bench", help="benchmarks: `hairwarp bench energy`",
                              description="Benchmarks that print and save figures.")
    sub = p.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    e = sub.add_parser("energy", help="forward+backward of every loss term and the total, Warp vs plain torch",
                       description="Times forward+backward of each term of Eq. 5/6 and of the total at the "
                                   "paper's sizes (1024 strands x 100 vertices, default body), Warp vs plain torch.")
    add_common_arguments(e)
    e.add_argument("--json", default=None, help="write the results JSON here (default: OUT/bench_energy.json)")
    e.add_argument("--batch", default="1,32", help="comma-separated batch sizes (default: 1,32)")
    e.add_argument("--terms", default=None, help="comma-separated subset of terms (default: all, and total)")
    e.set_defaults(run=run_energy)


def run_energy(args) -> int:
    import torch

    from hairwarp.bench.energy import markdown_table, run_energy_benchmark, write_json
    from hairwarp.runtime import resolve_device

    device = resolve_device(args.device, argument="--device")
    torch.manual_seed(args.seed)
    try:
        batches = tuple(int(b) for b in args.batch.split(","))
    except ValueError:
        raise ValueError(f"--batch: expected comma-separated integers, got {args.batch!r}") from None
    if any(b < 1 for b in batches):
        raise ValueError(f"--batch: batch sizes must be >= 1, got {args.batch!r}")
    names = None if args.terms is None else set(args.terms.split(","))
    record = run_energy_benchmark(device, batches, names=names)
    path = args.json or os.path.join(args.out, "bench_energy.json")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_json(record, path)
    table = markdown_table(record)
    with open(os.path.splitext(path)[0] + ".md", "w") as f:
        f.write(table + "\n")
    print(table)
    print(f"wrote {path}")
    return 0
