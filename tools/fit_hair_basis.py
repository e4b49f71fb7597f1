"""Fit the 512-d hair latent basis on a corpus of procedural hairstyles.

    python tools/fit_hair_basis.py --styles 1200 --heldout 100 \
        --out src/hairwarp/assets/hair_basis.npz

Generates `--styles` random hairstyles (`sample_hairstyle_params`) on the scalp grid, fits the
three-stage linear basis of `hairwarp.scene.hair_latent` (strand PCA -> spatial PCA -> 512
latent components) and reports the reconstruction error decode(encode(s)) on corpus styles and
on held-out styles of the same family, and the file size. The scalp is the synthetic sphere
cap of `sphere_cap_scalp()` unless `--scalp body` finds `build_scalp(default_body())`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

from hairwarp.scene.hair_latent import LATENT_DIM, HairLatentBasis, fit_hair_latent_basis
from hairwarp.scene.hairstyles import generate_hairstyle, sample_hairstyle_params, sphere_cap_scalp


def get_scalp(kind: str):
    if kind == "body":
        from hairwarp.scene.body import default_body  # noqa: PLC0415 (lands with the body work)
        from hairwarp.scene.scalp import build_scalp  # noqa: PLC0415

        return build_scalp(default_body())
    return sphere_cap_scalp()


def grid_strands(style, scalp) -> np.ndarray:
    """(M, N, 3) strands on every grid root: filtered roots borrow the nearest kept strand."""
    strands = style.strands.double().numpy()
    m = scalp.num_roots
    if style.num_strands == m:
        return strands
    uv = scalp.uv.double().numpy()
    kept_uv = style.root_uv.double().numpy()
    j = ((uv[:, None] - kept_uv[None]) ** 2).sum(-1).argmin(axis=1)
    roots = scalp.positions.double().numpy()
    return strands[j] - strands[j, :1] + roots[:, None]


def corpus(scalp, params_list, log_every=100):
    start = time.perf_counter()
    for i, p in enumerate(params_list):
        yield grid_strands(generate_hairstyle(scalp, p), scalp)
        if (i + 1) % log_every == 0:
            print(f"  {i + 1}/{len(params_list)} styles, {time.perf_counter() - start:.0f} s", flush=True)


def errors(basis, scalp, params_list):
    """Per-vertex reconstruction distances [m] of decode(encode(s)) over the given styles."""
    d = []
    for p in params_list:
        s = torch.tensor(grid_strands(generate_hairstyle(scalp, p), scalp))
        rec, _ = basis.decode(basis.encode(s))
        d.append((rec - s).norm(dim=-1).numpy())
    d = np.stack(d)
    return {"mean": float(d.mean()), "p99": float(np.percentile(d, 99)), "max": float(d.max()),
            "tip_mean": float(d[:, :, -1].mean())}


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--styles", type=int, default=1200, help="corpus size (> 512)")
    parser.add_argument("--heldout", type=int, default=100, help="held-out styles for the error report")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--scalp", choices=("synthetic", "body"), default="synthetic")
    parser.add_argument("--out", default=os.path.join("src", "hairwarp", "assets", "hair_basis.npz"))
    args = parser.parse_args(argv)
    if args.styles <= LATENT_DIM:
        parser.error(f"--styles must exceed the latent size {LATENT_DIM}")
    scalp = get_scalp(args.scalp)
    rng = np.random.default_rng(args.seed)
    train = [sample_hairstyle_params(rng) for _ in range(args.styles)]
    held = [sample_hairstyle_params(rng) for _ in range(args.heldout)]
    print(f"fitting on {args.styles} procedural styles, {scalp.num_roots} roots ({args.scalp} scalp)")
    t0 = time.perf_counter()
    basis = fit_hair_latent_basis(corpus(scalp, train), scalp, info={"seed": args.seed, "scalp": args.scalp})
    print(f"fit: {time.perf_counter() - t0:.0f} s; {basis.info}")
    basis.save(args.out)
    basis = HairLatentBasis.load(args.out)  # measure what ships: float16 factors
    basis.info["error_corpus_m"] = errors(basis, scalp, train[:50])
    basis.info["error_heldout_m"] = errors(basis, scalp, held)
    basis.info["file_bytes"] = os.path.getsize(args.out)
    basis.save(args.out)
    size = os.path.getsize(args.out)
    mm = lambda e: ", ".join(f"{k} {1000 * v:.2f} mm" for k, v in e.items())  # noqa: E731
    print(f"wrote {args.out}: {size / 2**20:.2f} MiB")
    print(f"decode(encode(s)) corpus (50 styles): {mm(basis.info['error_corpus_m'])}")
    print(f"decode(encode(s)) held-out ({args.heldout} styles): {mm(basis.info['error_heldout_m'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
