"""The body's BVH (constructor, faces per leaf) on the GPU: its build time, the hair-body energy
forward+backward (`bench energy`'s inputs), the whole energy replayed from a CUDA graph at batch 1,
and the shipped-size static drape with contact features.

    python benchmarks/bm_body_bvh.py --device cuda --bvhs lbvh:4,sah:4,sah:8,lbvh:8,sah:2 --out OUT

Prints one row per constructor:leaf pair and writes OUT/body_bvh.json (docs/contact.md 6; the
H100 run: docs/results/body_bvh_probe_h100.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import torch


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--bvhs", default="lbvh:4,sah:4,sah:8,lbvh:8,sah:2", help="constructor:leaf pairs")
    parser.add_argument("--batch", default="1,32", help="comma-separated batch sizes of the energy rows")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)

    import hairwarp.ops.hair_body_contact as hb
    from hairwarp import set_finite_checks
    from hairwarp.bench.energy import build_energy_inputs
    from hairwarp.config import EnergyConfig
    from hairwarp.energy import CapturedEnergy
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.models import StaticConfig, StaticNetwork
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.ops.barrier import barrier_variant_id
    from hairwarp.runtime import CapturedCall, machine_name, time_ms

    set_finite_checks(False)
    dev, c = torch.device(args.device), EnergyConfig()
    graph = CapturedCall if dev.type == "cuda" else (lambda f: f)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    frames = comparison_scene("medium_rest").frames(device=dev)
    rigid = frames.rigid.positions.float()[:1].contiguous()
    root_uv = frames.scene.hairstyle.root_uv.to(dev)
    static = StaticNetwork(dataclasses.replace(StaticConfig.shipped(), contact_samples=16)).to(dev).eval()
    z, beta, theta = torch.randn(1, 512, device=dev), torch.zeros(1, 16, device=dev), torch.zeros(1, 66, device=dev)
    leaf_sizes = dict(hb._BVH_LEAF_SIZE)
    rows = []
    try:
        for item in args.bvhs.split(","):
            ctor, leaf = item.split(":")
            hb._BVH_LEAF_SIZE[ctor] = int(leaf)
            sync()
            t = time.perf_counter()
            body = hb.BodyMesh(frames.body_mesh.vertices.clone(), frames.body_mesh.faces.clone(),
                               require_watertight=False, bvh=ctor)
            sync()
            row = {"bvh": ctor, "leaf": int(leaf), "build_ms": (time.perf_counter() - t) * 1e3}
            with torch.no_grad():
                drape = graph(lambda: apply_deformation(
                    rigid, static(z, beta, theta, contact=static.contact_features(rigid, root_uv, body)).float(),
                    root_uv, "follow_the_leader"))
                row["static_contact_ms"] = time_ms(drape, dev, warmup=5, repeats=50)
                features = graph(lambda: static.contact_features(rigid, root_uv, body))
                row["features_ms"] = time_ms(features, dev, warmup=5, repeats=50)
            for batch in (int(b) for b in args.batch.split(",")):
                x, inputs, _, _ = build_energy_inputs(batch, dev)
                b0 = inputs.body
                eb = hb.BodyMesh._from_parts(b0._points32.clone(), b0._faces, b0._batched, b0._watertight,
                                             b0._vertex_map, b0._face_map, b0._normal_faces, b0._face_rows, ctor)
                x = x.detach()
                row[f"hair_body_B{batch}_ms"] = time_ms(
                    lambda: hb._energy_forward(x, eb, c.hair_body_xi, c.hair_body_dhat, c.barrier_join_fraction,
                                               c.hair_body_weight, barrier_variant_id(c.barrier_variant), "vertex"),
                    dev, warmup=3, repeats=20, min_time_s=0.2)
                if batch == 1:
                    captured = CapturedEnergy(x, dataclasses.replace(inputs, body=eb), dynamic=True)
                    row["total_graph_B1_ms"] = time_ms(lambda: captured(x), dev, warmup=3, repeats=30)
            rows.append(row)
            print({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    finally:
        hb._BVH_LEAF_SIZE.update(leaf_sizes)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "body_bvh.json"), "w") as f:
        json.dump({"machine": machine_name(dev), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
