"""Why do the drapers learn "leave the hair where it is"? One-scene hypotheses, in numbers (issue 15).

On one comparison scene (table1 by default: every tip starts centimetres inside the body),
minimise the static energy (Eq. 5) of Eq. 2's drape from the rigid placement with several
optimisers and settings, each a named variant, and record for each its learning curve
(penetration %, length change %, energy every `--record-every` steps) and, every
`--grad-every` steps, the gradient norm of each energy term with respect to the map D:

    map-lbfgs          the free 8 x 8 x N x 3 map by L-BFGS (the reference, ~0.6 % inside)
    map-adam-1e-3      the free map by Adam, lr 1e-3 (a first-order optimiser on this energy)
    map-adam-1e-2      lr 1e-2
    net-1e-4           a fresh static network (shipped size), Adam lr 1e-4 (the paper's), b_p 0.01
    net-1e-3           lr 1e-3
    net-1e-4-bp        lr 1e-4, b_p annealed 0.9 -> 0.01 geometrically over the run (the paper)
    net-1e-3-gain1     lr 1e-3, head_init_gain 1 (initial deformations of decimetres, not mm)
    net-1e-3-soft      lr 1e-3, stretch weight / 100 (is the stiff stretch term the obstacle?)
    net-1e-3-clip      lr 1e-3, deformation clipped at 0.01 m for the first 10 % (the paper)

Writes OUT/diagnose_training_<scene>.json and .png.

    python tools/diagnose_training.py --device cuda --steps 1000 --out OUT [--variants a,b]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import torch

VARIANTS = {
    "map-lbfgs": {"kind": "lbfgs"},
    "map-adam-1e-3": {"kind": "map", "lr": 1e-3},
    "map-adam-1e-2": {"kind": "map", "lr": 1e-2},
    "net-1e-4": {"kind": "net", "lr": 1e-4},
    "net-1e-3": {"kind": "net", "lr": 1e-3},
    "net-1e-4-bp": {"kind": "net", "lr": 1e-4, "bp": "anneal"},
    "net-1e-3-bp": {"kind": "net", "lr": 1e-3, "bp": "anneal"},
    "net-1e-3-gain1": {"kind": "net", "lr": 1e-3, "model": {"head_init_gain": 1.0}},
    "net-1e-3-soft": {"kind": "net", "lr": 1e-3, "energy": {"stretch_weight": 1e6}},
    "net-1e-3-clip": {"kind": "net", "lr": 1e-3, "clip_fraction": 0.1},
    "net-3e-4": {"kind": "net", "lr": 3e-4},
    "net-1e-2": {"kind": "net", "lr": 1e-2},
}
DEFAULT_VARIANTS = "map-lbfgs,map-adam-1e-3,net-1e-4,net-1e-3,net-1e-4-bp,net-1e-3-gain1,net-1e-3-soft"


def main(argv=None) -> int:
    from hairwarp.config import EnergyConfig
    from hairwarp.energy import total_energy
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.metrics import length_change_percent, penetration_percent
    from hairwarp.models import StaticConfig, StaticNetwork
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.runtime import machine_name, resolve_device, synchronize
    from hairwarp.scene.hair_latent import HairLatentBasis
    from hairwarp.training.monitor import displacement_by_vertex, term_gradients
    from hairwarp.training.static import barrier_schedule

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scene", default="table1")
    p.add_argument("--strand-stride", type=int, default=None, help="default: full size")
    p.add_argument("--num-vertices", type=int, default=None, help="default: 100")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--lbfgs-iterations", type=int, default=300)
    p.add_argument("--record-every", type=int, default=25)
    p.add_argument("--grad-every", type=int, default=100)
    p.add_argument("--variants", default=DEFAULT_VARIANTS, help=f"comma list of {list(VARIANTS)}")
    p.add_argument("--model-preset", default="shipped", choices=("shipped", "paper", "tiny"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="hairwarp-out")
    args = p.parse_args(argv)
    device = resolve_device(args.device, argument="--device")
    os.makedirs(args.out, exist_ok=True)

    scene = comparison_scene(args.scene, strand_stride=args.strand_stride, num_vertices=args.num_vertices)
    frames = scene.frames(device=device)
    rigid = frames.rigid.positions
    n = rigid.shape[2]
    style = scene.scene.hairstyle
    root_uv = style.root_uv.to(device)
    z = HairLatentBasis.load_default().encode(style.strands.double(), style.root_uv.double())
    z = z.reshape(1, -1).to(device=device, dtype=torch.float32).expand(rigid.shape[0], -1)
    beta, theta = frames.betas.float(), frames.poses.float()
    base = EnergyConfig()
    preset = {"shipped": StaticConfig.shipped, "paper": StaticConfig, "tiny": StaticConfig.tiny}[args.model_preset]

    def net_config(overrides):
        import dataclasses

        return dataclasses.replace(preset(), num_vertices=n, latent_dim=512, **overrides)

    cfg0 = net_config({})

    def scores(x, energy):
        with torch.no_grad():
            return {"penetration": float(penetration_percent(x, frames.body_mesh).mean()),
                    "length_change": float(length_change_percent(x, frames.inputs.rest_lengths).mean()),
                    "energy": float(total_energy(x, frames.inputs, base).total.sum()),
                    "energy_at_bp": float(total_energy(x, frames.inputs, energy).total.sum())}

    record = {"machine": machine_name(device), "scene": scene.describe(), "steps": args.steps,
              "command": "python tools/diagnose_training.py " + " ".join(argv or __import__("sys").argv[1:]),
              "rigid": scores(rigid, base), "runs": {}}
    print("rigid", record["rigid"], flush=True)
    d0 = torch.zeros(rigid.shape[0], cfg0.grid_height, cfg0.grid_width, n, 3, device=device)
    record["gradient_at_rigid"] = term_gradients(d0, rigid, root_uv, frames.inputs, base)
    print("gradient norms at D = 0:", {k: f"{v:.3g}" for k, v in record["gradient_at_rigid"]["norm"].items()},
          flush=True)

    for name in args.variants.split(","):
        spec = VARIANTS[name]
        energy = base.replace(**spec.get("energy", {}))
        curve, grads = [], []
        start = time.perf_counter()
        if spec["kind"] == "lbfgs":
            d = torch.zeros_like(d0, requires_grad=True)
            opt = torch.optim.LBFGS([d], lr=1.0, max_iter=1, history_size=20, line_search_fn="strong_wolfe")
            for it in range(args.lbfgs_iterations + 1):
                if it % args.record_every == 0 or it == args.lbfgs_iterations:
                    synchronize(device)
                    curve.append({"step": it, "time_s": time.perf_counter() - start,
                                  **scores(apply_deformation(rigid, d.detach(), root_uv), energy)})
                if it == args.lbfgs_iterations:
                    break

                def closure():
                    opt.zero_grad(set_to_none=True)
                    loss = total_energy(apply_deformation(rigid, d, root_uv), frames.inputs, energy).total.sum()
                    loss.backward()
                    return loss

                opt.step(closure)
            x = apply_deformation(rigid, d.detach(), root_uv)
        else:
            if spec["kind"] == "map":
                d = torch.zeros_like(d0, requires_grad=True)
                params = [d]

                def predict(step, d=d):
                    return d
            else:
                torch.manual_seed(args.seed)
                net = StaticNetwork(net_config(spec.get("model", {}))).to(device).train()
                params = list(net.parameters())
                clip_until = int(spec.get("clip_fraction", 0.0) * args.steps)

                def predict(step, net=net, clip_until=clip_until):
                    return net(z, beta, theta, clip=0.01 if step < clip_until else None)
            opt = torch.optim.Adam(params, lr=spec["lr"])
            for step in range(args.steps + 1):
                bp = (barrier_schedule(min(step, args.steps - 1), args.steps, 0.9, 0.01, "geometric")
                      if spec.get("bp") == "anneal" else base.barrier_join_fraction)
                e_step = energy.replace(barrier_join_fraction=bp)
                if step % args.record_every == 0 or step == args.steps:
                    with torch.no_grad():
                        x = apply_deformation(rigid, predict(step), root_uv)
                    synchronize(device)
                    curve.append({"step": step, "time_s": time.perf_counter() - start, "bp": bp,
                                  **scores(x, e_step)})
                if step % args.grad_every == 0 or step == args.steps:
                    with torch.no_grad():
                        dmap = predict(step)
                    g = term_gradients(dmap, rigid, root_uv, frames.inputs, e_step)
                    grads.append({"step": step, "norm": g["norm"], "cosine_with_total": g["cosine_with_total"],
                                  "map_abs_max_m": float(dmap.abs().max())})
                if step == args.steps:
                    break
                opt.zero_grad(set_to_none=True)
                x = apply_deformation(rigid, predict(step), root_uv)
                loss = total_energy(x, frames.inputs, e_step).total.sum()
                if not math.isfinite(float(loss)):
                    curve.append({"step": step, "diverged": True})
                    break
                loss.backward()
                opt.step()
            with torch.no_grad():
                x = apply_deformation(rigid, predict(args.steps), root_uv)
        record["runs"][name] = {"spec": spec, "curve": curve, "gradients": grads, "final": curve[-1],
                                "wall_s": time.perf_counter() - start,
                                "displacement_by_vertex_mm": displacement_by_vertex(x, rigid)}
        print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in curve[-1].items()},
              f"{time.perf_counter() - start:.1f}s", flush=True)
        path = os.path.join(args.out, f"diagnose_training_{args.scene}.json")
        with open(path, "w") as f:
            json.dump(record, f, indent=1)
    _plot(record, os.path.join(args.out, f"diagnose_training_{args.scene}.png"))
    print("wrote", path)
    return 0


def _plot(record, path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(18, 8))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 3).ravel()
    for i, (name, run) in enumerate(record["runs"].items()):
        c = f"C{i % 10}"
        curve = [r for r in run["curve"] if "penetration" in r]
        steps = [r["step"] for r in curve]
        ax[0].plot(steps, [r["penetration"] for r in curve], c, label=name)
        ax[1].plot(steps, [r["length_change"] for r in curve], c, label=name)
        ax[2].plot(steps, [r["energy"] - record["rigid"]["energy"] for r in curve], c, label=name)
        ax[3].plot(run["displacement_by_vertex_mm"], c, label=name)
        if run["gradients"]:
            gs = [g["step"] for g in run["gradients"]]
            ax[4].semilogy(gs, [g["norm"].get("hair_body_contact", 1e-12) + 1e-12 for g in run["gradients"]], c,
                           label=f"{name}: contact")
            ax[4].semilogy(gs, [g["norm"].get("stretch", 1e-12) + 1e-12 for g in run["gradients"]], c, ls="--")
            ax[5].semilogy(gs, [g["map_abs_max_m"] + 1e-9 for g in run["gradients"]], c, label=name)
    ax[0].axhline(record["rigid"]["penetration"], color="0.5", ls="--", label="rigid")
    ax[0].set(xlabel="step / iteration", ylabel="penetration [%]", title=record["scene"]["name"])
    ax[1].set(xlabel="step / iteration", ylabel="length change [%]")
    ax[2].set(xlabel="step / iteration", ylabel="E - E(rigid) (b_p 0.01)")
    ax[2].set_yscale("symlog", linthresh=1e-2)
    ax[3].set(xlabel="vertex index", ylabel="mean |x - rigid| [mm]", title="at the end")
    ax[4].set(xlabel="step", ylabel="|dE/dD|", title="contact (solid), stretch (dashed)")
    ax[5].set(xlabel="step", ylabel="max |D| [m]")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(f"one-scene fit, {record['machine']}, {record['scene']['size']}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


if __name__ == "__main__":
    raise SystemExit(main())
