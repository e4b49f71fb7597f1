"""Timing of hair-body contact (Eq. 12 with d = signed distance to the body), forward + backward.

Warp (`hairwarp.ops.hair_body_contact`: BVH queries, per-strand walk or per-vertex kernel, full
or cropped body) against the plain-torch brute force (`hairwarp.torch_reference`, timed on a
few strands only: it is O(vertices x triangles)), on the test suite's mesh builders: a
body-sized stretched icosphere (13 692 vertices, 27 380 triangles) with hair draped over its
crown, resting mostly just outside the surface, a few strands dipping in.

    python benchmarks/bm_hair_body_contact.py [--strands 1024] [--vertices 100] [--batch 1]
        [--device cpu] [--repeats 20] [--torch-strands 4] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
import torch

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import meshes  # noqa: E402

from hairwarp._validate import set_finite_checks  # noqa: E402
from hairwarp.runtime import machine_name, time_ms  # noqa: E402
from hairwarp.config import EnergyConfig  # noqa: E402
from hairwarp.ops import hair_body_contact as ops  # noqa: E402
from hairwarp.torch_reference import hair_body_contact as torch_ref  # noqa: E402


def make_scene(rng, strands, vertices, length=0.3, dipping=0.06):
    """Body-like mesh and draped hair (numpy float64): (body vertices, faces, hair, roots, arc)."""
    v, f = meshes.body_like(37)
    hair, roots, _ = meshes.hair_on_cap(
        v, meshes.BODY_LIKE_CENTER, strands, vertices, length, rng, jitter=5e-4
    )
    hair[:, 2:] = meshes.push_outside_ellipsoid(hair[:, 2:], clearance=1.02)
    k = int(dipping * strands)
    hair[:k, 2:] = meshes.push_outside_ellipsoid(hair[:k, 2:], clearance=0.995)
    arc = np.linalg.norm(np.diff(hair, axis=1), axis=2).sum(axis=1)
    return v, f, hair, roots, arc


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strands", type=int, default=1024)
    parser.add_argument("--vertices", type=int, default=100)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--torch-strands", type=int, default=4)
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args(argv)

    device = torch.device(args.device)
    set_finite_checks(False)  # a hot loop trusts its inputs (the scan syncs on CUDA)
    cfg = EnergyConfig()
    rng = np.random.default_rng(0)
    v, f, hair, roots, arc = make_scene(rng, args.strands, args.vertices)
    vt = torch.tensor(v, dtype=torch.float32, device=device)
    ft = torch.tensor(f, dtype=torch.int32, device=device)
    x = torch.tensor(hair, dtype=torch.float32, device=device)[None]
    x = x.expand(args.batch, -1, -1, -1).contiguous().requires_grad_(True)
    params = (cfg.hair_body_xi, cfg.hair_body_dhat, cfg.barrier_join_fraction, cfg.hair_body_weight)

    results = {
        "machine": machine_name(device),
        "strands": args.strands,
        "vertices": args.vertices,
        "batch": args.batch,
        "body_vertices": len(v),
        "body_faces": len(f),
    }
    results["build_ms"] = time_ms(lambda: ops.BodyMesh(vt, ft), device, warmup=1, repeats=3)
    body = ops.BodyMesh(vt, ft)
    results["refit_ms"] = time_ms(lambda: body.update(vt), device, repeats=args.repeats)
    roots_t = torch.tensor(roots, dtype=torch.float32, device=device)
    arc_t = torch.tensor(arc, dtype=torch.float32, device=device)
    results["crop_ms"] = time_ms(lambda: body.crop_for_hair(roots_t, arc_t), device, repeats=5)
    crop = body.crop_for_hair(roots_t, arc_t)
    results["crop_faces"] = crop.num_faces
    results["crop_removed_fraction"] = 1.0 - crop.num_faces / body.num_faces

    def step(fn):
        def run():
            x.grad = None
            fn(x).sum().backward()

        return run

    def energy(b, strategy=None):
        if strategy is None:
            return lambda y: ops.hair_body_contact_energy(y, b, *params[:3], weight=params[3])
        return lambda y: ops._HairBodyContactEnergy.apply(y, b, *params, 1, strategy)

    with torch.no_grad():
        d = ops.hair_body_signed_distance(x[0], body)
        _, _, queries = ops._energy_forward(x.detach(), body, *params, 1, "strand")
    results["inside_fraction"] = float((d < 0).float().mean())
    results["within_reach_fraction"] = float((d < params[0] + params[1]).float().mean())
    moving = x.shape[0] * x.shape[1] * (x.shape[2] - 2)
    results["strand_walk_queries_per_vertex"] = float(queries.sum()) / moving

    timings = {
        "warp_full_auto": step(energy(body)),
        "warp_crop_auto": step(energy(crop)),
        "warp_full_strand": step(energy(body, "strand")),
        "warp_full_vertex": step(energy(body, "vertex")),
        "warp_crop_strand": step(energy(crop, "strand")),
    }
    for name, fn in timings.items():
        results[f"{name}_ms"] = time_ms(fn, device, repeats=args.repeats)
    sd = lambda: ops.hair_body_signed_distance(x.detach(), body)  # noqa: E731
    results["signed_distance_ms"] = time_ms(sd, device, repeats=5)

    # The plain-torch brute force on a few strands only; scaled to the full hair per vertex.
    k = min(args.torch_strands, args.strands)
    xs = x[:, :k].detach().clone().requires_grad_(True)

    def torch_step():
        xs.grad = None
        torch_ref.hair_body_contact_energy(xs, vt, ft, *params[:3], weight=params[3]).sum().backward()

    t = time_ms(torch_step, device, warmup=1, repeats=3, min_time_s=0.0)
    results["torch_reference_strands"] = k
    results["torch_reference_ms"] = t
    results["torch_reference_full_hair_ms_estimate"] = t * args.strands / k

    for key, value in results.items():
        print(f"{key:42s} {value:.4g}" if isinstance(value, float) else f"{key:42s} {value}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
