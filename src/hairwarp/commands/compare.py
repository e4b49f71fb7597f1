"""`hairwarp compare`: methods against each other on the fixed comparison scenes.

Runs the chosen methods (rigid, adam, lbfgs, physics, reference, the networks) on the chosen
scenes, every method on the same inputs, and writes OUT/compare.json (results, machine, sizes,
scenes version, command line), OUT/compare.md (Table-1-style tables, with the energy ratio E / E*
and the distance to the optimum's drape, or on a motion the distance to the physics and the tips'
swing ratio and correlation), OUT/speed_accuracy.png (time against penetration and energy gap)
and, per motion, OUT/swing_<scene>.png (each method's mean tip offset beside the physics). `--stability` runs the
stability study instead and writes OUT/stability.json and OUT/stability.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

_DEFAULT_METHODS = "rigid,adam,lbfgs,reference"


def add_parser(subparsers) -> None:
    from hairwarp.commands.common import add_common_arguments
    from hairwarp.evaluation.scenes import STATIC_SCENES

    p = subparsers.add_parser("compare", help="speed versus accuracy of the methods on the comparison scenes",
                              description=__doc__.split("\n\n")[1])
    add_common_arguments(p)
    p.add_argument("--methods", default=_DEFAULT_METHODS,
                   help=f"comma-separated registered methods (default: {_DEFAULT_METHODS})")
    p.add_argument("--scenes", default=",".join(STATIC_SCENES),
                   help="comma-separated comparison scenes (default: the static ones: "
                        f"{','.join(STATIC_SCENES)}; motions: whiplash, torso_bend)")
    p.add_argument("--reduced", action="store_true", help="quick size: every 4th scalp root (about 256 strands)")
    p.add_argument("--strand-stride", type=int, default=None, help="keep one scalp root in this many, spread over the scalp")
    p.add_argument("--num-vertices", type=int, default=None, help="vertices per strand (default: 100)")
    p.add_argument("--max-iterations", type=int, default=None,
                   help="iteration cap of adam and lbfgs (default: 2000)")
    p.add_argument("--reference-max-iterations", type=int, default=None,
                   help="iteration cap of the converged reference drape (default: 5000)")
    p.add_argument("--reference-starts", type=int, default=1,
                   help="the reference drape is the lowest of this many solves, the first from the rigid placement, "
                        "the others from it moved by 0.1 mm (default: 1)")
    p.add_argument("--patience", type=int, default=200,
                   help="optimizers stop after this many iterations without decrease (default: 200)")
    p.add_argument("--refine", type=int, default=0, metavar="K",
                   help="also run every network method finished by K L-BFGS iterations (NAME+refine), "
                        "drawn as a curve over the iterations (default: 0: no such rows)")
    p.add_argument("--checkpoint", default=None,
                   help="network methods: a checkpoint written by `hairwarp train` (default: the shipped one)")
    p.add_argument("--keep-out", action=argparse.BooleanOptionalAction, default=True,
                   help="network methods: their output through the body pass, rest lengths kept (default: on)")
    p.add_argument("--record-every", type=int, default=10,
                   help="record penetration every this many optimizer iterations, for the chart (default: 10)")
    p.add_argument("--stability", action="store_true", help="run the stability study instead of the comparison")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run)


def _check_int(value, flag: str, minimum: int) -> None:
    if value is not None and value < minimum:
        raise ValueError(f"{flag}: expected an integer >= {minimum}, got {value}")


def run(args) -> int:
    import torch

    from hairwarp.runtime import resolve_device
    from hairwarp.evaluation.charts import speed_accuracy_chart
    from hairwarp.evaluation.harness import markdown_tables, run_comparison, write_results
    from hairwarp.methods import REFERENCE_MAX_ITERATIONS, MethodOptions

    device = resolve_device(args.device, argument="--device")
    torch.manual_seed(args.seed)
    _check_int(args.strand_stride, "--strand-stride", 1)
    _check_int(args.num_vertices, "--num-vertices", 3)
    _check_int(args.max_iterations, "--max-iterations", 0)
    _check_int(args.reference_max_iterations, "--reference-max-iterations", 0)
    _check_int(args.reference_starts, "--reference-starts", 1)
    _check_int(args.patience, "--patience", 1)
    _check_int(args.record_every, "--record-every", 0)
    _check_int(args.refine, "--refine", 0)
    command_line = "hairwarp " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv else None
    os.makedirs(args.out, exist_ok=True)

    if args.stability:
        from hairwarp.evaluation.stability import run_stability_study, stability_markdown

        record = run_stability_study(device, progress=not args.quiet)
        record["command_line"] = command_line
        path = write_results(record, os.path.join(args.out, "stability.json"))
        table = stability_markdown(record)
        with open(os.path.join(args.out, "stability.md"), "w") as f:
            f.write(table + "\n")
        print(table)
        print(f"wrote {path} and stability.md")
        return 0

    options = MethodOptions(
        max_iterations=args.max_iterations,
        patience=args.patience,
        record_every=args.record_every,
        refine=args.refine,
        checkpoint=args.checkpoint,
        keep_out=args.keep_out,
        reference_max_iterations=(REFERENCE_MAX_ITERATIONS if args.reference_max_iterations is None
                                  else args.reference_max_iterations),
        reference_starts=args.reference_starts,
    )
    try:
        record = run_comparison(args.methods, args.scenes, reduced=args.reduced, strand_stride=args.strand_stride,
                                num_vertices=args.num_vertices, device=device, options=options, seed=args.seed,
                                command_line=command_line, progress=not args.quiet, plots_dir=args.out)
    except ValueError as exc:
        message = str(exc)
        for name in ("methods", "scenes"):  # name the flag, not the function argument
            if message.startswith(f"{name}:"):
                raise ValueError(f"--{message}") from None
        raise
    path = write_results(record, os.path.join(args.out, "compare.json"))
    table = markdown_tables(record)
    with open(os.path.join(args.out, "compare.md"), "w") as f:
        f.write(table + "\n")
    written = [path, "compare.md"]
    if any(e["kind"] == "static" for e in record["scenes"]):
        speed_accuracy_chart(record, os.path.join(args.out, "speed_accuracy.png"))
        written.append("speed_accuracy.png")
    written += [os.path.basename(e["swing_plot"]) for e in record["scenes"] if e.get("swing_plot")]
    print(table)
    print(f"wrote {', '.join(written)} into {args.out}")
    return 0
