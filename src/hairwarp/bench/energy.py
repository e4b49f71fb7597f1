"""Energy benchmark: forward + backward of each loss term and of the total, the Warp path
(`hairwarp.ops`, `hairwarp.energy`) against the plain-torch path (`hairwarp.torch_reference`),
on the default body (13 348 vertices, cropped to the hair's reach), B different frames of a
head-turn motion. Sizes (`default_sizes`): the paper's (`FULL_SIZES`: 1024 strands x 100
vertices, batch 1 and 32, the torch.compile column on) on CUDA or when asked for; on the CPU by
default `CPU_SIZES` (128 strands x 100 vertices, batch 1 and 4, no torch.compile column, a
plain-torch peer slower than 1 s a call timed once): 35-43 s on a 2-core CPU (73 s with Warp's
kernel cache empty) where the paper's sizes take about half an hour (docs/energy_cpu.md).

Writes {"device", "machine", "sizes", "torch_compile", "skip_torch_above_ms", "results": [{"name",
"warp_ms", "torch_ms", ...}]} (the command adds "preset": the `BenchSizes` name, "full" or "cpu",
or "custom" where a size flag changed it), a result named "total" included (Eq. 6 without
L_func_reg: every term, inertia too).

Each row: `warp_ms` and `torch_ms` (forward + backward, after untimed warm-up calls; the rivals of
a row timed in alternating rounds, `hairwarp.runtime.time_ms_interleaved`), `speedup`
(torch_ms / warp_ms) and `warp_rel_diff` (max |warp - torch| / |torch| of the (B,) energies, from
the first calls). It is float32 round-off except for hair_body_contact and total: their torch
peer takes the distance from the nearest body vertex (the neural simulators' query), Warp's is
exact (2e-2 and 6e-3 apart at 128 strands x 12 vertices, batch 1).

With `torch_compile` (default), each plain-torch energy function (the forward only: the backward
goes through AOTAutograd) is also timed wrapped in `torch.compile(dynamic=False)` (inductor; on
the CPU it needs a C++ compiler), after a first call that compiles it: fields `torch_compile_ms`,
`torch_compile_first_ms` (that first call, compile included), `speedup_vs_compile`
(torch_compile_ms / warp_ms) and `compile_rel_diff` (|compiled - eager| / |eager| of the energy).
A term whose peer does not compile (no C++ compiler; the contact peers' data-dependent searches
may not) records None in those fields and the exception's first line in `compile_note`.
The plain-torch hair-hair peer runs one batch item at a time (`torch_hair_hair_by_item`): at
batch 32 in one call it needs ~35 GB on the CPU.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import torch

from hairwarp.runtime import machine_name, synchronize, time_ms_interleaved
from hairwarp.config import EnergyConfig

STRAND_TERM_NAMES = ("stretch", "bending", "auxiliary", "smoothness", "gravity", "root_alignment", "inertia")


@dataclass(frozen=True)
class BenchSizes:
    """What one benchmark run times: its sizes and how hard it times.

    Attributes:
        name: "full" (the paper's sizes), "cpu" (the CPU's quick default), or "custom" (the command's
            flags changed one of them).
        batches: batch sizes, one set of rows each.
        strand_stride, num_vertices: one strand in k of the 1024 (`Scalp.every`), N vertices per strand.
        torch_compile: whether the torch.compile column is timed (compiling costs seconds a term on a CPU).
        skip_torch_above_ms: a plain-torch peer whose first call is slower than this is timed once.
    """

    name: str
    batches: tuple[int, ...]
    strand_stride: int
    num_vertices: int
    torch_compile: bool
    skip_torch_above_ms: float


# The paper's sizes. A complete run on the 2-core CPU took 26 min 28 s (docs/energy_cpu.md).
FULL_SIZES = BenchSizes("full", (1, 32), 1, 100, True, 60_000.0)
# The CPU's default: 1/8 of the strands (128 x 100 vertices), batch 1 and 4, eager peers only, and
# the plain-torch contact peers (1-6 s a call here) timed once: 35-43 s on a 2-core CPU (measured).
CPU_SIZES = BenchSizes("cpu", (1, 4), 8, 100, False, 1_000.0)


def default_sizes(device: torch.device | str, *, full: bool = False) -> BenchSizes:
    """The benchmark's sizes on `device`: the paper's on CUDA or with `full`, else the CPU's quick ones.

    Args:
        device: where the benchmark runs.
        full: the paper's sizes whatever the device.

    Returns:
        `FULL_SIZES` or `CPU_SIZES`.
    """
    return FULL_SIZES if full or torch.device(device).type != "cpu" else CPU_SIZES


def build_energy_inputs(batch: int, device: torch.device, *, hairstyle: str = "long_straight",
                        noise: float = 1e-3, seed: int = 0, strand_stride: int = 1, num_vertices: int = 100,
                        mixed_lengths: float | None = None):
    """Hair positions near the rigid placement of `batch` frames of the default scene.

    Args:
        batch, device: frames of the head turn, and where.
        hairstyle, noise, seed: the hair and its jitter [m] off the rigid placement.
        strand_stride, num_vertices: one strand in k, N vertices (1, 100: the paper's size).
        mixed_lengths: in (0, 1]: every other strand's positions (x and the inputs' rigid, prev
            and prev2 alike) cut to that fraction of its length (`mix_strand_lengths`), a groom
            whose segments are of two lengths; None keeps the hairstyle's.

    Returns:
        (x (B, M, N, 3) requiring grad, EnergyInputs with prev/prev2, scene, frames).
    """
    from hairwarp.scene.scene import default_scene

    scene = default_scene(hairstyle, "head_turn", strand_stride=strand_stride, num_vertices=num_vertices)
    idx = torch.linspace(0, scene.num_frames - 1, batch).round().long()
    frames = scene.frames(idx, device=device)
    g = torch.Generator(device="cpu").manual_seed(seed)
    rigid = frames.rigid.positions
    if mixed_lengths is not None:
        rigid = mix_strand_lengths(rigid, mixed_lengths)
    jitter = (torch.randn(rigid.shape, generator=g) * noise).to(device)
    jitter[:, :, :2] = 0
    x = (rigid + jitter).detach().requires_grad_(True)
    prev = (rigid + 0.5 * jitter).detach()
    inputs = replace(frames.inputs, prev=prev, prev2=rigid.detach())
    if mixed_lengths is not None:
        rest = (rigid[0, :, 1:] - rigid[0, :, :-1]).norm(dim=-1)
        inputs = replace(inputs, rigid=rigid.detach(), rest_lengths=rest)
    return x, inputs, scene, frames


def mix_strand_lengths(x: torch.Tensor, fraction: float) -> torch.Tensor:
    """(B, M, N, 3) hair with every other strand (0, 2, ...) resampled, N vertices still, along
    its first `fraction` of its polyline (linear interpolation; roots unchanged): segments
    `fraction` x as long as the others'. With fraction 0.1 half the segments are 1.8x the mean
    length, the case docs/contact.md 11 measures.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"mixed_lengths: expected a fraction in (0, 1], got {fraction}")
    n = x.shape[2]
    t = torch.linspace(0.0, fraction * (n - 1), n, dtype=x.dtype, device=x.device)
    first = t.floor().long().clamp(max=n - 2)
    w = (t - first)[:, None]
    mixed = x.clone()
    cut = x[:, ::2]
    mixed[:, ::2] = cut[:, :, first] * (1 - w) + cut[:, :, first + 1] * w
    return mixed


def torch_hair_hair_by_item(x, config: EnergyConfig):
    """The plain-torch hair-hair peer, one batch item at a time: (B,) energies.

    Its voxel-grid search holds every candidate pair of the 27 neighbouring voxels at once,
    about 1.1 GB per 1024 x 100 batch item on the CPU (measured; docs/contact.md): the whole
    batch of 32 in one call needs ~35 GB and was killed for memory at 24 GB. Item by item its
    peak stays that of one item, and the result is the same (pairs never cross items).
    """
    from hairwarp.torch_reference import hair_hair_contact as ref_hh

    c = config
    return torch.cat([
        ref_hh.hair_hair_contact_energy(x[b:b + 1], c.hair_diameter, c.hair_hair_dhat, c.barrier_join_fraction,
                                        c.hair_hair_weight, c.barrier_variant, method="grid")[0]
        for b in range(x.shape[0])
    ])


def _torch_total_by_item(x, inputs, config: EnergyConfig):
    """Plain-torch total energy with its hair-hair term evaluated item by item (see above)."""
    from hairwarp.torch_reference import energy as ref_energy

    rest = ref_energy.total_energy(x, inputs, replace(config, hair_hair_weight=0.0), dynamic=True).total
    if config.hair_hair_weight == 0.0:
        return rest
    return rest + torch_hair_hair_by_item(x, config)


def _closures(x, inputs, config: EnergyConfig):
    """Name -> (warp fn, torch fn), each returning a (B,) energy."""
    from hairwarp import energy as hw_energy
    from hairwarp import ops
    from hairwarp.torch_reference import energy as ref_energy
    from hairwarp.torch_reference import strand_energies as ref

    c = config
    m = c.vertex_mass
    args = {
        "stretch": ((inputs.rest_lengths, c.stretch_weight), {}),
        "bending": ((c.bending_weight, c.bending_eps), {}),
        "auxiliary": ((inputs.rigid, c.auxiliary_weight), {}),
        "smoothness": ((c.smoothness_weight,), {}),
        "gravity": ((m, c.gravity, c.gravity_weight), {}),
        "root_alignment": ((inputs.scalp_normals, c.root_alignment_weight, c.root_alignment_segments,
                            c.root_alignment_eps), {}),
        "inertia": ((inputs.prev, inputs.prev2, m, c.time_step, c.inertia_weight), {}),
    }
    out = {}
    for name in STRAND_TERM_NAMES:
        a, kw = args[name]
        warp_fn = getattr(ops, f"{name}_energy")
        torch_fn = getattr(ref, f"{name}_energy")
        out[name] = (lambda f=warp_fn, a=a: f(x, *a), lambda f=torch_fn, a=a: f(x, *a))
    body = inputs.body
    out["hair_body_contact"] = (
        lambda: ops.hair_body_contact_energy(x, body, c.hair_body_xi, c.hair_body_dhat, c.barrier_join_fraction,
                                             weight=c.hair_body_weight, variant=c.barrier_variant),
        lambda: ref_energy.hair_body_energy(x, body, c, "nearest_vertex"),
    )
    out["hair_hair_contact"] = (
        lambda: ops.hair_hair_contact_energy(x, c.hair_diameter, c.hair_hair_dhat, c.barrier_join_fraction,
                                             weight=c.hair_hair_weight, variant=c.barrier_variant)[0],
        lambda: torch_hair_hair_by_item(x, c),
    )
    out["total"] = (
        lambda: hw_energy.total_energy(x, inputs, c, dynamic=True).total,
        lambda: _torch_total_by_item(x, inputs, c),
    )
    return out


def _compiled_peer(torch_fn):
    """`torch_fn` through torch.compile, or (None, reason) when torch.compile is not usable."""
    try:
        return torch.compile(torch_fn, dynamic=False), None
    except Exception as exc:  # torch.compile itself unusable (a missing C++ compiler fails later, at the first call)
        return None, _exception_line(exc)


def run_energy_benchmark(device: torch.device, batches=(1, 32), *, config: EnergyConfig | None = None,
                         names=None, skip_torch_above_ms: float = 60_000.0, progress: bool = True,
                         torch_compile: bool = True, strand_stride: int = 1, num_vertices: int = 100) -> dict:
    """Time forward + backward of every term and the total, Warp vs plain torch.

    Args:
        device: where to run.
        batches: batch sizes.
        config: energy weights (default `EnergyConfig()`).
        names: subset of term names (plus "total"); None for all.
        skip_torch_above_ms: after one untimed call slower than this, the torch path of that
            term is timed once, not repeated (the CPU's brute-force peers can take minutes).
        progress: print each row as it is measured.
        torch_compile: also time each plain-torch energy through `torch.compile`.
        strand_stride, num_vertices: hair size (see `build_energy_inputs`; 1, 100: the paper's).

    Returns:
        The benchmark record (see the module docstring).
    """
    from hairwarp import set_finite_checks

    config = config or EnergyConfig()
    results = []
    sizes = {}
    compile_notes_printed = set()
    previous_checks = set_finite_checks(False)  # the inputs are ours: no NaN scans in the timed loop
    try:
        for batch in batches:
            x, inputs, scene, frames = build_energy_inputs(batch, device, strand_stride=strand_stride,
                                                           num_vertices=num_vertices)
            sizes = {"strands": int(x.shape[1]), "vertices_per_strand": int(x.shape[2]),
                     "body_vertices": scene.body.num_vertices, "body_faces": scene.body.num_faces,
                     "body_faces_after_crop": int(frames.body_mesh.num_faces), "batches": list(batches)}
            for name, (warp_fn, torch_fn) in _closures(x, inputs, config).items():
                if names is not None and name not in names:
                    continue

                def step(fn):
                    def run():
                        x.grad = None
                        fn().sum().backward()
                    return run

                # First calls (untimed: compiles, caches; their energies compared), then the rivals
                # timed in alternating rounds (`time_ms_interleaved`): a ratio of host-bound
                # sub-millisecond calls is only as good as the machine's steadiness between them.
                _, warp_value = _first_call(warp_fn, x)
                first, eager_value = _first_call(torch_fn, x)
                timed_fns = {"warp": step(warp_fn)}
                torch_note = ""
                if first > skip_torch_above_ms:
                    torch_note = "timed once"
                else:
                    timed_fns["torch"] = step(torch_fn)
                compiled_row = {}
                if torch_compile:
                    compiled_row, compiled, second_ms = _first_call_compiled(torch_fn, x, eager_value)
                    if compiled is not None:
                        if first > skip_torch_above_ms:
                            compiled_row["torch_compile_ms"] = second_ms  # timed once, like its eager peer
                        else:
                            timed_fns["compile"] = step(compiled)
                times = time_ms_interleaved(timed_fns, device, warmup=1)
                warp_ms = times["warp"]
                torch_ms = times.get("torch", first)
                row = {"name": name, "batch": batch, "warp_ms": warp_ms, "torch_ms": torch_ms,
                       "speedup": torch_ms / warp_ms if warp_ms > 0 else None,
                       "warp_rel_diff": _rel_diff(warp_value, eager_value)}
                if torch_note:
                    row["note"] = torch_note
                if torch_compile:
                    if "compile" in times:
                        compiled_row["torch_compile_ms"] = times["compile"]
                    row.update(compiled_row)
                    if row["torch_compile_ms"] is not None and warp_ms > 0:
                        row["speedup_vs_compile"] = row["torch_compile_ms"] / warp_ms
                    torch._dynamo.reset()  # one term's graphs and guards do not pile up on the next
                results.append(row)
                if progress:
                    compiled = row.get("torch_compile_ms")
                    extra = f"   compile {compiled:10.3f} ms" if compiled is not None else ""
                    once = " (timed once)" if torch_note else ""
                    print(f"  B={batch:<3d} {name:<18s} warp {warp_ms:10.3f} ms   torch {torch_ms:10.3f} ms   "
                          f"x{row['speedup']:.1f}{extra}{once}", flush=True)
                    note = row.get("compile_note")
                    if note and note not in compile_notes_printed:  # no C++ compiler: one line, not one per row
                        print(f"  torch.compile unusable for {name} (column n/a): {note}", flush=True)
                        compile_notes_printed.add(note)
    finally:
        set_finite_checks(previous_checks)
    return {"device": str(device), "machine": machine_name(device), "sizes": sizes,
            "torch_compile": torch_compile, "skip_torch_above_ms": skip_torch_above_ms,
            "config": {k: v for k, v in vars(config).items()}, "results": results}


def _first_call(fn, x) -> tuple[float, torch.Tensor]:
    """One untimed forward + backward of `fn`: (its time [ms], its (B,) energy detached in float64)."""
    import time

    x.grad = None
    t0 = time.perf_counter()
    value = fn()
    value.sum().backward()
    synchronize(x.device)  # a row "timed once" takes this time as its timing
    return (time.perf_counter() - t0) * 1e3, value.detach().double()


def _rel_diff(value: torch.Tensor, reference: torch.Tensor) -> float:
    """The largest |value - reference| / |reference| over the batch (0 where both are 0)."""
    return float(((value - reference).abs() / reference.abs().clamp_min(1e-30)).max())


def _exception_line(exc: Exception) -> str:
    """`Type: first line of the message`, for a row's note."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"


def _first_call_compiled(torch_fn, x, eager_value: torch.Tensor):
    """The torch.compile peer's first two calls: (its row fields, the compiled function or None,
    the second call's time [ms] or None).

    The first call compiles (forward and, through AOTAutograd, backward); its energy is checked
    against `eager_value`; the second runs what was compiled. Exceptions from compiling or running
    the compiled peer are recorded in `compile_note` (the function then None), never raised.
    """
    compiled, note = _compiled_peer(torch_fn)
    out = {"torch_compile_ms": None, "torch_compile_first_ms": None, "speedup_vs_compile": None}
    if compiled is None:
        return {**out, "compile_note": note}, None, None
    try:
        out["torch_compile_first_ms"], compiled_value = _first_call(compiled, x)
        out["compile_rel_diff"] = _rel_diff(compiled_value, eager_value)
        second_ms = _first_call(compiled, x)[0]  # a failure past the compile shows here, not in the timing
    except Exception as exc:  # a peer that does not compile (graph breaks are fine; errors are not)
        return {**out, "compile_note": _exception_line(exc)}, None, None
    return out, compiled, second_ms


def markdown_table(record: dict) -> str:
    """The benchmark as a markdown table (one row per term and batch)."""
    preset = f" ({record['preset']})" if record.get("preset") else ""
    lines = [f"Device: {record['machine']}; sizes{preset}: {record['sizes']}", "",
             "| term | batch | Warp fwd+bwd (ms) | plain torch fwd+bwd (ms) | speed-up | torch.compile fwd+bwd (ms) "
             "| vs compile |",
             "|---|---:|---:|---:|---:|---:|---:|"]

    def cell(value, fmt):
        return "n/a" if value is None else format(value, fmt)

    once = False
    for r in record["results"]:
        mark = " *" if r.get("note") == "timed once" else ""
        once = once or bool(mark)
        lines.append(f"| {r['name']} | {r['batch']} | {r['warp_ms']:.3f} | {r['torch_ms']:.3f}{mark} | "
                     f"{r['speedup']:.1f}x | {cell(r.get('torch_compile_ms'), '.3f')} | "
                     f"{cell(r.get('speedup_vs_compile'), '.1f')}{'' if r.get('speedup_vs_compile') is None else 'x'} |")
    if once:
        limit = record.get("skip_torch_above_ms")
        over = f" than {limit / 1e3:g} s" if limit is not None else ""
        lines += ["", f"\\* timed once (its first call), not repeated: that call was slower{over}"]
    return "\n".join(lines)


def write_json(record: dict, path: str) -> None:
    """Write the benchmark record as JSON to `path`."""
    with open(path, "w") as f:
        json.dump(record, f, indent=2, default=str)
