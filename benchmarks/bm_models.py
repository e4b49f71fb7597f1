"""ms per drape of the networks (static, dynamic per frame, Quaffure) at batch 1 and 32.

Times the network forward plus the deformation lookup and taper (Eq. 2) on the rigid placement,
as Table 1 counts it (the rigid placement, Eq. 1, is shared by every method and timed apart).
Untrained weights: speed does not depend on them.

    python benchmarks/bm_models.py --device cuda --out OUT

On CUDA every network is also timed replayed from a CUDA graph ("graph": captured once for the
shapes, `hairwarp.runtime.CapturedCall`, what `hairwarp.methods` uses on CUDA), which removes
the per-launch host cost that dominates at batch 1.
"""

from __future__ import annotations

import argparse
import json
import os

import torch

from hairwarp.runtime import CapturedCall, machine_name, time_ms
from hairwarp.models import (DynamicConfig, DynamicNetwork, QuaffureConfig, QuaffureNetwork, StaticConfig,
                             StaticNetwork)
from hairwarp.models.deformation import apply_deformation


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="hairwarp-out")
    parser.add_argument("--batch", default="1,32")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    os.makedirs(args.out, exist_ok=True)
    n, m = 100, 1024
    rows = []
    root_uv = torch.rand(m, 2, device=device)
    for size in ("paper", "shipped"):
        scfg = StaticConfig() if size == "paper" else StaticConfig.shipped()
        static = StaticNetwork(scfg).to(device).eval()
        dcfg = DynamicConfig(static=scfg, motion_dim=132) if size == "paper" else DynamicConfig.shipped(motion_dim=132)
        dynamic = DynamicNetwork.from_static(static, dcfg).to(device).eval()
        quaffure = QuaffureNetwork(QuaffureConfig()).to(device).eval()
        for batch in (int(b) for b in args.batch.split(",")):
            z = torch.randn(batch, 512, device=device)
            beta = torch.zeros(batch, 16, device=device)
            theta = torch.zeros(batch, 66, device=device)
            rigid = torch.randn(batch, m, n, 3, device=device)
            motion = torch.randn(batch, 1, dcfg.window, 132, device=device)
            hidden = torch.zeros(batch, scfg.model_dim, device=device)  # C_dyn of the previous frame
            for precision in ("fp32", "bf16"):
                ctx = (torch.autocast(device.type, dtype=torch.bfloat16) if precision == "bf16"
                       else torch.autocast(device.type, enabled=False))

                def run_static():
                    with torch.no_grad(), ctx:
                        return apply_deformation(rigid, static(z, beta, theta).float(), root_uv)

                def run_dynamic():
                    with torch.no_grad(), ctx:
                        out = dynamic.simulate(z, beta, theta[:, None], motion, hidden)
                        return apply_deformation(rigid, out.deformation_map[:, 0].float(), root_uv)

                def run_quaffure():
                    with torch.no_grad(), ctx:
                        return apply_deformation(rigid, quaffure(z, beta, theta).float(), root_uv)

                for name, fn in (("static", run_static), ("dynamic", run_dynamic), ("quaffure", run_quaffure)):
                    if size == "shipped" and name == "quaffure":
                        continue
                    modes = [("eager", fn)]
                    if device.type == "cuda":
                        try:
                            modes.append(("graph", CapturedCall(fn)))
                        except RuntimeError as exc:  # an op that cannot be captured
                            print(f"{name} {size} B={batch} {precision}: no CUDA graph ({exc})")
                    for mode, call in modes:
                        try:
                            ms = time_ms(call, device, warmup=5, repeats=20)
                        except RuntimeError as exc:  # e.g. bf16 unsupported on this CPU
                            print(f"{name} {size} B={batch} {precision}: {exc}")
                            continue
                        rows.append({"model": name, "size": size, "batch": batch, "precision": precision,
                                     "mode": mode, "ms_per_call": ms, "ms_per_drape": ms / batch})
                        print(f"{name:9s} {size:8s} B={batch:<3d} {precision} {mode:5s}: {ms:8.3f} ms/call  "
                              f"{ms / batch:8.4f} ms/drape", flush=True)
    record = {"device": str(device), "machine": machine_name(device), "strands": m, "vertices": n,
              "results": rows}
    with open(os.path.join(args.out, "bench_models.json"), "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
