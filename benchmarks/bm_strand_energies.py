"""Quick timing of the seven strand terms (Eq. 7-11, 15, 16), forward + backward, and of the
follow-the-leader projection (the physics solver's variables, forward + adjoint).

Warp fused kernel (`hairwarp.ops.strand_energies`) against the plain-torch reference
(`hairwarp.torch_reference.strand_energies`), on the test suite's own hair builder.

    python benchmarks/bm_strand_energies.py [--strands 1024] [--vertices 100] [--batch 1]
        [--device cpu|cuda] [--dtype float32|float64] [--repeats 100] [--json out.json]
"""

from __future__ import annotations

import argparse
import importlib
import json
import pathlib
import sys
import time

import numpy as np
import torch

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
from test_strand_energies import make_inputs, make_strands  # noqa: E402

from hairwarp._validate import set_finite_checks  # noqa: E402
from hairwarp.config import EnergyConfig  # noqa: E402

# The modules, not the function `hairwarp.ops.strand_energies` that shadows the submodule name.
ops = importlib.import_module("hairwarp.ops.strand_energies")
torch_ref = importlib.import_module("hairwarp.torch_reference.strand_energies")


def _synchronize(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_cases(cases, x, device, repeats):
    """(min, median) wall time [ms] of fn(x).sum().backward() for each case.

    The cases run round-robin, so a load change on a shared machine hits them alike; the
    minimum is the figure to compare (preemption only adds time). Synchronised inside the timed
    region.
    """
    for fn in cases.values():  # warm-up: kernel load, allocator
        for _ in range(3):
            x.grad = None
            fn(x).sum().backward()
    _synchronize(device)
    times = {name: [] for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            x.grad = None
            start = time.perf_counter()
            fn(x).sum().backward()
            _synchronize(device)
            times[name].append((time.perf_counter() - start) * 1e3)
    return {name: (float(np.min(t)), float(np.median(t))) for name, t in times.items()}


def kernel_times(cases, x, device, calls=20):
    """Device time [us] per call of the Warp kernels (CUDA only), from the torch profiler."""
    out = {}
    for name, fn in cases.items():
        if not name.startswith("warp") or name.endswith("checks"):
            continue
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(calls):
                x.grad = None
                fn(x).sum().backward()
            _synchronize(device)
        events = [e for e in prof.key_averages() if "strand_energies" in e.key]
        out[name] = sum(e.device_time_total for e in events) / calls
    return out


def projection_kernel_times(x, rigid, device, calls=20):
    """Device time [us] per call of the follow-the-leader forward and adjoint kernels (CUDA only)."""
    from hairwarp.ops.strand_projection import follow_the_leader

    target = x.detach().clone().requires_grad_(True)
    for _ in range(3):
        follow_the_leader(rigid, target, check=False).sum().backward()
    _synchronize(device)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            target.grad = None
            follow_the_leader(rigid, target, check=False).square().sum().backward()
        _synchronize(device)
    times = {"forward": 0.0, "adjoint": 0.0}
    for e in prof.key_averages():  # one-thread kernels, or the tile kernels' "..._tiled_kernels__locals__adjoint"
        if "follow_the_leader" not in e.key:
            continue
        times["adjoint" if "adjoint" in e.key else "forward"] += e.device_time_total / calls
    return times


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strands", type=int, default=1024)
    parser.add_argument("--vertices", type=int, default=100)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument("--repeats", type=int, default=100)
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args(argv)

    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    rng = np.random.default_rng(0)
    # One hairstyle from the tests' builder, jittered per batch item (the builder loops in Python).
    x_np = make_strands(rng, 1, args.strands, args.vertices)
    x_np = x_np + 1e-3 * rng.normal(size=(args.batch,) + x_np.shape[1:])
    inputs = make_inputs(rng, x_np, shared=True)
    t = {k: torch.tensor(v, dtype=dtype, device=device) for k, v in inputs.items()}
    x = torch.tensor(x_np, dtype=dtype, device=device, requires_grad=True)
    kwargs = dict(
        rest_lengths=t["rest_lengths"],
        config=EnergyConfig(),
        rigid=t["rigid"],
        scalp_normals=t["scalp_normals"],
        prev=t["prev"],
        prev2=t["prev2"],
    )

    cases = {
        "torch_reference": lambda y: torch_ref.strand_energies(y, **kwargs)[0],
        "warp_auto": lambda y: ops.strand_energies(y, **kwargs)[0],
        "warp_strand": lambda y: ops.strand_energies(y, layout="strand", **kwargs)[0],
        "warp_vertex": lambda y: ops.strand_energies(y, layout="vertex", **kwargs)[0],
    }
    results = {
        "strands": args.strands,
        "vertices": args.vertices,
        "batch": args.batch,
        "device": str(device),
        "dtype": args.dtype,
        "terms": 7,
        "ms": {},
    }

    # Finite checks scan every input for NaN/Inf (a host read on CUDA); hot loops turn them off.
    def unchecked(fn):
        def run(y):
            previous = set_finite_checks(False)
            try:
                return fn(y)
            finally:
                set_finite_checks(previous)

        return run

    warp_cases = [name for name in cases if name.startswith("warp")]
    cases.update({f"{name}_no_finite_checks": unchecked(cases[name]) for name in warp_cases})
    for name, (best, median) in time_cases(cases, x, device, args.repeats).items():
        results["ms"][name] = {"min": best, "median": median}
        print(f"{name:32s} min {best:8.3f} ms  median {median:8.3f} ms  (forward + backward)")
    if device.type == "cuda":
        results["kernel_us"] = kernel_times(cases, x, device)
        for name, us in results["kernel_us"].items():
            print(f"{name:32s} device time of the Warp kernel {us:8.1f} us per call")
        rigid = t["rigid"].expand_as(x).contiguous()
        results["follow_the_leader_us"] = projection_kernel_times(x, rigid, device)
        print("follow_the_leader                device time forward {forward:.1f} us, adjoint {adjoint:.1f} us "
              "per call".format(**results["follow_the_leader_us"]))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
