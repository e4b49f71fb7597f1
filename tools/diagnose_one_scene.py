"""Can the static network fit one scene? The first check of the networks' diagnosis (issue 15).

On one comparison scene (table1 by default: every tip starts inside the body), minimise the
static energy (Eq. 5) of Eq. 2's drape three ways, from the same start, and record the
learning curves:

- "map": the deformation map itself (8 x 8 x N x 3 numbers, no network) by Adam;
- "map-lbfgs": the same map by L-BFGS (the issue's reference: 0.61 % inside at 300 iterations);
- "network": a fresh static network (shipped size) by Adam on its weights, inputs fixed.

and, at the start, the gradient norm of each energy term with respect to the map (which terms
steer the deformation), and at the end the deformation magnitude by vertex index. Writes
OUT/diagnose_<scene>.json and OUT/diagnose_<scene>.png.

    python tools/diagnose_one_scene.py --device cuda --steps 1500 --out OUT
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch


def _map_shape(cfg, n):
    return (1, cfg.grid_height, cfg.grid_width, n, 3)


def main(argv=None) -> int:
    from hairwarp.config import STRAND_TERMS, CONTACT_TERMS, EnergyConfig
    from hairwarp.energy import total_energy
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.metrics import length_change_percent, penetration_percent
    from hairwarp.models import StaticConfig, StaticNetwork
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.runtime import machine_name, resolve_device, synchronize
    from hairwarp.scene.hair_latent import HairLatentBasis

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scene", default="table1")
    p.add_argument("--strand-stride", type=int, default=None, help="default: full size")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--record-every", type=int, default=25)
    p.add_argument("--lrs", default="1e-4,1e-3", help="Adam learning rates of the network runs")
    p.add_argument("--map-lrs", default="1e-3,1e-2", help="Adam learning rates of the free-map runs")
    p.add_argument("--lbfgs-iterations", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="hairwarp-out")
    args = p.parse_args(argv)
    device = resolve_device(args.device, argument="--device")
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)

    scene = comparison_scene(args.scene, strand_stride=args.strand_stride)
    frames = scene.frames(device=device)
    rigid = frames.rigid.positions
    n = rigid.shape[2]
    root_uv = scene.scene.hairstyle.root_uv.to(device)
    config = EnergyConfig()
    style = scene.scene.hairstyle
    z = HairLatentBasis.load_default().encode(style.strands.double(), style.root_uv.double())
    z = z.reshape(1, -1).to(device=device, dtype=torch.float32)
    cfg = StaticConfig.shipped()
    rest = frames.inputs.rest_lengths

    def scores(x):
        with torch.no_grad():
            return {"penetration": float(penetration_percent(x, frames.body_mesh)),
                    "length_change": float(length_change_percent(x, rest)),
                    "energy": float(total_energy(x, frames.inputs, config).total.sum())}

    record = {"machine": machine_name(device), "scene": scene.describe(), "steps": args.steps,
              "rigid": scores(rigid), "runs": {}}
    print("rigid", record["rigid"], flush=True)

    # Which terms steer the map at the start: |dE_term / dD| for each term, D = 0.
    d0 = torch.zeros(_map_shape(cfg, n), device=device, requires_grad=True)
    norms = {}
    for term in STRAND_TERMS + CONTACT_TERMS:
        if term == "inertia":  # the static energy (Eq. 5) has none
            continue
        value = total_energy(apply_deformation(rigid, d0, root_uv), frames.inputs, config, terms=(term,)).total
        (g,) = torch.autograd.grad(value.sum(), d0, allow_unused=True)
        norms[term] = 0.0 if g is None else float(g.norm())
    record["gradient_norms_at_start"] = norms
    print("gradient norms at D = 0:", {k: f"{v:.3g}" for k, v in norms.items()}, flush=True)

    def run(name, params, positions_fn, opt, steps):
        curve = []
        start = time.perf_counter()
        for step in range(steps + 1):
            if step % args.record_every == 0 or step == steps:
                x = positions_fn().detach()
                synchronize(device)
                curve.append({"step": step, "time_s": time.perf_counter() - start, **scores(x)})
            if step == steps:
                break
            opt.zero_grad(set_to_none=True)
            loss = total_energy(positions_fn(), frames.inputs, config).total.sum()
            loss.backward()
            opt.step()
        x = positions_fn().detach()
        magnitude = (x - rigid).norm(dim=-1).mean(dim=(0, 1))  # (N,) mean displacement by vertex index
        record["runs"][name] = {"curve": curve, "final": curve[-1],
                                "displacement_by_vertex_m": magnitude.tolist()}
        print(name, curve[-1], flush=True)

    for lr in (float(v) for v in args.map_lrs.split(",")):
        d = torch.zeros(_map_shape(cfg, n), device=device, requires_grad=True)
        run(f"map adam lr={lr:g}", [d], lambda d=d: apply_deformation(rigid, d, root_uv),
            torch.optim.Adam([d], lr=lr), args.steps)

    # The free map by L-BFGS (strong Wolfe), the reference point.
    d = torch.zeros(_map_shape(cfg, n), device=device, requires_grad=True)
    lbfgs = torch.optim.LBFGS([d], lr=1.0, max_iter=1, history_size=20, line_search_fn="strong_wolfe")
    curve = []
    start = time.perf_counter()
    for it in range(args.lbfgs_iterations + 1):
        if it % args.record_every == 0 or it == args.lbfgs_iterations:
            curve.append({"step": it, "time_s": time.perf_counter() - start,
                          **scores(apply_deformation(rigid, d.detach(), root_uv))})
        if it == args.lbfgs_iterations:
            break

        def closure():
            lbfgs.zero_grad(set_to_none=True)
            loss = total_energy(apply_deformation(rigid, d, root_uv), frames.inputs, config).total.sum()
            loss.backward()
            return loss

        lbfgs.step(closure)
    record["runs"]["map lbfgs"] = {"curve": curve, "final": curve[-1]}
    print("map lbfgs", curve[-1], flush=True)

    beta = frames.betas[:1].float()
    theta = frames.poses[:1].float()
    for lr in (float(v) for v in args.lrs.split(",")):
        torch.manual_seed(args.seed)
        net = StaticNetwork(cfg).to(device).train()
        run(f"network adam lr={lr:g}", list(net.parameters()),
            lambda net=net: apply_deformation(rigid, net(z, beta, theta), root_uv),
            torch.optim.Adam(net.parameters(), lr=lr), args.steps)

    path = os.path.join(args.out, f"diagnose_{args.scene}.json")
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
    _plot(record, os.path.join(args.out, f"diagnose_{args.scene}.png"))
    print("wrote", path)
    return 0


def _plot(record, path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 4))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    for name, run in record["runs"].items():
        steps = [c["step"] for c in run["curve"]]
        axes[0].plot(steps, [c["penetration"] for c in run["curve"]], label=name)
        axes[1].plot(steps, [c["length_change"] for c in run["curve"]], label=name)
        if "displacement_by_vertex_m" in run:
            axes[2].plot([v * 1e3 for v in run["displacement_by_vertex_m"]], label=name)
    axes[0].axhline(record["rigid"]["penetration"], color="0.5", ls="--", label="rigid")
    axes[0].set(xlabel="step / iteration", ylabel="penetration [%]", title=record["scene"]["name"])
    axes[1].set(xlabel="step / iteration", ylabel="length change [%]")
    axes[2].set(xlabel="vertex index", ylabel="mean displacement from rigid [mm]", title="at the end")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"one-scene fit, {record['machine']}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    raise SystemExit(main())
