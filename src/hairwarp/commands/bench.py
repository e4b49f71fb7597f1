"""`hairwarp bench energy`: the energy benchmark (Warp vs plain torch)."""

from __future__ import annotations

import argparse
import os

# What `--full` costs on this project's 2-core CPU (a complete run at the paper's sizes on an idle
# machine, measured; docs/energy_cpu.md): quoted by --help.
FULL_CPU_TIME = "26 min 28 s"


def add_parser(subparsers) -> None:
    from hairwarp.bench.energy import CPU_SIZES, FULL_SIZES
    from hairwarp.commands.common import add_common_arguments

    def batches(sizes):
        return ",".join(str(b) for b in sizes.batches)

    full_strands = 1024 // FULL_SIZES.strand_stride
    cpu_strands = 1024 // CPU_SIZES.strand_stride
    p = subparsers.add_parser("bench", help="benchmarks: `hairwarp bench energy`",
                              description="Benchmarks that print and save figures.")
    sub = p.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    e = sub.add_parser(
        "energy", help="forward+backward of every loss term and the total, Warp vs plain torch",
        description=f"Times forward+backward of each term of Eq. 5/6 and of the total on the default body, Warp vs "
                    f"plain torch. Sizes follow --device: on CUDA the paper's ({full_strands} strands x "
                    f"{FULL_SIZES.num_vertices} vertices, batch {batches(FULL_SIZES)}, torch.compile column on); on "
                    f"the CPU a quick run ({cpu_strands} strands x {CPU_SIZES.num_vertices} vertices, batch "
                    f"{batches(CPU_SIZES)}, no torch.compile column, plain-torch peers slower than "
                    f"{CPU_SIZES.skip_torch_above_ms / 1e3:g} s a call timed once; 35-45 s on a 2-core CPU, "
                    "about 75 s the first time, while Warp builds its kernels). --full gives the paper's sizes "
                    "on any device; --batch, --strand-stride, --vertices and "
                    "--[no-]torch-compile override either.")
    add_common_arguments(e)
    e.add_argument("--json", default=None, help="write the results JSON here (default: OUT/bench_energy.json)")
    e.add_argument("--full", action="store_true",
                   help=f"the paper's sizes on any device: {full_strands} strands x {FULL_SIZES.num_vertices} "
                        f"vertices, batch {batches(FULL_SIZES)}, torch.compile column on (the default on CUDA). On "
                        f"a 2-core CPU this takes about half an hour: {FULL_CPU_TIME} measured for a complete run on "
                        "an idle machine, longer under load (with another process on one core its batch-1 half "
                        "alone ran past 10 min; docs/energy_cpu.md)")
    e.add_argument("--batch", default=None,
                   help=f"comma-separated batch sizes (default: {batches(CPU_SIZES)} on the CPU, "
                        f"{batches(FULL_SIZES)} on CUDA or with --full)")
    e.add_argument("--terms", default=None, help="comma-separated subset of terms (default: all, and total)")
    e.add_argument("--torch-compile", action=argparse.BooleanOptionalAction, default=None,
                   help="also time each plain-torch energy through torch.compile (inductor, dynamic=False; on the "
                        "CPU it needs a C++ compiler, and compiling takes seconds per term; a term that does not "
                        "compile shows n/a and its reason in the JSON) (default: off on the CPU, on on CUDA or "
                        "with --full)")
    e.add_argument("--strand-stride", type=int, default=None,
                   help=f"keep one strand in k of the 1024, spread over the scalp "
                        f"(default: {CPU_SIZES.strand_stride} on the CPU, "
                        f"{cpu_strands} strands; {FULL_SIZES.strand_stride} on CUDA or with --full, the paper's "
                        f"{full_strands})")
    e.add_argument("--vertices", type=int, default=None,
                   help=f"vertices per strand (default: {CPU_SIZES.num_vertices} on the CPU, "
                        f"{FULL_SIZES.num_vertices} on CUDA or with --full, the paper's)")
    e.set_defaults(run=run_energy)


def resolve_sizes(args, device):
    """The `BenchSizes` a run of `args` on `device` takes: the device's default (`--full`: the
    paper's), each size flag given on the command line overriding its field.

    Args:
        args: the parsed `bench energy` arguments.
        device: the resolved torch device.

    Returns:
        A `hairwarp.bench.energy.BenchSizes`, named "custom" when a flag changed a field.

    Raises:
        ValueError: a malformed --batch, a stride below 1 or fewer than 3 vertices.
    """
    from dataclasses import replace

    from hairwarp.bench.energy import default_sizes

    sizes = default_sizes(device, full=args.full)
    changes = {}
    if args.batch is not None:
        try:
            changes["batches"] = tuple(int(b) for b in args.batch.split(","))
        except ValueError:
            raise ValueError(f"--batch: expected comma-separated integers, got {args.batch!r}") from None
        if any(b < 1 for b in changes["batches"]):
            raise ValueError(f"--batch: batch sizes must be >= 1, got {args.batch!r}")
    if args.strand_stride is not None:
        if args.strand_stride < 1:
            raise ValueError(f"--strand-stride: expected a positive int, got {args.strand_stride}")
        changes["strand_stride"] = args.strand_stride
    if args.vertices is not None:
        if args.vertices < 3:
            raise ValueError(f"--vertices: expected >= 3, got {args.vertices}")
        changes["num_vertices"] = args.vertices
    if args.torch_compile is not None:
        changes["torch_compile"] = args.torch_compile
    changes = {k: v for k, v in changes.items() if getattr(sizes, k) != v}
    return replace(sizes, name="custom", **changes) if changes else sizes


def run_energy(args) -> int:
    import torch

    from hairwarp.bench.energy import markdown_table, run_energy_benchmark, write_json
    from hairwarp.runtime import resolve_device

    device = resolve_device(args.device, argument="--device")
    torch.manual_seed(args.seed)
    sizes = resolve_sizes(args, device)
    names = None if args.terms is None else set(args.terms.split(","))
    print(f"bench energy ({sizes.name} sizes): batch {','.join(map(str, sizes.batches))}, strand stride "
          f"{sizes.strand_stride} x {sizes.num_vertices} vertices, torch.compile "
          f"{'on' if sizes.torch_compile else 'off'}" + ("" if sizes.name == "full" else "; --full: the paper's sizes"),
          flush=True)
    record = run_energy_benchmark(device, sizes.batches, names=names, torch_compile=sizes.torch_compile,
                                  strand_stride=sizes.strand_stride, num_vertices=sizes.num_vertices,
                                  skip_torch_above_ms=sizes.skip_torch_above_ms)
    record = {"preset": sizes.name, **record}
    path = args.json or os.path.join(args.out, "bench_energy.json")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_json(record, path)
    table = markdown_table(record)
    with open(os.path.splitext(path)[0] + ".md", "w") as f:
        f.write(table + "\n")
    print(table)
    print(f"wrote {path}")
    return 0
