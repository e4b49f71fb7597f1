"""A large foreign groom's load, stage by stage, and how its strands leave our scalp after the fit.

    python3 benchmarks/bm_groom_load.py --out OUT                      # 10 000 and 100 000 strands, .data and .usdc
    python3 benchmarks/bm_groom_load.py --out OUT --strands 10000 --formats data --no-root-check

For each size and format, a groom of tools/foreign_grooms.py (seed 0: grown on a head 15 %
wider and 10 % flatter than ours, in centimetres, 40-80 vertices a strand, 2 % bald-root
markers in the .data) is written to OUT and loaded onto the default body, each stage timed
once (wall clock):
- read: `read_hair_data_flat` (.data); `read_usd_curves` (USD, its unit, axis and Xform
  conversion included);
- transform: .data: centimetres -> metres on the concatenated points; USD: the strands
  concatenated (`flatten_strands`);
- fit: the ICP (`fit_similarity_to_scalp`, on 4096 of the roots);
- normals: the old scalp's normals at the roots (`estimate_root_normals`);
- attach: lengths, filter, resampling to 100 vertices, nearest scalp root, snap and turn
  (`attach_flat_strands`);
- load: the library's load as one call (`hairwarp.io.hair_data.load_hairstyle`, or
  `read_usd_curves` + `place_groom`);
- build_scene: `hairwarp.builder.build_scene(hairstyle=path, pose="rest")`, everything in
  (the body, the builder's unit check of a .data, the guides of a groom over 1024 strands);
- guides: of that, `hairwarp.builder.make_guides` on the loaded groom, timed on its own;
- build_no_guides: `build_scene(..., guides=<the groom's strand count>)`: every strand
  simulated, no guide set chosen.

The root check (`--root-strands`, 400): the tool's groom fitted to the default body by
`build_scene`, placed rigidly at frame 0; vertices inside the body (root vertex left out): %
of all, count in the first tenth of the strands, % of strands with any. "before": the load
without the turn at the roots; "rigid": whole strands turned about their roots from the old
normal to the new (the variant not taken, kept here as its measurement); "after": the library
(the root part turned). Also the first segments' median angle to the scalp normal [deg].

The load itself runs in numpy and scipy (no torch threads); the guide selection runs in torch,
and with torch's default 2 threads on a 2-core CPU whose other core is busy it took 26-34 s for
100 000 strands against 3 s with one thread, hence `--threads 1` (the commands' default).

Writes OUT/groom_load.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time

import numpy as np
import torch

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tools"))
sys.path.insert(0, str(HERE.parent / "tests"))
import foreign_grooms  # noqa: E402
from test_groom_fit import _root_region  # noqa: E402

from hairwarp.builder import build_scene, load_body, make_guides  # noqa: E402
from hairwarp.io.hair_data import LENGTH_UNITS, load_hairstyle, read_hair_data_flat  # noqa: E402
from hairwarp.io.usd import read_usd_curves  # noqa: E402
from hairwarp.runtime import machine_name  # noqa: E402
from hairwarp.scene.groom import (  # noqa: E402
    attach_flat_strands,
    estimate_root_normals,
    fit_similarity_to_scalp,
    flatten_strands,
    place_groom,
)

NUM_VERTICES = 100
MIN_LENGTH = 0.02  # [m], as the builder loads grooms


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def load_stages(path: str, fmt: str, body, scalp) -> dict:
    """Seconds per stage of one groom's load (see the module docstring)."""
    head = body.rest_vertices[body.head_vertex_indices].double().numpy()
    times = {}
    if fmt == "data":
        (raw, counts), times["read"] = _timed(lambda: read_hair_data_flat(path))
        points, times["transform"] = _timed(lambda: raw.astype(np.float64) * LENGTH_UNITS["cm"])
    else:
        curves, times["read"] = _timed(lambda: read_usd_curves(path))
        (points, counts), times["transform"] = _timed(lambda: flatten_strands(curves["strands"]))
    usable = counts >= 2
    roots = points[(np.cumsum(counts) - counts)[usable]]
    fit, times["fit"] = _timed(lambda: fit_similarity_to_scalp(roots, scalp, head))
    moved = fit.apply(points)
    old = np.zeros((len(counts), 3))
    old[usable], times["normals"] = _timed(lambda: estimate_root_normals(fit.apply(roots)))
    style, times["attach"] = _timed(lambda: attach_flat_strands(moved, counts, scalp, num_vertices=NUM_VERTICES,
                                                                min_length=MIN_LENGTH, old_normals=old))
    if fmt == "data":
        _, times["load"] = _timed(lambda: load_hairstyle(path, scalp, units="cm", align="auto", head_points=head))
    else:
        _, times["load"] = _timed(lambda: place_groom(read_usd_curves(path)["strands"], scalp, head,
                                                       num_vertices=NUM_VERTICES, min_length=MIN_LENGTH))
    scene, times["build_scene"] = _timed(lambda: build_scene(hairstyle=path, pose="rest"))
    groom = scene.hairstyle if scene.guides is None else scene.guides.groom
    _, times["guides"] = _timed(lambda: make_guides(groom, None))
    # Every strand simulated (guides = the groom's strand count: no guide set).
    _, times["build_no_guides"] = _timed(lambda: build_scene(hairstyle=path, pose="rest", guides=groom.num_strands))
    return {"strands_in_file": int(len(counts)), "strands_loaded": groom.num_strands, "vertices": int(counts.sum()),
            "fit": fit.describe(), "seconds": times}


def _rigid_turn(style, old_normals, new_normals):
    """Whole strands turned about their roots (Rodrigues) from `old` to `new` normals."""
    x = style.strands.double().numpy()
    v = np.cross(old_normals, new_normals)
    c = np.einsum("ki,ki->k", old_normals, new_normals)
    skew = np.zeros((len(v), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    skew -= skew.transpose(0, 2, 1)
    rot = np.eye(3) + skew + skew @ skew / (1.0 + c)[:, None, None]
    out = x[:, :1] + np.einsum("mij,mnj->mni", rot, x - x[:, :1])
    return dataclasses.replace(style, strands=torch.tensor(out, dtype=torch.float32))


def _first_segment_angle(scene) -> float:
    frames = scene.frames([0])
    x, normals = frames.rigid.positions[0].double(), frames.rigid.normals[0].double()
    first = x[:, 1] - x[:, 0]
    cos = (first / first.norm(dim=1, keepdim=True) * normals).sum(1).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos)).median())


def root_check(path: str) -> dict:
    """Inside counts before, rigid and after for one `.data` groom (see the module docstring)."""
    scene = build_scene(hairstyle=path, pose="rest")
    head = scene.body.rest_vertices[scene.body.head_vertex_indices].double().numpy()
    before = load_hairstyle(path, scene.scalp, units="cm", align="auto", head_points=head, orient_roots=False)
    # The old normals of the kept strands, as the library estimates them.
    raw, counts = read_hair_data_flat(path)
    points = raw.astype(np.float64) * LENGTH_UNITS["cm"]
    roots = points[(np.cumsum(counts) - counts)[counts >= 2]]
    fit = fit_similarity_to_scalp(roots, scene.scalp, head)
    old = np.zeros((len(counts), 3))
    old[counts >= 2] = estimate_root_normals(fit.apply(roots))
    kept = np.setdiff1d(np.arange(len(counts)), before.filtered.numpy())
    new = scene.scalp.normals.double().numpy()[before.root_index.numpy()]
    new /= np.linalg.norm(new, axis=1, keepdims=True)
    rigid = _rigid_turn(before, old[kept], new)
    rows = {}
    for name, style in (("before", before), ("rigid", rigid), ("after", scene.hairstyle)):
        s = dataclasses.replace(scene, hairstyle=style)
        rows[name] = dict(_root_region(s), first_segment_angle_deg=_first_segment_angle(s))
    rows["turn_deg_median"] = scene.hairstyle.info["root_rotation_deg_median"]
    rows["fit"] = scene.hairstyle.info["fit"]
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="folder for the grooms and groom_load.json")
    p.add_argument("--strands", default="10000,100000", help="comma-separated groom sizes (default: 10000,100000)")
    p.add_argument("--formats", default="data,usdc", help="comma-separated, of data, usdc (default: both)")
    p.add_argument("--root-strands", type=int, default=400, help="the root check's groom size (default: 400)")
    p.add_argument("--no-root-check", action="store_true", help="skip the root check")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads, as the commands' --threads (default: 1; 0 leaves torch's default)")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    sizes = [int(s) for s in args.strands.split(",") if s.strip()]
    formats = [f for f in args.formats.split(",") if f]
    if not sizes or any(s < 1 for s in sizes):
        p.error(f"--strands: expected positive counts, got {args.strands!r}")
    if not formats or any(f not in ("data", "usdc") for f in formats):
        p.error(f"--formats: expected some of data, usdc, got {args.formats!r}")
    os.makedirs(args.out, exist_ok=True)
    body, scalp, _ = load_body("default")
    build_scene(hairstyle="short_straight", pose="rest", strand_stride=64)  # imports and caches warm
    record = {"machine": machine_name(torch.device("cpu")), "torch_threads": torch.get_num_threads(),
              "command": "python3 benchmarks/bm_groom_load.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "loads": []}
    stages = ("read", "transform", "fit", "normals", "attach", "load", "build_scene", "guides", "build_no_guides")
    print(f"{record['machine']}\n")
    print(f"| strands | format | {' | '.join(stages)} |  [s]")
    print("|---|---|" + "---|" * len(stages))
    for size in sizes:
        for fmt in formats:
            path = os.path.join(args.out, f"groom_{size}.{fmt}")
            if fmt == "data":
                foreign_grooms.write_data_groom(path, size, seed=0)
            else:
                foreign_grooms.write_usd_groom(path, size, seed=0)
            row = load_stages(path, fmt, body, scalp)
            row.update(strands=size, format=fmt)
            record["loads"].append(row)
            print(f"| {size} | {fmt} | " + " | ".join(f"{row['seconds'][s]:.2f}" for s in stages) + " |", flush=True)
    if not args.no_root_check:
        path = foreign_grooms.write_data_groom(os.path.join(args.out, f"groom_{args.root_strands}.data"),
                                               args.root_strands, seed=0)
        check = root_check(path)
        record["root_check"] = check
        print(f"\nroot check, {args.root_strands} strands ({check['fit']}; median turn {check['turn_deg_median']:.1f} deg)")
        print("| | inside % | first-tenth inside | strands with inside % | first segment to normal [deg] |")
        print("|---|---|---|---|---|")
        for name in ("before", "rigid", "after"):
            r = check[name]
            print(f"| {name} | {r['inside_percent']:.2f} | {r['first_tenth_inside']} | "
                  f"{r['strands_inside_percent']:.1f} | {r['first_segment_angle_deg']:.1f} |")
    with open(os.path.join(args.out, "groom_load.json"), "w") as f:
        json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
