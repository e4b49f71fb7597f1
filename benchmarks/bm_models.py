"""ms per drape of the networks (static, dynamic per frame, Quaffure) at batch 1 and 32.

Times the network forward plus the deformation lookup and taper (Eq. 2) on the rigid placement,
as Table 1 counts it (the rigid placement, Eq. 1, is shared by every method and timed apart).
Untrained weights: speed does not depend on them. The hair and body are the medium_rest
comparison scene's (1024 strands x 100 vertices, the default body): the shipped size projects
its drapes onto the rest lengths, and "shipped+contact" also reads contact features (a body
query per frame, timed with the network).

    python benchmarks/bm_models.py --device cuda --out OUT

On CUDA every network is also timed replayed from a CUDA graph ("graph": captured once for the
shapes, `hairwarp.runtime.CapturedCall`, what `hairwarp.methods` uses on CUDA), which removes
the per-launch host cost that dominates at batch 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import torch

from hairwarp.runtime import CapturedCall, machine_name, time_ms
from hairwarp.models import (DynamicConfig, DynamicNetwork, QuaffureConfig, QuaffureNetwork, StaticConfig,
                             StaticNetwork)
from hairwarp.models.deformation import apply_deformation
from hairwarp.evaluation.scenes import comparison_scene


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="hairwarp-out")
    parser.add_argument("--batch", default="1,32")
    parser.add_argument("--contact-samples", type=int, default=16,
                        help="the shipped size is also timed reading this many contact samples per strand (0: not)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    os.makedirs(args.out, exist_ok=True)
    # A real rigid placement and body (the default body, full scalp): the contact features
    # query this body, and the length projection walks real strands.
    frames = comparison_scene("medium_rest").frames(device=device)
    body = frames.body_mesh
    base_rigid = frames.rigid.positions.float()
    m, n = base_rigid.shape[1], base_rigid.shape[2]
    root_uv = frames.scene.hairstyle.root_uv.to(device)
    rows = []
    sizes = ["paper", "shipped"] + (["shipped+contact"] if args.contact_samples > 0 else [])
    for size in sizes:
        scfg = StaticConfig() if size == "paper" else StaticConfig.shipped()
        if size == "shipped+contact":
            scfg = dataclasses.replace(scfg, contact_samples=args.contact_samples)
        projection = scfg.length_projection
        static = StaticNetwork(scfg).to(device).eval()
        dcfg = (DynamicConfig(static=scfg, motion_dim=132) if size == "paper"
                else dataclasses.replace(DynamicConfig.shipped(motion_dim=132), static=scfg))
        dynamic = DynamicNetwork.from_static(static, dcfg).to(device).eval()
        quaffure = QuaffureNetwork(QuaffureConfig()).to(device).eval()
        for batch in (int(b) for b in args.batch.split(",")):
            z = torch.randn(batch, 512, device=device)
            beta = torch.zeros(batch, 16, device=device)
            theta = torch.zeros(batch, 66, device=device)
            rigid = base_rigid.expand(batch, -1, -1, -1).contiguous()
            motion = torch.randn(batch, 1, dcfg.window, 132, device=device)
            hidden = torch.zeros(batch, scfg.model_dim, device=device)  # C_dyn of the previous frame
            for precision in ("fp32", "bf16"):
                ctx = (torch.autocast(device.type, dtype=torch.bfloat16) if precision == "bf16"
                       else torch.autocast(device.type, enabled=False))

                def run_static(contact=None):
                    with torch.no_grad(), ctx:
                        return apply_deformation(rigid, static(z, beta, theta, contact=contact).float(), root_uv,
                                                 projection)

                def run_dynamic(contact=None):
                    with torch.no_grad(), ctx:
                        out = dynamic.simulate(z, beta, theta[:, None], motion, hidden,
                                               contact=None if contact is None else contact[:, None])
                        return apply_deformation(rigid, out.deformation_map[:, 0].float(), root_uv, projection)

                def run_quaffure(contact=None):
                    with torch.no_grad(), ctx:
                        return apply_deformation(rigid, quaffure(z, beta, theta).float(), root_uv)

                for name, fn in (("static", run_static), ("dynamic", run_dynamic), ("quaffure", run_quaffure)):
                    if size != "paper" and name == "quaffure":
                        continue
                    # The contact features (a body query) are part of the drape, as in
                    # `hairwarp.methods`, and of its CUDA graph.
                    if scfg.contact_samples:
                        def call(f=fn):
                            return f(static.contact_features(rigid, root_uv, body))
                    else:
                        call = fn
                    modes = [("eager", call)]
                    if device.type == "cuda":
                        try:
                            modes.append(("graph", CapturedCall(call)))
                        except RuntimeError as exc:  # an op that cannot be captured
                            print(f"{name} {size} B={batch} {precision}: no CUDA graph ({exc})")
                    for mode, timed_call in modes:
                        try:
                            ms = time_ms(timed_call, device, warmup=5, repeats=20)
                        except RuntimeError as exc:  # e.g. bf16 unsupported on this CPU
                            print(f"{name} {size} B={batch} {precision}: {exc}")
                            continue
                        rows.append({"model": name, "size": size, "batch": batch, "precision": precision,
                                     "mode": mode, "ms_per_call": ms, "ms_per_drape": ms / batch,
                                     "length_projection": projection, "contact_samples": scfg.contact_samples})
                        print(f"{name:9s} {size:16s} B={batch:<3d} {precision} {mode:5s}: {ms:8.3f} ms/call  "
                              f"{ms / batch:8.4f} ms/drape", flush=True)
    record = {"device": str(device), "machine": machine_name(device), "strands": m, "vertices": n,
              "results": rows}
    with open(os.path.join(args.out, "bench_models.json"), "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
