"""`hairwarp bench energy`: the energy benchmark (Warp vs plain torch)."""

from __future__ import annotations

import argparse
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
    e.add_argument("--torch-compile", action=argparse.BooleanOptionalAction, default=True,
                   help="also time each plain-torch energy through torch.compile (inductor, dynamic=False; on the "
                        "CPU it needs a C++ compiler, and compiling takes seconds per term; a term that does not "
                        "compile shows n/a and its reason in the JSON) (default: on)")
    e.add_argument("--strand-stride", type=int, default=1,
                   help="keep every k-th strand (1: the paper's 1024)")
    e.add_argument("--vertices", type=int, default=100, help="vertices per strand (100: the paper's)")
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
    if args.strand_stride < 1:
        raise ValueError(f"--strand-stride: expected a positive int, got {args.strand_stride}")
    if args.vertices < 3:
        raise ValueError(f"--vertices: expected >= 3, got {args.vertices}")
    record = run_energy_benchmark(device, batches, names=names, torch_compile=args.torch_compile,
                                  strand_stride=args.strand_stride, num_vertices=args.vertices)
    path = args.json or os.path.join(args.out, "bench_energy.json")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_json(record, path)
    table = markdown_table(record)
    with open(os.path.splitext(path)[0] + ".md", "w") as f:
        f.write(table + "\n")
    print(table)
    print(f"wrote {path}")
    return 0
