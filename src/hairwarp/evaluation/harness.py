"""The speed-versus-accuracy harness: every chosen method on every chosen scene, same inputs.

For each comparison scene (`hairwarp.evaluation.scenes`) the harness builds the frames once,
hands that very object to every method (and checks afterwards that no method changed it), and
scores what comes back with the metrics of Table 1 and beyond (`hairwarp.metrics`):

Static scenes (a batch of B independent drapes):
    - ms per drape, measured by the method after its warm-up (None for the rigid placement);
    - penetration % (share of moving vertices with signed distance < 0), mean over the batch;
    - length change % (mean |l / l0 - 1|), mean over the batch;
    - energy: the static total energy (Eq. 5) of the drapes, summed over the batch;
    - energy gap to the converged optimum E* (the "reference" method's energy) relative to
      the energy the method had to remove: (E - E*) / (E0 - E*), E0 the rigid placement's
      energy (both summed over the batch). 1 = no progress, 0 = the optimum.
    Optimizers also return their history, which becomes curves on the chart: loss (hence the
    energy gap) every iteration, penetration every `record_every` iterations.
    - shape against the optimum (`hairwarp.metrics.static_fidelity`): energy ratio E / E*,
      mean and p95 vertex distance and mean tip height difference to the reference's drape
      [mm] (penetration and length change cannot see a splayed or lifted drape).

Motion scenes (T frames in time order):
    - ms per frame; penetration % and length change %, mean over frames (and the worst frame);
    - per frame, the mean and the max vertex distance to the physics reference (the
      "reference" method's implicit-Euler simulation) [m];
    - jitter: mean norm of the second time difference of positions beyond the reference's [m];
    - motion against the physics (`hairwarp.metrics.motion_fidelity`; the "reference" method's
      simulation, else "physics"): mean / worst-frame distance [mm], the tips' swing beyond
      the rigid placement (RMS [mm]) of the method and of the physics, their amplitude ratio
      and correlation; with `plots_dir`, a PNG per motion of each method's mean tip offset
      beside the physics (`hairwarp.evaluation.charts.swing_plot`).

`run_comparison` returns a JSON-ready dict (schema `RESULTS_SCHEMA`); `write_results` stores
it, `markdown_tables` renders the Table-1-style tables.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
from collections.abc import Sequence

import torch

from hairwarp import metrics as M
from hairwarp.methods import NETWORK_METHODS, REFINE_SUFFIX, MethodOptions, composed_names, make
from hairwarp.evaluation.scenes import SCENE_NAMES, SCENES_VERSION, comparison_scene
from hairwarp.runtime import jsonable, machine_description, resolve_device

RESULTS_SCHEMA = "hairwarp.compare/1"


def _fingerprint(frames) -> list[float]:
    """Cheap checksum of what a method may read: rigid placement, rest lengths, normals, body."""
    parts = [frames.rigid.positions, frames.inputs.rest_lengths, frames.rigid.normals,
             frames.body_mesh.vertices]
    return [float(p.detach().double().sum()) + float((p.detach().double() ** 2).sum()) for p in parts]


def _static_energy(x: torch.Tensor, frames, config) -> float:
    from hairwarp.energy import total_energy

    with torch.no_grad():
        return float(total_energy(x, frames.inputs, config).total.sum())


def _gap(energy: float, optimum: float | None, initial: float) -> float | None:
    if optimum is None or not math.isfinite(energy):
        return None
    return float(M.energy_gap(torch.tensor(energy, dtype=torch.float64), optimum, initial))


def _check_positions(name: str, positions: torch.Tensor, shape: tuple) -> None:
    if tuple(positions.shape) != shape:
        raise ValueError(f"methods: {name!r} returned positions of shape {tuple(positions.shape)}, expected {shape}")


def _run_static(scene, frames, methods: dict, config, record_every: int, progress) -> list[dict]:
    rigid = frames.rigid.positions
    body = frames.body_mesh
    rest = frames.inputs.rest_lengths
    batch = rigid.shape[0]
    e_initial = _static_energy(rigid, frames, config)

    def pen_metric(x):
        return {"penetration": float(M.penetration_percent(x, body).mean())}

    rows, drapes = [], {}
    before = _fingerprint(frames)
    for name, method in methods.items():
        progress(f"{scene.name}: {name}")
        result = method.drape(frames, metrics=pen_metric if record_every else None)
        if _fingerprint(frames) != before:
            raise RuntimeError(f"method {name!r} modified the scene's inputs; every method must see the same inputs")
        positions = result.positions.detach()
        _check_positions(name, positions, tuple(rigid.shape))
        drapes[name] = positions
        finite = bool(torch.isfinite(positions).all())
        row = {
            "method": name,
            "kind": method.kind,
            "time_ms": result.time_ms,
            "finite": finite,
            "penetration_percent": float(M.penetration_percent(positions, body).mean()) if finite else None,
            "penetration_percent_per_drape": M.penetration_percent(positions, body).tolist() if finite else None,
            "length_change_percent": float(M.length_change_percent(positions, rest).mean()) if finite else None,
            "energy": _static_energy(positions, frames, config) if finite else None,
            "info": jsonable(result.info),
            "history": [jsonable(h) for h in result.history],
            "batch": batch,
        }
        rows.append(row)
    # The optimum E*: the reference method's energy (or the lowest energy anyone reached, if
    # that is lower: then the "reference" was not converged, and the gap says so by being < 0).
    optimum = next((r["energy"] for r in rows if r["method"] == "reference"), None)
    optimum_positions = drapes.get("reference")
    for row in rows:
        for key in _STATIC_FIDELITY:
            row[key] = None
        if optimum_positions is not None and row["finite"]:
            fidelity = M.static_fidelity(drapes[row["method"]], optimum_positions, row["energy"], optimum)
            row.update({key: fidelity.get(key) for key in _STATIC_FIDELITY})
        row["energy_initial"] = e_initial
        row["energy_optimum"] = optimum
        row["energy_gap"] = _gap(row["energy"], optimum, e_initial) if row["energy"] is not None else None
        for h in row["history"]:
            h["energy_gap"] = _gap(h["loss"], optimum, e_initial)
    return rows


# Fields of `metrics.static_fidelity` and `metrics.motion_fidelity` in the harness's rows.
_STATIC_FIDELITY = ("energy_ratio", "mean_distance_mm", "p95_distance_mm", "tip_height_difference_mm")
_MOTION_FIDELITY = ("mean_distance_mm", "max_distance_mm", "per_frame_distance_mm", "strand_distance_p99_mm",
                    "swing_mm", "physics_swing_mm", "swing_amplitude_ratio", "swing_correlation",
                    "largest_step_mm", "physics_largest_step_mm", "swing_by_axis_mm", "physics_swing_by_axis_mm",
                    "swing_correlation_by_axis", "bulk_swing_correlation")


def _physics_of(sims: dict) -> tuple[str | None, torch.Tensor | None]:
    """The physics simulation the motion metrics compare against: "reference", else "physics"."""
    for name in ("reference", "physics"):
        x = sims.get(name)
        if x is not None and bool(torch.isfinite(x).all()):
            return name, x
    return None, None


def _run_motion(scene, frames, methods: dict, progress, plots_dir: str | None = None) -> tuple[list[dict], str | None]:
    body = frames.body_mesh
    rest = frames.inputs.rest_lengths
    shape = tuple(frames.rigid.positions.shape)
    rows, sims = [], {}
    before = _fingerprint(frames)
    for name, method in methods.items():
        progress(f"{scene.name}: {name}")
        sim = method.simulate(frames)
        if _fingerprint(frames) != before:
            raise RuntimeError(f"method {name!r} modified the scene's inputs; every method must see the same inputs")
        positions = sim.positions.detach()
        _check_positions(name, positions, shape)
        sims[name] = positions
        finite = bool(torch.isfinite(positions).all())
        pen = M.penetration_percent(positions, body) if finite else None
        lc = M.length_change_percent(positions, rest) if finite else None
        rows.append({
            "method": name,
            "kind": method.kind,
            "time_ms": sim.time_ms,
            "finite": finite,
            "penetration_percent": float(pen.mean()) if finite else None,
            "penetration_percent_max_frame": float(pen.max()) if finite else None,
            "length_change_percent": float(lc.mean()) if finite else None,
            "info": jsonable(sim.info),
        })
    reference = sims.get("reference")
    for row in rows:
        x = sims[row["method"]]
        row["distance_mean_m"] = row["distance_max_m"] = row["jitter_m"] = None
        row["distance_mean_per_frame_m"] = row["distance_max_per_frame_m"] = None
        if reference is None or not row["finite"] or not bool(torch.isfinite(reference).all()):
            continue
        mean_d, max_d = M.distance_to_reference(x, reference)
        row["distance_mean_per_frame_m"] = mean_d.tolist()
        row["distance_max_per_frame_m"] = max_d.tolist()
        row["distance_mean_m"] = float(mean_d.mean())
        row["distance_max_m"] = float(max_d.max())
        if x.shape[0] >= 3:
            row["jitter_m"] = float(M.jitter(x, reference))
    physics_name, physics = _physics_of(sims)
    rigid = frames.rigid.positions
    for row in rows:
        row["physics"] = physics_name
        for key in _MOTION_FIDELITY:
            row[key] = None
        if physics is not None and row["finite"]:
            fidelity = M.motion_fidelity(sims[row["method"]], physics, rigid)
            row.update({key: fidelity.get(key) for key in _MOTION_FIDELITY})
    plot = None
    if plots_dir is not None and physics is not None:
        from hairwarp.evaluation.charts import swing_plot

        curves = {name: M.mean_tip_offset(x, rigid) for name, x in sims.items() if bool(torch.isfinite(x).all())}
        os.makedirs(plots_dir, exist_ok=True)
        plot = swing_plot(curves, os.path.join(plots_dir, f"swing_{scene.name}.png"), fps=float(scene.fps),
                          physics=physics_name, title=f"{scene.name}: mean tip offset from the rigid placement")
    return rows, plot


def parse_names(text: str | Sequence[str], known: Sequence[str], flag: str) -> list[str]:
    """Comma-separated names (or a sequence) checked against `known`; ValueError names `flag`."""
    names = [n.strip() for n in text.split(",")] if isinstance(text, str) else [str(n) for n in text]
    names = [n for n in names if n]
    if not names:
        raise ValueError(f"{flag}: expected at least one name from {list(known)}")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"{flag}: unknown {unknown}; expected names from {list(known)}")
    if len(set(names)) != len(names):
        raise ValueError(f"{flag}: a name is repeated in {names}")
    return names


def run_comparison(
    methods: Sequence[str] | str,
    scenes: Sequence[str] | str,
    *,
    reduced: bool = True,
    strand_stride: int | None = None,
    num_vertices: int | None = None,
    device="cpu",
    options: MethodOptions | None = None,
    seed: int = 0,
    command_line: str | None = None,
    progress: bool = False,
    plots_dir: str | None = None,
) -> dict:
    """Run `methods` on `scenes` (every method on the same frames) and score them.

    Args:
        methods: registered method names (comma-separated string or sequence). "reference"
            among them gives the energy gap (static scenes) and the distances to the physics
            reference (motions); without it those fields are None.
        scenes: names from `hairwarp.evaluation.scenes.SCENE_NAMES`.
        reduced: the quick size (every 4th scalp root).
        strand_stride, num_vertices: explicit sizes (override `reduced`; tests use them).
        device: torch device of every computation.
        options: what every method factory receives (iteration caps, patience, record_every).
        seed: torch's seed, set before each method runs.
        command_line: recorded in the results.
        progress: print a line per (scene, method) and show the methods' progress bars.
        plots_dir: write a swing plot (PNG) per motion scene here (needs "physics" or
            "reference" among the methods); its path goes into the scene's "swing_plot".

    Returns:
        dict with schema `RESULTS_SCHEMA`: "machine", "sizes", "scenes_version", "options",
        "command_line", and "scenes": one entry per scene with its description and "results"
        (one row per method; see the module docstring for the fields).

    Raises:
        ValueError: unknown method or scene names (naming `methods` / `scenes`).
    """
    device = resolve_device(device)
    known = composed_names()
    method_names = parse_names(methods, known, "methods")
    options = options or MethodOptions()
    if options.refine > 0:  # every network also finished by `refine` L-BFGS iterations: a curve over K
        for name in list(method_names):
            if name in NETWORK_METHODS and name + REFINE_SUFFIX not in method_names:
                method_names.insert(method_names.index(name) + 1, name + REFINE_SUFFIX)
    scene_names = parse_names(scenes, SCENE_NAMES, "scenes")
    if progress:
        options = dataclasses.replace(options, progress=True)
    config = options.config()
    say = print if progress else (lambda *_: None)
    record = {
        "schema": RESULTS_SCHEMA,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command_line": command_line,
        "machine": machine_description(device),
        "scenes_version": SCENES_VERSION,
        "seed": seed,
        "methods": method_names,
        "sizes": {"reduced": reduced, "strand_stride": strand_stride, "num_vertices": num_vertices},
        "options": {"max_iterations": options.max_iterations, "patience": options.patience,
                    "record_every": options.record_every,
                    "reference_max_iterations": options.reference_max_iterations,
                    "reference_starts": options.reference_starts,
                    "energy_config": jsonable(config.__dict__)},
        "scenes": [],
    }
    for scene_name in scene_names:
        scene = comparison_scene(scene_name, reduced, strand_stride=strand_stride, num_vertices=num_vertices)
        frames = scene.frames(device=device)
        instances = {}
        for name in method_names:
            instances[name] = make(name, options)
        torch.manual_seed(seed)
        if scene.is_motion:
            # The motion's frame spacing is the implicit-Euler time step of the reference.
            rows, plot = _run_motion(scene, frames, instances, say, plots_dir)
        else:
            rows, plot = _run_static(scene, frames, instances, config, options.record_every, say), None
        entry = scene.describe()
        entry["results"] = rows
        entry["swing_plot"] = plot
        record["scenes"].append(entry)
    return record


def write_results(record: dict, path: str) -> str:
    """Write the results JSON (non-finite floats as strings) and return the path."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(jsonable(record), f, indent=1, allow_nan=False)
    return path


def _fmt(value, spec: str, scale: float = 1.0) -> str:
    if value is None:
        return "-"
    return format(value * scale, spec)


def markdown_tables(record: dict) -> str:
    """Table-1-style markdown: one table per scene (static and motion columns differ)."""
    machine = record["machine"]
    lines = [f"Device: {machine['device_name']} (`{machine['device']}`); scenes version "
             f"{record['scenes_version']}; torch {machine['torch']}, warp {machine['warp']}."]
    if record.get("command_line"):
        lines.append(f"Command: `{record['command_line']}`")
    lines.append("")
    for entry in record["scenes"]:
        size = entry["size"]
        lines.append(f"### {entry['name']}: {entry['description']}")
        lines.append(f"{size['strands']} strands x {size['vertices']} vertices, {size['frames']} frame(s).")
        lines.append("")
        if entry["kind"] == "static":
            lines.append("| method | ms/drape | penetration % | length change % | E / E* | distance to E*'s drape "
                         "mean / p95 [mm] | tip height vs E* [mm] | iterations (stop) |")
            lines.append("|---|---:|---:|---:|---:|---:|---:|---|")
            for r in entry["results"]:
                it = r["info"].get("iterations")
                stop = r["info"].get("stop_reason")
                its = "-" if it is None else f"{it} ({stop})"
                dist = f"{_fmt(r.get('mean_distance_mm'), '.1f')} / {_fmt(r.get('p95_distance_mm'), '.1f')}"
                lines.append(f"| {r['method']} | {_fmt(r['time_ms'], '.1f')} | {_fmt(r['penetration_percent'], '.2f')} | "
                             f"{_fmt(r['length_change_percent'], '.3f')} | {_fmt(r.get('energy_ratio'), '.3f')} | {dist} | "
                             f"{_fmt(r.get('tip_height_difference_mm'), '+.1f')} | {its} |")
        else:
            lines.append("| method | ms/frame | penetration % (mean / worst frame) | length change % | "
                         "distance to physics mean / worst frame [mm] | worst strands (p99, worst frame) [mm] | "
                         "tip swing [mm] (physics) | swing ratio | swing correlation | largest move a frame [mm] |")
            lines.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
            for r in entry["results"]:
                pen = f"{_fmt(r['penetration_percent'], '.2f')} / {_fmt(r['penetration_percent_max_frame'], '.2f')}"
                dist = f"{_fmt(r.get('mean_distance_mm'), '.1f')} / {_fmt(r.get('max_distance_mm'), '.1f')}"
                swing = f"{_fmt(r.get('swing_mm'), '.1f')} ({_fmt(r.get('physics_swing_mm'), '.1f')})"
                lines.append(f"| {r['method']} | {_fmt(r['time_ms'], '.1f')} | {pen} | "
                             f"{_fmt(r['length_change_percent'], '.3f')} | {dist} | "
                             f"{_fmt(r.get('strand_distance_p99_mm'), '.1f')} | {swing} | "
                             f"{_fmt(r.get('swing_amplitude_ratio'), '.2f')} | {_fmt(r.get('swing_correlation'), '+.2f')} | "
                             f"{_fmt(r.get('largest_step_mm'), '.1f')} |")
            if entry.get("swing_plot"):
                lines.append("")
                lines.append(f"Swing plot: `{entry['swing_plot']}`")
        lines.append("")
    return "\n".join(lines)
