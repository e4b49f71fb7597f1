"""Why the static drape lifts and splays, and why the dynamic network ignores the motion (issue 31, item 1).

The answers, figures and commands: docs/network_diagnosis.md. Each subcommand tests hypotheses with
the shipped checkpoint (`src/hairwarp/assets`) on the CPU at a reduced size, prints its figures and
writes OUT/<subcommand>_<what>.json (+ a PNG). The converged optimum E* of a drape is method
"reference"; the physics of a motion is method "physics".

- `static` (H-a representation ceiling, H-b loss balance): per scene, the rigid placement, the
  static network, L-BFGS 300, the optimum, and "oracle maps": the deformation map the static network
  outputs, optimised directly on the static energy (L-BFGS over the map, no network) through the same
  Eq. 2 lookup + taper + follow-the-leader projection, at 8 x 8 (the network's), without the taper,
  at 16 x 16 and 32 x 32, and one map per strand; the energy terms of every drape; lift (tip height)
  and splay (tip distance from the head's vertical axis) against the optimum.
- `sizes`: the optimum and the network on the same strands at several strand counts (the energy
  mixes means over vertices and sums over strands, so its optimum moves with the strand count while
  the network's drape of a strand does not).
- `training`: the static network on samples of its own training distribution (phase 3 of the shipped
  recipe's data) against a per-strand oracle: is it at its optimum where it was trained?
- `motion` (H-c): a motion scene: the physics, the dynamic network with the true motion, with the
  motion descriptors zeroed (a still body: the descriptors are pure velocities and accelerations),
  scaled as a training clip sampled every k frames presents them, run on every k-th frame as it was
  trained, with its GRU restarted every frame, and the static network per frame: distance between
  outputs [mm], tip swing, correlation with the physics.
- `rollout` (H-d): what a dynamic training step sees (the checkpoint's recipe, the code's lines),
  and the training loss (Eq. 6 over 3 warm-up + 4 rollout frames, each trajectory judged on its own
  history, h = k / 60 s) of the physics, the dynamic network, the static network and the rigid
  placement on the motion's frames; the per-term gradient norms w.r.t. the map at the network's
  outputs. Reuses `motion`'s cached trajectories (--cache) when they are there.
- `plot`: redraws every figure from the JSON files in --out.

    OMP_NUM_THREADS=1 python tools/diagnose_networks.py --out docs/network_diagnosis static --scenes table1,long_rest
    OMP_NUM_THREADS=1 python tools/diagnose_networks.py --out docs/network_diagnosis sizes
    OMP_NUM_THREADS=1 python tools/diagnose_networks.py --out docs/network_diagnosis training
    OMP_NUM_THREADS=1 python tools/diagnose_networks.py --out docs/network_diagnosis motion --scene whiplash
    OMP_NUM_THREADS=1 python tools/diagnose_networks.py --out docs/network_diagnosis rollout --scene whiplash
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

import numpy as np
import torch

# Scenes beyond the comparison scenes: a preset grown around the rest body, at rest.
GROWN_REST = {"long_rest": "long_straight", "bob_rest": "bob", "medium_rest_grown": "medium_wavy"}
# The energy terms, in the order of the figures.
TERMS = ("stretch", "bending", "auxiliary", "smoothness", "gravity", "root_alignment", "hair_body_contact",
         "hair_hair_contact", "inertia")
# Oracle variants: (grid cells per side or "strand", taper on).
ORACLES = {"map8": (8, True), "map8_warm": (8, True), "map8_notaper": (8, False), "map16": (16, True),
           "map32": (32, True), "strand": ("strand", True)}
# Shipped dynamic recipe (src/hairwarp/training/config.py defaults, the checkpoint's stored config).
_MM = 1e3


# ------------------------------------------------------------------------------------------ common
def machine(device: str) -> dict:
    """What ran it: CPU model, cores, torch and warp versions."""
    import warp

    cpu = platform.processor() or "cpu"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return {"device": device, "cpu": cpu, "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "warp": warp.config.version, "python": platform.python_version()}


def _rounded(value):
    """Floats to 6 significant digits, recursively (the results' files stay small)."""
    if isinstance(value, float):
        return float(f"{value:.6g}") if math.isfinite(value) else value
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return _rounded(value.item())
    return value


def write_json(out: str, name: str, data: dict) -> str:
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, name)
    with open(path, "w", encoding="utf-8") as f:
        json.dump(_rounded(data), f, indent=1, default=float)
    print(f"wrote {path}")
    return path


def load_scene(name: str, stride: int):
    """(scene, size dict) of a comparison scene or a `GROWN_REST` scene at every `stride`-th root."""
    if name in GROWN_REST:
        import hairwarp as hw

        scene = hw.default_scene(GROWN_REST[name], grow_around_body=True, strand_stride=stride)
        return scene, {"strands": scene.hairstyle.num_strands, "vertices": scene.hairstyle.strands.shape[1],
                       "frames": scene.num_frames, "strand_stride": stride,
                       "made_by": f"hw.default_scene({GROWN_REST[name]!r}, grow_around_body=True, strand_stride={stride})"}
    from hairwarp.evaluation.scenes import comparison_scene

    cs = comparison_scene(name, strand_stride=stride)
    return cs.scene, {**cs.size, "made_by": f"comparison_scene({name!r}, strand_stride={stride})"}


def energy_config(scene):
    from hairwarp.config import EnergyConfig

    return EnergyConfig().replace(time_step=1.0 / float(scene.motion.fps))


def energy_terms(x: torch.Tensor, inputs, config) -> dict:
    """Static energy (Eq. 5) terms per frame of drapes x (B, M, N, 3): {term: [B floats], "total": [...]}."""
    from hairwarp.energy import total_energy

    with torch.no_grad():
        r = total_energy(x, inputs, config)
    out = {k: v.double().tolist() for k, v in r.terms.items()}
    out["total"] = r.total.double().tolist()
    return out


def lift_and_splay(x: torch.Tensor, optimum: torch.Tensor, rigid: torch.Tensor) -> dict:
    """Per strand: tip height above the optimum's and tip distance from the head's vertical axis beyond
    the optimum's [mm] (the axis through the mean root, per frame); their profiles along the strand.
    """
    x, o = x.double(), optimum.double()
    centre = rigid[:, :, 0].double().mean(dim=1, keepdim=True)  # (B, 1, 3)

    def radial(p):  # (B, M, N) horizontal distance to the axis
        d = p - centre[:, :, None, :]
        return torch.sqrt(d[..., 0] ** 2 + d[..., 2] ** 2)

    dy = (x[..., 1] - o[..., 1]) * _MM
    dr = (radial(x) - radial(o)) * _MM
    return {"tip_lift_mm": float(dy[:, :, -1].mean()), "tip_splay_mm": float(dr[:, :, -1].mean()),
            "tip_lift_per_strand_mm": dy[:, :, -1].flatten().tolist(),
            "tip_splay_per_strand_mm": dr[:, :, -1].flatten().tolist(),
            "lift_profile_mm": dy.mean(dim=(0, 1)).tolist(), "splay_profile_mm": dr.mean(dim=(0, 1)).tolist()}


def drape_summary(x, optimum, frames, config, e_star) -> dict:
    """E / E*, energy gap to the rigid placement's, distance, lift, splay, penetration, terms of drapes x."""
    from hairwarp.metrics import frame_metrics, static_fidelity

    terms = energy_terms(x, frames.inputs, config)
    e = float(np.sum(terms["total"]))
    rigid_e = float(np.sum(energy_terms(frames.rigid.positions, frames.inputs, config)["total"]))
    fid = static_fidelity(x, optimum, e, e_star)
    metrics, _ = frame_metrics(x, frames)
    return {"energy": e, "energy_ratio": e / e_star, "energy_gap": (e - e_star) / (rigid_e - e_star),
            "mean_distance_mm": fid["mean_distance_mm"], "p95_distance_mm": fid["p95_distance_mm"],
            "penetration_percent": float(np.mean(metrics["penetration_percent"])),
            "length_change_percent": float(np.mean(metrics["length_change_percent"])),
            "terms": terms, **lift_and_splay(x, optimum, frames.rigid.positions)}


def cached(cache: str | None, key: str, fn):
    """fn() cached as CACHE/key.pt (positions and the like; None: no cache)."""
    if cache is None:
        return fn()
    path = os.path.join(cache, key + ".pt")
    if os.path.exists(path):
        return torch.load(path)
    value = fn()
    os.makedirs(cache, exist_ok=True)
    torch.save(value, path)
    return value


def method_positions(name: str, frames, *, max_iterations: int | None = None, simulate: bool = False,
                     reference_iterations: int | None = None):
    """Positions and seconds of a registered method on the frames."""
    from hairwarp.methods import MethodOptions, make
    from hairwarp.methods.base import REFERENCE_MAX_ITERATIONS

    method = make(name, MethodOptions(max_iterations=max_iterations,
                                      reference_max_iterations=reference_iterations or REFERENCE_MAX_ITERATIONS))
    start = time.perf_counter()
    result = method.simulate(frames) if simulate else method.drape(frames)
    return result.positions.detach(), time.perf_counter() - start


# ---------------------------------------------------------------------------------- the static network
def network_map(sim, frames) -> torch.Tensor:
    """The static network's deformation map (B, 8, 8, N, 3) [m] of the frames, in world axes (the
    canonical heading turned back), as `HairFormerSimulator.drape` applies it.
    """
    from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors

    net = sim.static
    rigid = frames.rigid.positions
    dtype = next(net.parameters()).dtype
    style = frames.scene.hairstyle
    z = sim.latent(style, rigid.device, dtype).expand(rigid.shape[0], -1)
    root_uv = style.root_uv.to(rigid.device)
    theta = frames.poses.to(dtype)
    angle = heading(theta)
    contact = net.contact_features(rigid.to(dtype), root_uv, frames.body_mesh)
    kwargs = {} if contact is None else {"contact": turn_contact_features(contact, -angle)}
    with torch.no_grad():
        d = net(z, frames.betas.to(dtype), turn_pose(theta, -angle), **kwargs)
    return turn_vectors(d, angle)


def strand_cells(root_uv: torch.Tensor, grid) -> tuple[torch.Tensor, int]:
    """(M,) cell of each strand and the cell count: the nearest lookup of Eq. 2, or one per strand."""
    from hairwarp.models.deformation import nearest_cell

    if grid == "strand":
        return torch.arange(root_uv.shape[0]), root_uv.shape[0]
    return nearest_cell(root_uv, grid, grid), grid * grid


def drape_from_cells(rigid, cell_map, cells, taper: bool):
    """Eq. 2 with a map of C cells (B, C, N, 3): rigid + map[cell(s)] * taper, then follow-the-leader."""
    from hairwarp.models.deformation import taper_weights
    from hairwarp.ops import follow_the_leader

    n = rigid.shape[2]
    w = taper_weights(n, dtype=rigid.dtype)
    if not taper:
        w = (w > 0).to(rigid.dtype)
    target = rigid + cell_map[:, cells] * w[:, None]
    return follow_the_leader(rigid.contiguous(), target.contiguous())


def optimise_cells(rigid, inputs, root_uv, config, grid, taper: bool, iterations: int, *, init=None, start=None,
                   dynamic: bool = False, record_every: int = 10) -> dict:
    """L-BFGS (strong Wolfe) over a deformation map of C cells through `drape_from_cells`, in the dtype of
    `rigid` (B, M, N, 3); `inputs` the matching `EnergyInputs` (with prev/prev2 when `dynamic`).

    Args:
        init: a starting map (B, cells, N, 3) or (B, g, g, N, 3); start: (B, M, N, 3) starting positions
            at the rest lengths (per-strand maps only); neither: the rigid placement.

    Returns {"positions" float32, "history": [[evaluation, energy, seconds]], "seconds", "evaluations", "cells"}.
    """
    from hairwarp.energy import total_energy
    from hairwarp.models.deformation import taper_weights

    cells, count = strand_cells(root_uv, grid)
    b, _, n, _ = rigid.shape
    dtype = rigid.dtype
    if start is not None:
        w = taper_weights(n, dtype=dtype)
        w = w if taper else (w > 0).to(dtype)
        d = ((start.to(dtype) - rigid) / w.clamp_min(1e-30)[:, None]) * (w > 0).to(dtype)[:, None]
    elif init is None:
        d = torch.zeros(b, count, n, 3, dtype=dtype)
    else:
        d = init.detach().to(dtype).reshape(b, count, n, 3).clone()
    d.requires_grad_(True)
    opt = torch.optim.LBFGS([d], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)
    history, evals, t0 = [], [0], time.perf_counter()

    def closure():
        opt.zero_grad()
        x = drape_from_cells(rigid, d, cells, taper)
        e = total_energy(x, inputs, config, dynamic=dynamic).total.sum()
        e.backward()
        evals[0] += 1
        if evals[0] % record_every == 1:
            history.append([evals[0], float(e.detach()), time.perf_counter() - t0])
        return e

    opt.step(closure)
    with torch.no_grad():
        x = drape_from_cells(rigid, d, cells, taper)
    return {"positions": x.float(), "history": history, "seconds": time.perf_counter() - t0,
            "evaluations": evals[0], "cells": count}


def optimise_map(frames, config, grid, taper: bool, iterations: int, init=None, record_every: int = 10,
                 start=None, prev=None, prev2=None) -> dict:
    """Oracle: `optimise_cells` in float64 on the static energy of scene frames (Eq. 6's, inertia
    included, when `prev` and `prev2` (B, M, N, 3) are given).
    """
    import dataclasses

    frames64 = frames.scene.frames(frames.frame_indices.tolist(), dtype=torch.float64)
    inputs = frames64.inputs
    if prev is not None:
        inputs = dataclasses.replace(inputs, prev=prev.double(), prev2=prev2.double())
    return optimise_cells(frames64.rigid.positions, inputs, frames64.scene.hairstyle.root_uv, config, grid, taper,
                          iterations, init=init, start=start, dynamic=prev is not None, record_every=record_every)

def finetune_network(sim, frames, config, steps: int, lr: float, record_every: int = 10) -> dict:
    """A copy of the static network trained by Adam on these frames alone (can it reach the oracle's energy?)."""
    import copy

    from hairwarp.energy import total_energy
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors

    net = copy.deepcopy(sim.static).train()
    net.requires_grad_(True)
    rigid = frames.rigid.positions
    style = frames.scene.hairstyle
    z = sim.latent(style, rigid.device, rigid.dtype).expand(rigid.shape[0], -1)
    theta = frames.poses.to(rigid.dtype)
    angle = heading(theta)
    contact = net.contact_features(rigid, style.root_uv, frames.body_mesh)
    kwargs = {} if contact is None else {"contact": turn_contact_features(contact, -angle).detach()}
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    history, start = [], time.perf_counter()
    for step in range(steps + 1):
        d = turn_vectors(net(z, frames.betas, turn_pose(theta, -angle), **kwargs), angle)
        x = apply_deformation(rigid, d, style.root_uv, net.config.length_projection)
        e = total_energy(x, frames.inputs, config).total.sum()
        if step % record_every == 0 or step == steps:
            history.append([step, float(e.detach()), time.perf_counter() - start])
        if step == steps:
            break
        opt.zero_grad()
        e.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
    return {"positions": x.detach(), "history": history, "seconds": time.perf_counter() - start}


def scans(frames, config, optimum, network, e_star) -> dict:
    """The energy along the line from the optimum to the network's drape and beyond it on both sides
    (x(s) = FTL(optimum + s (network - optimum))), and of the optimum shifted up or down (tapered along
    the strand, then projected): how asymmetric is the price of an error?
    """
    from hairwarp.energy import total_energy
    from hairwarp.metrics import penetration_percent
    from hairwarp.models.deformation import taper_weights
    from hairwarp.ops import follow_the_leader

    rigid = frames.rigid.positions
    w = taper_weights(rigid.shape[2], dtype=rigid.dtype)

    def score(target):
        x = follow_the_leader(rigid.contiguous(), target.contiguous())
        with torch.no_grad():
            e = float(total_energy(x, frames.inputs, config).total.sum())
        return {"energy_ratio": e / e_star, "penetration_percent": float(penetration_percent(x, frames.body_mesh).mean())}

    line = {f"{t:g}": score(optimum + t * (network - optimum)) for t in (-1.0, -0.5, -0.25, -0.1, 0.0, 0.1, 0.25, 0.5,
                                                                          0.75, 1.0, 1.25)}
    up = torch.zeros(3, dtype=rigid.dtype)
    up[1] = 1.0
    vertical = {f"{mm:g}": score(optimum + (mm / _MM) * w[:, None] * up) for mm in (-20, -10, -5, -2, 0, 2, 5, 10, 20)}
    return {"line_optimum_to_network": line, "vertical_shift_mm": vertical}


def within_cell_share(values: np.ndarray, cells: np.ndarray) -> float | None:
    """Share of the variance of a per-strand quantity that lies within the 8 x 8 cells (0: every
    strand of a cell alike, what a shared displacement gives; 1: nothing shared).
    """
    total = values.var()
    if total <= 0:
        return None
    within = sum(((values[cells == c] - values[cells == c].mean()) ** 2).sum() for c in np.unique(cells))
    return float(within / (values.size * total))


def cmd_static(args) -> None:
    """H-a and H-b on each scene (see the module docstring)."""
    from hairwarp.methods.networks import load_simulator
    from hairwarp.models.deformation import nearest_cell

    sim = load_simulator("static", None, torch.device(args.device))
    for name in args.scenes.split(","):
        scene, size = load_scene(name, args.strand_stride)
        frames = scene.frames(None if args.frames is None else [int(i) for i in args.frames.split(",")])
        config = energy_config(scene)
        tag = f"{name}_s{args.strand_stride}_f{'-'.join(map(str, frames.frame_indices.tolist()))}"
        print(f"== {name}: {size}")
        drapes, seconds = {}, {}
        drapes["rigid"] = frames.rigid.positions
        drapes["static"], seconds["static"] = method_positions("static", frames)
        if not args.skip_lbfgs:
            drapes["lbfgs300"], seconds["lbfgs300"] = cached(
                args.cache, f"lbfgs300_{tag}", lambda: method_positions("lbfgs", frames, max_iterations=300))
        ref_tag = tag if args.reference_iterations is None else f"{tag}_it{args.reference_iterations}"
        drapes["reference"], seconds["reference"] = cached(
            args.cache, f"reference_{ref_tag}",
            lambda: method_positions("reference", frames, reference_iterations=args.reference_iterations))
        net_map = network_map(sim, frames)
        check = drape_from_cells(frames.rigid.positions, net_map.reshape(net_map.shape[0], 64, *net_map.shape[3:]),
                                 nearest_cell(scene.hairstyle.root_uv, 8, 8), True)
        mismatch = float((check - drapes["static"]).norm(dim=-1).max()) * _MM
        print(f"network map re-applied: max {mismatch:.4f} mm from the method's drape")
        histories = {}
        for variant in args.oracles.split(","):
            if not variant:
                continue
            grid, taper = ORACLES[variant]
            init = net_map if variant == "map8_warm" else None
            res = optimise_map(frames, config, grid, taper, args.iterations, init=init)
            drapes[f"oracle_{variant}"] = res["positions"]
            seconds[f"oracle_{variant}"] = res["seconds"]
            histories[f"oracle_{variant}"] = {"history": res["history"], "evaluations": res["evaluations"],
                                              "cells": res["cells"]}
            print(f"oracle {variant}: {res['evaluations']} evaluations, {res['seconds']:.0f} s")
        if args.finetune_steps > 0:
            res = finetune_network(sim, frames, config, args.finetune_steps, args.finetune_lr)
            drapes["network_finetuned_here"] = res["positions"]
            seconds["network_finetuned_here"] = res["seconds"]
            histories["network_finetuned_here"] = {"history": [[h[0], h[1], h[2]] for h in res["history"]],
                                                   "steps": args.finetune_steps, "lr": args.finetune_lr}
            print(f"network fine-tuned here: {args.finetune_steps} steps, {res['seconds']:.0f} s")
        e_star = float(np.sum(energy_terms(drapes["reference"], frames.inputs, config)["total"]))
        rows = {}
        cells8 = nearest_cell(scene.hairstyle.root_uv, 8, 8).repeat(frames.rigid.positions.shape[0]).numpy()
        for key, x in drapes.items():
            rows[key] = drape_summary(x, drapes["reference"], frames, config, e_star)
            rows[key]["seconds"] = seconds.get(key)
            rows[key]["within_cell_share_of_tip_lift"] = within_cell_share(
                np.asarray(rows[key]["tip_lift_per_strand_mm"]), cells8)
            if key in histories:
                rows[key].update(histories[key])
            r = rows[key]
            print(f"{key:22s} E/E* {r['energy_ratio']:8.3f}  gap {r['energy_gap']:+.4f}  lift {r['tip_lift_mm']:+7.1f} "
                  f"splay {r['tip_splay_mm']:+7.1f} mm  dist {r['mean_distance_mm']:6.1f} mm  "
                  f"pen {r['penetration_percent']:.2f} %  len {r['length_change_percent']:.3f} %")
        scan = scans(frames, config, drapes["reference"], drapes["static"], e_star)
        print("E/E* from the optimum (0) to the network (1): " + "  ".join(
            f"{k}: {v['energy_ratio']:.3f}" for k, v in scan["line_optimum_to_network"].items()))
        print("E/E* of the optimum shifted vertically [mm]: " + "  ".join(
            f"{k}: {v['energy_ratio']:.3f}" for k, v in scan["vertical_shift_mm"].items()))
        best = min(r["energy"] for r in rows.values())
        for r in rows.values():
            r["energy_ratio_to_best"] = r["energy"] / best
        data = {"question": "H-a representation ceiling, H-b loss balance", "scene": name, "size": size,
                "best_energy": best, "best_drape": min(rows, key=lambda k: rows[k]["energy"]),
                "scans": scan,
                "frames": frames.frame_indices.tolist(), "machine": machine(args.device), "seed": args.seed,
                "command": " ".join(sys.argv), "oracle_iterations": args.iterations, "e_star": e_star,
                "reference_iterations": args.reference_iterations,
                "network_map_reapplied_max_mm": mismatch,
                "root_uv": scene.hairstyle.root_uv.tolist(), "cells8": cells8.tolist(), "drapes": rows}
        write_json(args.out, f"static_{tag}.json", data)
        plot_static(data, os.path.join(args.out, f"static_{tag}.png"))



def cmd_sizes(args) -> None:
    """The optimum and the static network on the same strands at several strand counts."""
    import hairwarp as hw
    from hairwarp.scene.scene import Scene

    strides = [int(v) for v in args.strides.split(",")]
    common = max(strides)
    rows = {}
    base_rigid = None
    # One groom grown at full size; each size keeps every stride-th of its strands (as the comparison
    # scenes do), so the common strands are the same strands at every size.
    full = hw.default_scene(GROWN_REST[args.scene], grow_around_body=True)
    for stride in strides:
        keep_all = torch.arange(0, full.hairstyle.num_strands, stride)
        scene = Scene(body=full.body, scalp=full.scalp, hairstyle=full.hairstyle.subset(keep_all),
                      motion=full.motion, name=f"{args.scene}/{stride}")
        size = {"strands": int(keep_all.numel()), "vertices": full.hairstyle.strands.shape[1], "frames": 1,
                "strand_stride": stride, "made_by": f"hw.default_scene({GROWN_REST[args.scene]!r}, grow_around_body=True)"
                f".hairstyle.subset(every {stride}th strand)"}
        frames = scene.frames(None)
        config = energy_config(scene)
        tag = f"{args.scene}_subset{stride}_f0"
        static, _ = method_positions("static", frames)
        ref, ref_s = cached(args.cache, f"reference_{tag}", lambda: method_positions("reference", frames))
        keep = list(range(0, size["strands"], common // stride))  # the roots every `common`-th
        rigid = frames.rigid.positions
        if base_rigid is None:
            base_rigid = rigid[:, keep]
        same = float((rigid[:, keep] - base_rigid).norm(dim=-1).max()) * _MM
        terms = {name: energy_terms(x, frames.inputs, config) for name, x in
                 (("rigid", rigid), ("static", static), ("reference", ref))}
        e_star = terms["reference"]["total"][0]
        row = {"size": size, "reference_seconds": ref_s, "common_strands": len(keep),
               "common_strands_rigid_max_difference_mm": same,
               "terms": terms,
               "energy_ratio": {name: terms[name]["total"][0] / e_star for name in ("rigid", "static")},
               "optimum_tip_above_rigid_mm": float((ref[:, keep, -1, 1] - rigid[:, keep, -1, 1]).mean()) * _MM,
               "network_tip_above_rigid_mm": float((static[:, keep, -1, 1] - rigid[:, keep, -1, 1]).mean()) * _MM,
               "network_tip_above_optimum_mm": float((static[:, keep, -1, 1] - ref[:, keep, -1, 1]).mean()) * _MM,
               "optimum_distance_to_rigid_mm": float((ref[:, keep, 2:] - rigid[:, keep, 2:]).norm(dim=-1).mean()) * _MM,
               "optimum_tips_per_common_strand_mm": (ref[0, keep, -1] * _MM).tolist(),
               "network_tips_per_common_strand_mm": (static[0, keep, -1] * _MM).tolist()}
        row["excess_per_strand"] = {name: (terms[name]["total"][0] - e_star) / size["strands"]
                                    for name in ("rigid", "static")}
        rows[stride] = row
        print(f"stride {stride:2d} ({size['strands']} strands): E/E* static {row['energy_ratio']['static']:.3f} "
              f"rigid {row['energy_ratio']['rigid']:.3f}; common strands: optimum tips "
              f"{row['optimum_tip_above_rigid_mm']:+.1f} mm above rigid, network "
              f"{row['network_tip_above_rigid_mm']:+.1f} mm ({same:.3f} mm rigid mismatch)")
    base = rows[strides[0]]
    for stride, row in rows.items():
        a = np.asarray(row["optimum_tips_per_common_strand_mm"])
        b = np.asarray(base["optimum_tips_per_common_strand_mm"])
        row["optimum_tips_moved_vs_first_stride_mm"] = float(np.linalg.norm(a - b, axis=-1).mean())
        a = np.asarray(row["network_tips_per_common_strand_mm"])
        b = np.asarray(base["network_tips_per_common_strand_mm"])
        row["network_tips_moved_vs_first_stride_mm"] = float(np.linalg.norm(a - b, axis=-1).mean())
    data = {"question": "does the optimum move with the strand count (sums vs means in the energy)?",
            "scene": args.scene, "strides": strides, "machine": machine(args.device), "seed": args.seed,
            "command": " ".join(sys.argv), "size": rows[strides[-1]]["size"], "rows": rows}
    write_json(args.out, f"sizes_{args.scene}.json", data)
    plot_sizes(data, os.path.join(args.out, f"sizes_{args.scene}.png"))


def cmd_training(args) -> None:
    """The static network on samples of its own training distribution (phase 3 of the shipped recipe's
    data: 16 x 16 roots, half the hairstyles grown around the body, 30 % long hair), against a per-strand
    oracle (L-BFGS over every strand's map with the projection: E* here).
    """
    from hairwarp.energy import total_energy
    from hairwarp.methods.networks import load_simulator
    from hairwarp.metrics import penetration_percent
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.training.config import DataConfig
    from hairwarp.training.data import TrainingSampler

    sim = load_simulator("static", None, torch.device(args.device))
    net = sim.static
    config = DataConfig(strand_stride=2, long_hair_fraction=0.3, grown_hair_fraction=0.5,
                        hairstyle_cache_size=64, pose_cache_size=64)
    sampler = TrainingSampler(config, seed=args.seed)
    from hairwarp.config import EnergyConfig

    energy = EnergyConfig()
    rows = []
    for i in range(args.samples):
        batch = sampler.static_batch(args.first_step + i, 3, 1.0, 1, num_hairstyles=512)
        contact = net.contact_features(batch.rigid, batch.root_uv, batch.inputs.body)
        with torch.no_grad():
            d = net(batch.z, batch.betas, batch.poses, contact=contact)
        x = apply_deformation(batch.rigid, d, batch.root_uv, net.config.length_projection)
        oracle = optimise_cells(batch.rigid, batch.inputs, batch.root_uv, energy, "strand", True, args.iterations)
        o = oracle["positions"]
        with torch.no_grad():
            e = {name: float(total_energy(p, batch.inputs, energy).total.sum())
                 for name, p in (("rigid", batch.rigid), ("network", x), ("oracle", o))}
        sid = batch.hairstyle_ids[0]
        length = float((batch.strands[0, :, 1:] - batch.strands[0, :, :-1]).norm(dim=-1).sum(-1).mean())
        row = {"step": args.first_step + i, "hairstyle": sid, "grown": bool(sampler.is_grown(sid)),
               "mean_strand_length_m": length, "energy": e,
               "energy_ratio_network": e["network"] / e["oracle"], "energy_ratio_rigid": e["rigid"] / e["oracle"],
               "penetration_rigid": float(penetration_percent(batch.rigid, batch.inputs.body).mean()),
               "penetration_network": float(penetration_percent(x, batch.inputs.body).mean()),
               **{k: v for k, v in lift_and_splay(x, o, batch.rigid).items() if not k.endswith("per_strand_mm")
                  and not k.endswith("profile_mm")},
               "oracle_evaluations": oracle["evaluations"], "oracle_seconds": oracle["seconds"]}
        rows.append(row)
        print(f"sample {i}: hairstyle {sid} ({'grown' if row['grown'] else 'decoded'}, {length:.2f} m): E/E* network "
              f"{row['energy_ratio_network']:.3f} rigid {row['energy_ratio_rigid']:.3f}; pen rigid "
              f"{row['penetration_rigid']:.2f} % network {row['penetration_network']:.2f} %; lift "
              f"{row['tip_lift_mm']:+.1f} splay {row['tip_splay_mm']:+.1f} mm")
    ratios = np.asarray([r["energy_ratio_network"] for r in rows])
    data = {"question": "is the static network at its optimum on its own training distribution?",
            "data_config": {"strand_stride": 2, "long_hair_fraction": 0.3, "grown_hair_fraction": 0.5, "phase": 3,
                            "hairstyles": 512},
            "oracle": f"per-strand map + taper + follow-the-leader, L-BFGS {args.iterations} iterations, float32",
            "size": {"strands": sampler.num_strands, "vertices": sampler.num_vertices},
            "machine": machine(args.device), "seed": args.seed, "command": " ".join(sys.argv), "samples": rows,
            "median_energy_ratio_network": float(np.median(ratios))}
    print(f"median E/E* of the network on its training distribution: {np.median(ratios):.3f}")
    write_json(args.out, "training_distribution.json", data)
    plot_training(data, os.path.join(args.out, "training_distribution.png"))


# ---------------------------------------------------------------------------------- the dynamic network
def descriptor_scale(k: float, dim: int) -> torch.Tensor:
    """(D,) factors that turn frame-rate descriptors into those of the same motion sampled every k frames
    and played at dt = 1/60 s, as training presents a clip of interval k: velocities x k, accelerations x k^2.
    """
    from hairwarp.scene.motion import DESCRIPTOR_SLICES

    scale = torch.ones(dim, dtype=torch.float64)
    scale[DESCRIPTOR_SLICES["joint_angular_velocity"]] = k
    scale[DESCRIPTOR_SLICES["gravity_velocity"]] = k
    scale[DESCRIPTOR_SLICES["joint_acceleration"]] = k * k
    return scale


def dynamic_run(sim, frames, *, every: int = 1, motion_scale=None, reset: bool = False) -> dict:
    """The dynamic network over the scene's frames 0, every, 2 every, ... as `simulate_poses` runs it
    (canonical heading, GRU carried), with the descriptors of that subsampled sequence at dt = 1/fps (a
    training clip's convention), optionally multiplied by `motion_scale` (a number or (D,) factors), or
    with the GRU restarted from zero at every frame (`reset`).

    Returns {"frames": indices, "positions" (T', M, N, 3), "hidden" (T', d_m), "fused_norm": ...}.
    """
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.models.heading import heading, turn_contact_features, turn_pose, turn_vectors
    from hairwarp.scene.motion import motion_descriptor_windows

    dyn = sim.dynamic
    scene = frames.scene
    idx = list(range(0, frames.rigid.positions.shape[0], every))
    rigid = frames.rigid.positions[idx]
    t = len(idx)
    dtype = next(dyn.parameters()).dtype
    poses64 = scene.motion.poses[frames.frame_indices[idx].cpu()].double()
    betas = frames.betas[:1].to(dtype)
    angle = heading(poses64[:1])
    poses64 = turn_pose(poses64, -angle.expand(t))
    motion = motion_descriptor_windows(poses64, betas[0].double(), 1.0 / float(scene.motion.fps),
                                       dyn.config.window, include_betas=False)
    if motion_scale is not None:
        motion = motion * torch.as_tensor(motion_scale, dtype=torch.float64)
    motion = motion.to(dtype)[None]
    z = sim.latent(scene.hairstyle, rigid.device, dtype)
    root_uv = scene.hairstyle.root_uv
    angles = angle.to(dtype).expand(t)
    body = frames.body_mesh
    contact = dyn.contact_features(frames.rigid.positions.to(dtype), root_uv, body)
    contact = turn_contact_features(contact[idx], -angles)
    poses = poses64.to(dtype)[None]
    with torch.no_grad():
        if reset:
            outs = [dyn.simulate(z, betas, poses[:, i:i + 1], motion[:, i:i + 1], contact=contact[None, i:i + 1])
                    for i in range(t)]
            maps = torch.cat([o.deformation_map[0] for o in outs])
            hidden = torch.cat([o.hidden for o in outs])
        else:
            hidden_list, h = [], None
            for i in range(t):
                h = dyn.encode_motion(motion[:, i], betas, h)
                hidden_list.append(h)
            hidden = torch.cat(hidden_list)
            maps = dyn.simulate(z, betas, poses, motion, contact=contact[None]).deformation_map[0]
    maps = turn_vectors(maps, angles)
    x = apply_deformation(rigid.to(dtype), maps, root_uv, dyn.config.static.length_projection)
    return {"frames": idx, "positions": x.to(rigid.dtype), "hidden": hidden, "maps": maps}


def _moving_mm(a: torch.Tensor, b: torch.Tensor) -> list:
    """Per-frame mean distance [mm] over the moving vertices 2..N-1."""
    return ((a[:, :, 2:] - b[:, :, 2:]).norm(dim=-1).mean(dim=(1, 2)) * _MM).tolist()


def training_descriptor_rms(window: int = 10) -> dict:
    """RMS of the descriptor slices of the training pool's procedural motions (the base variant of each)
    sampled every k = 1..5 frames at dt = 1/60 s (k = 1: what inference shows).
    """
    from hairwarp.scene.motion import DESCRIPTOR_SLICES, motion_descriptor_windows, procedural_motion
    from hairwarp.training.config import DataConfig

    out = {}
    for k in range(1, 6):
        per = {name: [] for name in ("joint_angular_velocity", "gravity_velocity", "joint_acceleration")}
        for name in DataConfig().motions:
            m = procedural_motion(name)
            for offset in range(k):
                d = motion_descriptor_windows(m.poses[offset::k].double(), m.betas.double(), 1.0 / m.fps, window,
                                              include_betas=False)[:, -1]
                for key in per:
                    per[key].append(d[:, DESCRIPTOR_SLICES[key]])
        out[k] = {key: float(torch.cat(v).square().mean().sqrt()) for key, v in per.items()}
    return out


def _motion_frames(args):
    """(scene, size, frames, T, tag) of a motion command: the scene's first `--frames` frames."""
    scene, size = load_scene(args.scene, args.strand_stride)
    frames = scene.frames(None if args.frames is None else list(range(args.frames)))
    t = frames.rigid.positions.shape[0]
    size["frames"] = t
    return scene, size, frames, t, f"{args.scene}_s{args.strand_stride}_t{t}"


def cmd_motion(args) -> None:
    """H-c on one motion scene (see the module docstring)."""
    from hairwarp.methods.networks import load_simulator
    from hairwarp.metrics import mean_tip_offset, motion_fidelity
    from hairwarp.scene.motion import DESCRIPTOR_DIM_NO_BETAS

    scene, size, frames, t, tag = _motion_frames(args)
    print(f"== {args.scene}: {size}")
    sim = load_simulator("dynamic", None, torch.device(args.device))
    rigid = frames.rigid.positions
    physics, physics_s = cached(args.cache, f"physics_{tag}", lambda: method_positions("physics", frames, simulate=True))
    print(f"physics: {physics_s:.0f} s")
    static, _ = cached(args.cache, f"static_{tag}", lambda: method_positions("static", frames))
    shipped, _ = method_positions("dynamic", frames, simulate=True)
    runs = {"dynamic": dynamic_run(sim, frames)}
    check = float((runs["dynamic"]["positions"] - shipped).norm(dim=-1).max()) * _MM
    print(f"dynamic re-run vs the method: max {check:.4f} mm")
    runs["zero_motion"] = dynamic_run(sim, frames, motion_scale=0.0)
    runs["gru_reset"] = dynamic_run(sim, frames, reset=True)
    for k in args.ks:
        runs[f"descriptors_as_k{k}"] = dynamic_run(sim, frames, motion_scale=descriptor_scale(k, DESCRIPTOR_DIM_NO_BETAS))
        runs[f"every_k{k}"] = dynamic_run(sim, frames, every=k)
    for scale in (10.0, 100.0):
        runs[f"motion_x{scale:g}"] = dynamic_run(sim, frames, motion_scale=scale)
    cached(args.cache, f"dynamic_{tag}", lambda: runs["dynamic"]["positions"])
    rows = {}
    for key, x in [("physics", physics), ("static", static), ("rigid", rigid)]:
        fid = motion_fidelity(x, physics, rigid)
        rows[key] = {**{k: v for k, v in fid.items() if k != "per_frame_distance_mm"},
                     "distance_to_physics_per_frame_mm": fid["per_frame_distance_mm"],
                     "mean_tip_offset_mm": (mean_tip_offset(x, rigid) * _MM).tolist(), "frames": list(range(t))}
    for key, run in runs.items():
        idx = run["frames"]
        x = run["positions"]
        fid = motion_fidelity(x, physics[idx], rigid[idx])
        hidden = run["hidden"]
        rows[key] = {**{k: v for k, v in fid.items() if k != "per_frame_distance_mm"},
                     "distance_to_physics_per_frame_mm": fid["per_frame_distance_mm"],
                     "distance_to_dynamic_per_frame_mm": _moving_mm(x, runs["dynamic"]["positions"][idx])
                     if len(idx) == t else None,
                     "distance_to_static_per_frame_mm": _moving_mm(x, static[idx]),
                     "hidden_norm": hidden.norm(dim=-1).tolist(),
                     "hidden_change_vs_dynamic": ((hidden - runs["dynamic"]["hidden"]).norm(dim=-1)
                                                  / runs["dynamic"]["hidden"].norm(dim=-1)).tolist()
                     if len(idx) == t else None,
                     "mean_tip_offset_mm": (mean_tip_offset(x, rigid[idx]) * _MM).tolist(), "frames": idx}
        if len(idx) < t:  # the same subsampled frames for the static network: its swing there
            rows[key]["static_on_these_frames"] = {k: v for k, v in motion_fidelity(static[idx], physics[idx],
                                                                                    rigid[idx]).items()
                                                   if k != "per_frame_distance_mm"}
    for key, r in rows.items():
        extra = ""
        if r.get("distance_to_dynamic_per_frame_mm"):
            extra = (f"  vs dynamic {np.mean(r['distance_to_dynamic_per_frame_mm']):6.2f} mm"
                     f" (max {np.max(r['distance_to_dynamic_per_frame_mm']):.2f})")
        corr = r["swing_correlation"]
        ratio = r["swing_amplitude_ratio"]
        print(f"{key:20s} to physics {r['mean_distance_mm']:6.1f} mm  swing {r['swing_mm']:6.1f} mm "
              f"(physics {r['physics_swing_mm']:.1f})  ratio {ratio if ratio is None else round(ratio, 2)}  "
              f"corr {corr if corr is None else round(corr, 3)}{extra}")
    # Frames whose descriptor window is all zero (the body has stood still for T_w frames): every input
    # of the network but its GRU state is then constant, while the physics hair keeps swinging.
    from hairwarp.scene.motion import motion_descriptor_windows

    windows = motion_descriptor_windows(scene.motion.poses[frames.frame_indices].double(), frames.betas[0].double(),
                                        1.0 / float(scene.motion.fps), sim.dynamic.config.window, include_betas=False)
    moving = [i for i in range(t) if float(windows[i].abs().max()) >= 1e-9]
    still = list(range(moving[-1] + 1, t)) if moving else []  # the last frames, once the body stopped
    after_stop = {}
    if len(still) > 1:
        for key, x in (("physics", physics), ("dynamic", runs["dynamic"]["positions"]), ("static", static)):
            tips = x[still, :, -1]
            after_stop[key] = float((tips - tips[:1]).norm(dim=-1).square().mean().sqrt()) * _MM
        print(f"last {len(still)} frames with the body still for the whole window (from frame {still[0]}): tips move "
              + ", ".join(f"{k} {v:.1f} mm RMS" for k, v in after_stop.items()))
    data = {"question": "H-c: does the motion reach the dynamic network's output?", "scene": args.scene,
            "still_frames": still, "tip_motion_while_still_mm": after_stop,
            "size": size, "machine": machine(args.device), "seed": args.seed, "command": " ".join(sys.argv),
            "physics_seconds": physics_s, "dynamic_rerun_max_mm": check, "runs": rows,
            "descriptor_rms_training_motions": training_descriptor_rms(sim.dynamic.config.window)}
    write_json(args.out, f"motion_{tag}.json", data)
    plot_motion(data, os.path.join(args.out, f"motion_{tag}.png"))


def code_facts() -> dict:
    """Where the dynamic training's history comes from, read from the source (file:line)."""
    import inspect

    from hairwarp.training import dynamic as training_dynamic

    path = os.path.relpath(inspect.getsourcefile(training_dynamic))
    lines, first = inspect.getsourcelines(training_dynamic._dynamic_loss)

    def where(text):
        hits = [first + i for i, line in enumerate(lines) if text in line]
        return f"{path}:{hits[0]}" if hits else None

    return {"warm_up_without_gradient": where("with torch.no_grad():"),
            "warm_up_drapes_by_the_network": where("warm = model.simulate("),
            "rollout_by_the_network": where("out = model.simulate("),
            "history_of_eq16": where("inertia_history(warm_positions"),
            "history_detached": f"{path}:{inspect.getsourcelines(training_dynamic.inertia_history)[1]}"
                                " (inertia_history: warm-up[-2:] + rollout positions, .detach())",
            "interval_time_step": where('inertia_time_step == "interval"')}


def swing_extrema(offset_mm: np.ndarray) -> dict:
    """Frames of the lowest and highest value of the dominant mean-subtracted tip-offset component, and the
    frames between them (a lower bound of the swing's half period when the window holds one swing).
    """
    comp = int(np.argmax((offset_mm - offset_mm.mean(0)).std(0)))
    y = offset_mm[:, comp]
    lo, hi = int(np.argmin(y)), int(np.argmax(y))
    return {"axis": "xyz"[comp], "min_frame": lo, "max_frame": hi, "frames_between": abs(hi - lo),
            "peak_to_peak_mm": float(y.max() - y.min())}

def windowed_loss(trajectory: torch.Tensor, scene, config, k: int, warmup: int, rollout: int) -> dict:
    """The dynamic training loss of a trajectory (T, M, N, 3) judged on its own history: Eq. 5 + Eq. 16
    at h = k / fps for every frame f that a window of `warmup` + `rollout` frames spaced k apart can hold
    as a rollout frame (f >= warmup k), with P(f - k), P(f - 2k) of the same trajectory. Means over them.
    """
    import dataclasses

    from hairwarp.energy import total_energy

    t = trajectory.shape[0]
    fs = list(range(warmup * k, t))
    if not fs:
        return {}
    frames = scene.frames(fs)
    cfg = config.replace(time_step=k / float(scene.motion.fps))
    inputs = dataclasses.replace(frames.inputs, prev=trajectory[[f - k for f in fs]],
                                 prev2=trajectory[[f - 2 * k for f in fs]])
    with torch.no_grad():
        static = total_energy(trajectory[fs], inputs, cfg).total
        inertia = total_energy(trajectory[fs], inputs, cfg, dynamic=True, terms=("inertia",)).total
    return {"frames": len(fs), "static": float(static.mean()), "inertia": float(inertia.mean()),
            "total": float((static + inertia).mean()), "inertia_per_frame": inertia.tolist()}


def term_gradients(maps: torch.Tensor, trajectory: torch.Tensor, scene, config, k: int, fs: list,
                   projection: str) -> dict:
    """Per-term |dE/dD| w.r.t. the deformation maps D of frames fs (Eq. 6 at h = k / fps, the history the
    trajectory's own, detached) and each term's cosine with the total's, summed over the frames.
    """
    import dataclasses

    from hairwarp.config import ALL_TERMS
    from hairwarp.energy import total_energy
    from hairwarp.models.deformation import apply_deformation

    frames = scene.frames(fs)
    cfg = config.replace(time_step=k / float(scene.motion.fps))
    inputs = dataclasses.replace(frames.inputs, prev=trajectory[[f - k for f in fs]].detach(),
                                 prev2=trajectory[[f - 2 * k for f in fs]].detach())
    grads = {}
    for term in [*ALL_TERMS, None]:
        d = maps[fs].detach().clone().requires_grad_(True)
        x = apply_deformation(frames.rigid.positions, d, scene.hairstyle.root_uv, projection)
        e = total_energy(x, inputs, cfg, dynamic=True, terms=None if term is None else (term,)).total.sum()
        (g,) = torch.autograd.grad(e, d)
        grads["total" if term is None else term] = g.flatten().double()
    total = grads["total"]
    return {name: {"norm": float(g.norm()), "cosine_with_total": float(g @ total / (g.norm() * total.norm()))
                   if float(g.norm()) > 0 else 0.0} for name, g in grads.items()}


def cmd_rollout(args) -> None:
    """H-d on one motion scene (see the module docstring)."""
    from hairwarp.methods.networks import load_simulator, shipped_checkpoint
    from hairwarp.metrics import mean_tip_offset, motion_fidelity
    from hairwarp.models.checkpoint import load_checkpoint

    scene, size, frames, t, tag = _motion_frames(args)
    config = energy_config(scene)
    sim = load_simulator("dynamic", None, torch.device(args.device))
    ckpt = load_checkpoint(shipped_checkpoint("hairformer_dynamic.pt"))
    recipe = ckpt.extra.get("training_config", {})
    warmup, rollout = recipe.get("warmup_frames", 3), recipe.get("rollout_frames", 4)
    kmin, kmax = recipe.get("subsample_min", 2), recipe.get("subsample_max", 5)
    fps = float(scene.motion.fps)
    rigid = frames.rigid.positions
    physics, _ = cached(args.cache, f"physics_{tag}", lambda: method_positions("physics", frames, simulate=True))
    static, _ = cached(args.cache, f"static_{tag}", lambda: method_positions("static", frames))
    run = dynamic_run(sim, frames)
    dynamic, maps = run["positions"], run["maps"]
    trajectories = {"physics": physics, "dynamic": dynamic, "static": static, "rigid": rigid}
    phys_offset = (mean_tip_offset(physics, rigid) * _MM).numpy()
    facts = {
        "checkpoint_recipe": {key: recipe.get(key) for key in ("warmup_frames", "rollout_frames", "subsample_min",
                                                               "subsample_max", "window", "inertia_time_step",
                                                               "learning_rate", "batch_size", "grad_clip_norm",
                                                               "energy")},
        "checkpoint_model": {"func_reg_weight": ckpt.model.config.func_reg_weight,
                             "fusion": ckpt.model.config.fusion},
        "code": code_facts(),
        "sequence_frames": warmup + rollout,
        "sequence_span_s": {k: (warmup + rollout - 1) * k / fps for k in range(kmin, kmax + 1)},
        "rollout_span_with_gradient_s": {k: (rollout - 1) * k / fps for k in range(kmin, kmax + 1)},
        "gru_steps_with_gradient": rollout,
        "descriptor_time_step_s": 1.0 / fps,
        "physics_swing_extrema": swing_extrema(phys_offset),
    }
    print(json.dumps(facts, indent=1))
    losses = {}
    for k in range(1, kmax + 1):
        if warmup * k >= t:  # no window of interval k fits in the frames
            continue
        losses[k] = {name: windowed_loss(x, scene, config, k, warmup, rollout) for name, x in trajectories.items()}
        print(f"k={k}: " + "  ".join(f"{n} {v['total']:.5f} (static {v['static']:.5f} + inertia {v['inertia']:.2e})"
                                     for n, v in losses[k].items()))
    # What a training step pulls the network towards: per frame, Eq. 6's minimiser from its own history.
    k = args.target_k
    fs = list(range(warmup * k, t, args.target_every))
    target_frames = scene.frames(fs)
    prev, prev2 = dynamic[[f - k for f in fs]], dynamic[[f - 2 * k for f in fs]]
    cfg_k = config.replace(time_step=k / fps)
    targets = {}
    for name, kwargs in (("eq6_target", {"prev": prev, "prev2": prev2}), ("eq5_target", {})):
        res = optimise_map(target_frames, cfg_k, "strand", True, args.target_iterations, start=dynamic[fs], **kwargs)
        x = res["positions"]
        fid = motion_fidelity(x, physics[fs], rigid[fs])
        targets[name] = {"distance_to_network_mm": float(np.mean(_moving_mm(x, dynamic[fs]))),
                         "distance_to_physics_mm": fid["mean_distance_mm"], "swing_mm": fid["swing_mm"],
                         "swing_correlation": fid["swing_correlation"],
                         "swing_amplitude_ratio": fid["swing_amplitude_ratio"],
                         "mean_tip_offset_mm": (mean_tip_offset(x, rigid[fs]) * _MM).tolist(),
                         "evaluations": res["evaluations"], "seconds": res["seconds"], "positions": x}
    inertia_part = targets["eq6_target"]["positions"] - targets["eq5_target"]["positions"]
    net_fid = motion_fidelity(dynamic[fs], physics[fs], rigid[fs])
    target_summary = {
        "k": k, "frames": fs, "iterations": args.target_iterations,
        "network": {"distance_to_physics_mm": net_fid["mean_distance_mm"], "swing_mm": net_fid["swing_mm"],
                    "swing_correlation": net_fid["swing_correlation"],
                    "mean_tip_offset_mm": (mean_tip_offset(dynamic[fs], rigid[fs]) * _MM).tolist()},
        "physics": {"mean_tip_offset_mm": (mean_tip_offset(physics[fs], rigid[fs]) * _MM).tolist(),
                    "swing_mm": net_fid["physics_swing_mm"]},
        "inertia_share_of_target_mm": float(inertia_part[:, :, 2:].norm(dim=-1).mean()) * _MM,
        "network_to_physics_mm": float(np.mean(_moving_mm(dynamic[fs], physics[fs]))),
        **{name: {key: v for key, v in r.items() if key != "positions"} for name, r in targets.items()}}
    for name in ("eq6_target", "eq5_target"):
        r = target_summary[name]
        print(f"{name}: {r['distance_to_network_mm']:.2f} mm from the network, {r['distance_to_physics_mm']:.1f} mm "
              f"from the physics, swing corr {r['swing_correlation']}")
    print(f"inertia's share of the target: {target_summary['inertia_share_of_target_mm']:.2f} mm; "
          f"network to physics {target_summary['network_to_physics_mm']:.1f} mm")
    projection = sim.dynamic.config.static.length_projection
    gradients = {kk: term_gradients(maps, dynamic, scene, config, kk, list(range(warmup * kk, t)), projection)
                 for kk in (1, 3)}
    for kk, g in gradients.items():
        print(f"k={kk} |dE/dD|: " + "  ".join(f"{n} {v['norm']:.2e} ({v['cosine_with_total']:+.2f})"
                                             for n, v in g.items()))
    log = []
    log_path = os.path.join("docs", "results", "train_dynamic_grown_h100_log.jsonl")
    if os.path.exists(log_path):
        with open(log_path, encoding="utf-8") as f:
            log = [json.loads(line) for line in f if line.strip()]
    data = {"question": "H-d: does the dynamic training roll out its own predictions, and what does its loss reward?",
            "scene": args.scene, "size": size, "machine": machine(args.device), "seed": args.seed,
            "command": " ".join(sys.argv), "facts": facts, "windowed_loss": losses, "targets": target_summary,
            "gradients": gradients, "physics_mean_tip_offset_mm": phys_offset.tolist(),
            "training_log": {"source": log_path, "steps": len(log),
                             "terms_last_50_mean": {key: float(np.mean([r["terms"][key] for r in log[-50:]]))
                                                    for key in (log[-1]["terms"] if log else {})},
                             "loss_first_20_mean": float(np.mean([r["loss"] for r in log[:20]])) if log else None,
                             "loss_last_20_mean": float(np.mean([r["loss"] for r in log[-20:]])) if log else None}}
    write_json(args.out, f"rollout_{tag}.json", data)
    plot_rollout(data, os.path.join(args.out, f"rollout_{tag}.png"))

# ------------------------------------------------------------------------------------------ figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _footer(fig, data) -> None:
    m = data["machine"]
    size = data.get("size", {})
    fig.text(0.01, 0.005, f"{m['cpu_count']}-core CPU ({m['cpu']}), torch {m['torch']}, warp {m['warp']}, "
             f"{torch.get_num_threads()} thread; {size.get('strands')} strands x {size.get('vertices')} vertices; "
             f"{data['command']}", fontsize=6)


def _save(fig, data, path: str, bottom: float = 0.03) -> None:
    """The machine footer, then the figure (its axes above `bottom`) written to `path` and closed."""
    _footer(fig, data)
    fig.tight_layout(rect=(0, bottom, 1, 1))
    fig.savefig(path, dpi=90)
    _plt().close(fig)
    print(f"wrote {path}")


def plot_static(data: dict, path: str) -> None:
    """Six panels: E / E*, energy terms against the optimum's, tip lift over the scalp (network and the
    8 x 8 oracle), lift along the strand, the oracles' convergence.
    """
    plt = _plt()
    rows = data["drapes"]
    keys = [k for k in rows if k != "reference"]
    fig, ax = plt.subplots(2, 4, figsize=(22, 9.5))
    a = ax[0, 0]
    ratios = [rows[k]["energy_ratio"] for k in keys]
    a.barh(keys, ratios, color=["tab:red" if k == "static" else "tab:blue" for k in keys])
    if max(ratios) > 5:
        a.set_xscale("log")
        a.xaxis.set_minor_formatter(plt.NullFormatter())
    else:
        a.set_xlim(min(0.8, min(ratios) - 0.05), max(ratios) * 1.1)
    a.axvline(1.0, color="k", lw=0.8)
    a.axvline(1.05, color="g", lw=0.8, ls="--")
    for i, r in enumerate(ratios):
        a.text(r, i, f" {r:.3f}", va="center", fontsize=7)
    a.set_title(f"a) {data['scene']}: E / E* (E* = reference {data['e_star']:.4g})", fontsize=9)
    a = ax[0, 1]
    shown = [k for k in ("static", "lbfgs300", "oracle_map8", "oracle_map8_warm", "oracle_strand") if k in rows]
    terms = [t for t in TERMS if t in rows["reference"]["terms"]]
    width = 0.8 / max(len(shown), 1)
    for j, k in enumerate(shown):
        diff = [np.sum(rows[k]["terms"][t]) - np.sum(rows["reference"]["terms"][t]) for t in terms]
        a.bar(np.arange(len(terms)) + j * width, diff, width, label=k)
    a.set_yscale("symlog", linthresh=1e-4)
    a.set_xticks(np.arange(len(terms)) + 0.4, [t.replace("_", "\n") for t in terms], fontsize=7)
    a.axhline(0, color="k", lw=0.6)
    a.legend(fontsize=7)
    a.set_title("b) energy term minus the optimum's (summed over frames)", fontsize=9)
    uv = np.asarray(data["root_uv"])
    m = uv.shape[0]
    for a, key, title in ((ax[0, 2], "static", "c) network"), (ax[1, 0], "oracle_map8", "d) 8 x 8 oracle map")):
        if key not in rows:
            a.axis("off")
            continue
        lift = np.asarray(rows[key]["tip_lift_per_strand_mm"])[:m]
        lim = max(1.0, float(np.percentile(np.abs(lift), 98)))
        sc = a.scatter(uv[:, 0], uv[:, 1], c=lift, cmap="coolwarm", vmin=-lim, vmax=lim, s=18)
        for k in range(1, 8):
            a.axhline(k / 8, color="gray", lw=0.3)
            a.axvline(k / 8, color="gray", lw=0.3)
        fig.colorbar(sc, ax=a, label="tip height above the optimum's [mm]")
        share = rows[key]["within_cell_share_of_tip_lift"]
        a.set_title(f"{title}: tip lift per strand by root UV (frame {data['frames'][0]}); "
                    f"within-cell variance {share if share is None else round(share, 2)}", fontsize=8)
        a.set_xlabel("u")
        a.set_ylabel("v")
    a = ax[1, 1]
    for k in ("rigid", "static", "lbfgs300", "oracle_map8", "oracle_map8_notaper", "oracle_map32", "oracle_strand"):
        if k in rows:
            a.plot(rows[k]["lift_profile_mm"], label=f"{k} height")
            a.plot(rows[k]["splay_profile_mm"], ls=":", color=a.lines[-1].get_color())
    a.axhline(0, color="k", lw=0.6)
    a.set_xlabel("vertex index")
    a.set_ylabel("vs the optimum [mm] (solid: height, dotted: radial)")
    a.legend(fontsize=7)
    a.set_title("e) lift and splay along the strand, mean over strands", fontsize=9)
    a = ax[1, 2]
    for k, r in rows.items():
        if "history" in r and r["history"]:
            h = np.asarray(r["history"])
            a.plot(h[:, 0], h[:, 1] / data["e_star"], label=k)
    a.set_yscale("log")
    a.axhline(1.0, color="k", lw=0.8)
    a.axhline(rows["static"]["energy_ratio"], color="tab:red", ls="--", lw=0.8, label="network")
    a.set_xlabel("L-BFGS energy evaluations (float64) / Adam steps (fine-tuned network)")
    a.set_ylabel("E / E*")
    a.legend(fontsize=7)
    a.set_title("f) oracle maps, network fine-tuned here: convergence", fontsize=9)
    if "scans" in data:
        a = ax[0, 3]
        line = data["scans"]["line_optimum_to_network"]
        xs = [float(k) for k in line]
        a.plot(xs, [v["energy_ratio"] for v in line.values()], "o-")
        a.set_yscale("log")
        a.axvline(0, color="k", lw=0.6)
        a.axvline(1, color="tab:red", lw=0.6)
        a.set_xlabel("s: x = FTL(optimum + s (network - optimum))")
        a.set_ylabel("E / E*")
        a.set_title("g) optimum (0) to network (1), and mirrored (< 0)", fontsize=9)
        a = ax[1, 3]
        vert = data["scans"]["vertical_shift_mm"]
        a.plot([float(k) for k in vert], [v["energy_ratio"] for v in vert.values()], "o-")
        a.set_yscale("log")
        a.set_xlabel("optimum shifted up (+) / down (-) at the tip, tapered [mm]")
        a.set_ylabel("E / E*")
        a.set_title("h) price of a height error of the whole drape", fontsize=9)
    else:
        ax[0, 3].axis("off")
        ax[1, 3].axis("off")
    _save(fig, data, path, bottom=0.02)



def plot_motion(data: dict, path: str) -> None:
    """Four panels: the tips' swing over time, the variants' distance to the shipped network's output,
    swing correlation and amplitude against the physics, the descriptors' size by training interval k.
    """
    plt = _plt()
    runs = data["runs"]
    fig, ax = plt.subplots(2, 2, figsize=(15, 9.5))
    phys = np.asarray(runs["physics"]["mean_tip_offset_mm"])
    comp = int(np.argmax((phys - phys.mean(0)).std(0)))
    a = ax[0, 0]
    for key in ("physics", "static", "dynamic", "zero_motion", "descriptors_as_k3", "every_k3", "motion_x10"):
        if key not in runs:
            continue
        y = np.asarray(runs[key]["mean_tip_offset_mm"])[:, comp]
        a.plot(runs[key]["frames"], y - y.mean(), marker="o" if key.startswith("every") else None, ms=3,
               lw=2.5 if key == "physics" else 1.2, label=key)
    a.set_xlabel("frame (60 fps)")
    a.set_ylabel(f"mean tip offset from rigid, {'xyz'[comp]}, minus its mean [mm]")
    a.legend(fontsize=7)
    a.set_title(f"a) {data['scene']}: the tips' swing (mean over strands)", fontsize=9)
    a = ax[0, 1]
    for key, r in runs.items():
        if r.get("distance_to_dynamic_per_frame_mm") and key != "dynamic":
            a.plot(r["distance_to_dynamic_per_frame_mm"], label=key)
    a.plot(runs["dynamic"]["distance_to_static_per_frame_mm"], "k--", label="static network")
    a.set_yscale("log")
    a.set_xlabel("frame")
    a.set_ylabel("mean vertex distance to the shipped dynamic output [mm]")
    a.legend(fontsize=7)
    a.set_title("b) what changes the output", fontsize=9)
    a = ax[1, 0]
    keys = [k for k in runs if k not in ("rigid",)]
    corr = [runs[k]["swing_correlation"] or 0.0 for k in keys]
    ratio = [runs[k]["swing_amplitude_ratio"] or 0.0 for k in keys]
    pos = np.arange(len(keys))
    a.barh(pos - 0.2, corr, 0.4, label="swing correlation with the physics")
    a.barh(pos + 0.2, ratio, 0.4, label="swing amplitude / physics")
    for i, k in enumerate(keys):
        if k.startswith("every_k"):
            st = runs[k]["static_on_these_frames"]
            a.plot([st["swing_correlation"] or 0.0], [i - 0.2], "k|", ms=10)
    a.set_yticks(pos, keys, fontsize=7)
    a.axvline(0.8, color="g", ls="--", lw=0.8)
    a.axvline(1.0, color="k", lw=0.6)
    a.legend(fontsize=7)
    a.set_title("c) against the physics (|: the static network on the same subsampled frames)", fontsize=9)
    a = ax[1, 1]
    rms = data["descriptor_rms_training_motions"]
    ks = sorted(rms, key=int)
    for key in ("joint_angular_velocity", "gravity_velocity", "joint_acceleration"):
        a.plot([int(k) for k in ks], [rms[k][key] for k in ks], marker="o", label=key)
    a.set_yscale("log")
    a.set_xlabel("training frame interval k (clip sampled every k frames, descriptors at dt = 1/60 s)")
    a.set_ylabel("RMS over the training pool's procedural motions")
    a.legend(fontsize=7)
    a.set_title("d) the descriptors training shows grow with k (inference: k = 1)", fontsize=9)
    _save(fig, data, path, bottom=0.02)


def plot_rollout(data: dict, path: str) -> None:
    """Three panels: the self-judged training loss by interval k, the per-frame Eq. 6 targets' swing
    against the network's and the physics', the per-term gradient norms w.r.t. the map.
    """
    plt = _plt()
    fig, ax = plt.subplots(1, 3, figsize=(18, 5.5))
    a = ax[0]
    losses = data["windowed_loss"]
    ks = sorted(losses, key=int)
    names = list(losses[ks[0]])
    ref = {k: losses[k]["physics"]["total"] for k in ks}
    for name in names:
        a.plot([int(k) for k in ks], [losses[k][name]["total"] - ref[k] for k in ks], marker="o", label=f"{name} total")
        a.plot([int(k) for k in ks], [losses[k][name]["inertia"] for k in ks], ls=":",
               color=a.lines[-1].get_color(), label=f"{name} inertia")
    a.set_yscale("symlog", linthresh=1e-4)
    a.set_xlabel("frame interval k (h = k / 60 s)")
    a.set_ylabel("loss minus the physics' (solid); inertia (dotted)")
    a.legend(fontsize=7)
    a.set_title("a) Eq. 6 over training windows, each trajectory on its own history", fontsize=9)
    a = ax[1]
    tg = data["targets"]
    phys = np.asarray(tg["physics"]["mean_tip_offset_mm"])
    comp = int(np.argmax((phys - phys.mean(0)).std(0)))
    for name, series in (("physics", phys), ("network", np.asarray(tg["network"]["mean_tip_offset_mm"])),
                         ("Eq. 6 target (own history)", np.asarray(tg["eq6_target"]["mean_tip_offset_mm"])),
                         ("Eq. 5 target (no inertia)", np.asarray(tg["eq5_target"]["mean_tip_offset_mm"]))):
        y = series[:, comp]
        a.plot(tg["frames"], y - y.mean(), marker="o", ms=3, label=name)
    a.set_xlabel("frame")
    a.set_ylabel(f"mean tip offset from rigid, {'xyz'[comp]}, minus its mean [mm]")
    a.legend(fontsize=7)
    a.set_title(f"b) what one step's loss pulls the network's frames to (k = {tg['k']})", fontsize=9)
    a = ax[2]
    grads = data["gradients"]
    for j, (kk, g) in enumerate(sorted(grads.items())):
        names = [n for n in g if n != "total"]
        a.barh(np.arange(len(names)) + 0.4 * j, [g[n]["norm"] for n in names], 0.4, label=f"k = {kk}")
    a.set_yticks(np.arange(len(names)) + 0.2, names, fontsize=7)
    a.set_xscale("log")
    a.legend(fontsize=7)
    a.set_title("c) |dE_term / dD| at the network's maps (own history)", fontsize=9)
    _save(fig, data, path)


def plot_sizes(data: dict, path: str) -> None:
    """E / E* and the tips of the common strands against the strand count; the terms of the optimum."""
    plt = _plt()
    rows = {int(k): v for k, v in data["rows"].items()}
    strides = [int(s) for s in data["strides"]]
    counts = [rows[s]["size"]["strands"] for s in strides]
    fig, ax = plt.subplots(1, 4, figsize=(22, 5))
    a = ax[3]
    a.plot(counts, [rows[s]["excess_per_strand"]["static"] for s in strides], "o-", label="static network")
    a.plot(counts, [rows[s]["excess_per_strand"]["rigid"] for s in strides], "s-", label="rigid placement")
    a.set_xscale("log", base=2)
    a.set_yscale("log")
    a.set_xlabel("strands")
    a.set_ylabel("(E - E*) / strands [J]")
    a.legend(fontsize=8)
    a.set_title("d) the excess per strand", fontsize=9)
    a = ax[0]
    a.plot(counts, [rows[s]["energy_ratio"]["static"] for s in strides], "o-", label="static network")
    a.plot(counts, [rows[s]["energy_ratio"]["rigid"] for s in strides], "s-", label="rigid placement")
    a.set_xscale("log", base=2)
    a.set_yscale("log")
    a.axhline(1.0, color="k", lw=0.6)
    a.set_xlabel("strands")
    a.set_ylabel("E / E*")
    a.legend(fontsize=8)
    a.set_title(f"a) {data['scene']}: E / E* by strand count", fontsize=9)
    a = ax[1]
    a.plot(counts, [rows[s]["optimum_tip_above_rigid_mm"] for s in strides], "o-", label="optimum")
    a.plot(counts, [rows[s]["network_tip_above_rigid_mm"] for s in strides], "s-", label="static network")
    a.set_xscale("log", base=2)
    a.set_xlabel("strands")
    a.set_ylabel("tip height above the rigid placement's, common strands [mm]")
    a.legend(fontsize=8)
    a.set_title(f"b) the same {rows[strides[0]]['common_strands']} strands at every size", fontsize=9)
    a = ax[2]
    terms = [t for t in TERMS if t in rows[strides[0]]["terms"]["reference"]]
    for j, s in enumerate(strides):
        vals = [abs(rows[s]["terms"]["reference"][t][0]) for t in terms]
        a.bar(np.arange(len(terms)) + j * 0.8 / len(strides), vals, 0.8 / len(strides), label=f"{counts[j]} strands")
    a.set_yscale("log")
    a.set_xticks(np.arange(len(terms)) + 0.4, [t.replace("_", "\n") for t in terms], fontsize=7)
    a.legend(fontsize=7)
    a.set_title("c) |term| of the optimum: sums grow with the strand count, means do not", fontsize=9)
    _save(fig, data, path)


def plot_training(data: dict, path: str) -> None:
    """E / E* and tip lift / splay of the network on its own training samples, by strand length."""
    plt = _plt()
    rows = data["samples"]
    length = np.asarray([r["mean_strand_length_m"] for r in rows])
    grown = np.asarray([r["grown"] for r in rows])
    fig, ax = plt.subplots(1, 2, figsize=(13, 5))
    a = ax[0]
    for mask, label, marker in ((grown, "grown around the body", "o"), (~grown, "decoded from z", "s")):
        a.scatter(length[mask], np.asarray([r["energy_ratio_network"] for r in rows])[mask], marker=marker,
                  label=label)
    a.axhline(1.0, color="k", lw=0.6)
    a.axhline(1.05, color="g", lw=0.8, ls="--")
    a.set_xlabel("mean strand length [m]")
    a.set_ylabel("E / E* (E*: per-strand oracle, L-BFGS)")
    a.legend(fontsize=8)
    a.set_title(f"a) the static network on {len(rows)} phase-3 training samples "
                f"(median {data['median_energy_ratio_network']:.3f})", fontsize=9)
    a = ax[1]
    a.scatter(length, [r["tip_lift_mm"] for r in rows], label="tip height above the oracle's")
    a.scatter(length, [r["tip_splay_mm"] for r in rows], marker="x", label="tip distance from the head axis beyond")
    a.axhline(0, color="k", lw=0.6)
    a.set_xlabel("mean strand length [m]")
    a.set_ylabel("[mm]")
    a.legend(fontsize=8)
    a.set_title("b) lift and splay on its own training samples", fontsize=9)
    _save(fig, data, path)


def cmd_plot(args) -> None:
    """Redraw the PNG of every result JSON in --out."""
    plots = {"static_": plot_static, "motion_": plot_motion, "rollout_": plot_rollout, "sizes_": plot_sizes,
             "training_": plot_training}
    for name in sorted(os.listdir(args.out)):
        for prefix, fn in plots.items():
            if name.startswith(prefix) and name.endswith(".json"):
                with open(os.path.join(args.out, name), encoding="utf-8") as f:
                    fn(json.load(f), os.path.join(args.out, name[:-5] + ".png"))

# ---------------------------------------------------------------------------------------------- CLI
def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/network_diagnosis", help="folder of the JSON and PNG results")
    parser.add_argument("--device", default="cpu", help="torch device (cpu; cuda untested)")
    parser.add_argument("--seed", type=int, default=0, help="torch seed (the experiments are deterministic otherwise)")
    parser.add_argument("--cache", default="/tmp/diagnose_networks_cache",
                        help="folder caching slow results (optima, physics) between subcommands; '' for none")
    parser.add_argument("--strand-stride", type=int, default=4, help="every k-th scalp root (4: 256 strands)")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("static", help="H-a oracle maps and H-b energy terms of static drapes")
    p.add_argument("--scenes", default="table1,long_rest",
                   help=f"comparison scenes or {', '.join(GROWN_REST)} (presets grown around the body, at rest)")
    p.add_argument("--frames", default=None, help="frame indices, comma separated (default: all)")
    p.add_argument("--oracles", default=",".join(ORACLES), help=f"oracle variants among {', '.join(ORACLES)}")
    p.add_argument("--iterations", type=int, default=300, help="L-BFGS iterations of each oracle map")
    p.add_argument("--finetune-steps", type=int, default=200,
                   help="Adam steps of a copy of the static network trained on the scene alone (0: none)")
    p.add_argument("--finetune-lr", type=float, default=2e-4, help="its learning rate (the shipped recipe's)")
    p.add_argument("--skip-lbfgs", action="store_true", help="no L-BFGS 300 baseline (saves time at full size)")
    p.add_argument("--reference-iterations", type=int, default=None,
                   help="cap of the reference optimum's iterations (default: the method's 5000)")
    p = sub.add_parser("sizes", help="the optimum and the network on the same strands at several strand counts")
    p.add_argument("--scene", default="long_rest", help=f"one of {', '.join(GROWN_REST)} (one frame)")
    p.add_argument("--strides", default="16,8,4,2", help="scalp-root strides, the largest first")
    p.add_argument("--frames", default=None, help=argparse.SUPPRESS)
    p = sub.add_parser("training", help="the static network on samples of its own training distribution")
    p.add_argument("--samples", type=int, default=8, help="phase-3 samples to draw")
    p.add_argument("--first-step", type=int, default=1000, help="step key of the first sample")
    p.add_argument("--iterations", type=int, default=300, help="L-BFGS iterations of each sample's oracle")
    p = sub.add_parser("motion", help="H-c: the dynamic network's output with the motion changed, against the physics")
    p.add_argument("--scene", default="whiplash", help="a motion comparison scene")
    p.add_argument("--frames", type=int, default=None, help="first this many frames (default: all)")
    p.add_argument("--ks", type=lambda v: [int(k) for k in v.split(",")], default=[2, 3, 5],
                   help="training intervals k to imitate (descriptor scaling, subsampled runs)")
    p = sub.add_parser("rollout", help="H-d: what the dynamic training's loss sees and rewards")
    p.add_argument("--scene", default="whiplash", help="a motion comparison scene")
    p.add_argument("--frames", type=int, default=None, help="first this many frames (default: all)")
    p.add_argument("--target-k", type=int, default=3, help="frame interval of the per-frame Eq. 6 targets")
    p.add_argument("--target-every", type=int, default=2, help="a target every this many frames")
    p.add_argument("--target-iterations", type=int, default=100, help="L-BFGS iterations of each target")
    sub.add_parser("plot", help="redraw every figure from the JSON files in --out")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    args.cache = args.cache or None
    commands = {"static": cmd_static, "sizes": cmd_sizes, "training": cmd_training, "motion": cmd_motion,
                "rollout": cmd_rollout, "plot": cmd_plot}
    commands[args.command](args)


if __name__ == "__main__":
    main()
