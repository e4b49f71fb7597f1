"""`hairwarp export`: convert hair (and body) files between the formats artists' tools read.

    hairwarp export drape.data drape.usda                  # strands -> USD BasisCurves
    hairwarp export simulate.usdc hair.ply --frame 30 --body-out body.obj
    hairwarp export simulate.usda frames/ --all-frames --format obj   # hair_0000.obj, body_0000.obj, ...
    hairwarp export z.npy hair.data                        # a hair latent, decoded by the shipped basis
    hairwarp export perm_hair.data hair.usda --units cm --num-vertices 100

Inputs: `.data` (USC-HairSalon strands), `.usd`/`.usda`/`.usdc` (hair BasisCurves and body Mesh,
animated), `.obj`/`.ply` hair polylines, `.npy` (strands (M, N, 3) or (T, M, N, 3) [m], or a
hair latent of 512 numbers). Outputs by suffix: `.data`, `.obj`, `.ply` (one frame), `.usd`,
`.usda`, `.usdc` (every frame, the body too when the input has one). Everything in metres, y up.
"""

from __future__ import annotations

import argparse
import os

HAIR_INPUTS = (".data", ".usd", ".usda", ".usdc", ".obj", ".ply", ".npy")
HAIR_OUTPUTS = (".data", ".obj", ".ply", ".usd", ".usda", ".usdc")
USD = (".usd", ".usda", ".usdc")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="convert hair files (.data/.usd*/.obj/.ply/.npy) to .data/.obj/.ply/.usd*; body to .obj/.ply",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
    )
    p.add_argument("input", help=f"hair file ({', '.join(HAIR_INPUTS)})")
    p.add_argument("output", help=f"output file ({', '.join(HAIR_OUTPUTS)}), or a folder with --all-frames")
    p.add_argument("--frame", type=int, default=0,
                   help="frame written to single-frame formats (.data/.obj/.ply, --body-out) (default: 0)")
    p.add_argument("--all-frames", action="store_true",
                   help="write every frame as numbered files into the OUTPUT folder (hair and body)")
    p.add_argument("--format", choices=("ply", "obj"), default="ply", help="--all-frames: file format (default: ply)")
    p.add_argument("--body-out", default=None, help="also write the body mesh of --frame here (.obj or .ply)")
    p.add_argument("--units", choices=("auto", "m", "cm", "mm"), default="auto",
                   help=".data input: its length unit; auto = cm when the hair spans more than 3 units (default: auto)")
    p.add_argument("--num-vertices", type=int, default=None,
                   help="resample every strand to this many vertices (default: keep; .data strands of "
                        "unequal counts are resampled to the largest count for formats that need equal counts)")
    p.add_argument("--fps", type=float, default=None, help="USD output: frames per second (default: the input's, else 60)")
    p.add_argument("--up-axis", choices=("Y", "Z"), default="Y", help="USD output: stage up axis (default: Y)")
    p.add_argument("--ascii", action="store_true", help="PLY output: ASCII instead of binary")
    p.set_defaults(run=run)


def _read(path: str, units: str):
    """(hair (T, M, N, 3) float32 tensor [m] or a list of (n_i, 3) arrays, body vertices, faces, fps)."""
    import numpy as np

    from hairwarp.builder import data_units
    from hairwarp.io.export import read_hair_obj, read_hair_ply
    from hairwarp.io.hair_data import LENGTH_UNITS, read_hair_data
    from hairwarp.io.usd import read_usd

    suffix = os.path.splitext(path)[1].lower()
    if suffix not in HAIR_INPUTS:
        raise ValueError(f"input: expected a file ending in {', '.join(HAIR_INPUTS)}, got {path!r}")
    if not os.path.isfile(path):
        raise ValueError(f"input: no such file {path!r}")
    try:
        if suffix == ".data":
            scale = LENGTH_UNITS[data_units(path, units)]
            strands = [(a.astype(np.float64) * scale).astype(np.float32) for a in read_hair_data(path)]
            strands = [a for a in strands if len(a) >= 2]
            if not strands:
                raise ValueError(f"{path}: no strand with at least 2 vertices")
            return strands, None, None, None
        if suffix in USD:
            d = read_usd(path)
            return d["hair"], d["body_vertices"], d["body_faces"], d["fps"]
        if suffix == ".obj":
            return read_hair_obj(path)[None], None, None, None
        if suffix == ".ply":
            return read_hair_ply(path)[None], None, None, None
        return _read_npy(path), None, None, None
    except (ValueError, KeyError, OSError) as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"input: {text}") from None


def _read_npy(path: str):
    import numpy as np
    import torch

    from hairwarp.scene.hair_latent import HairLatentBasis

    a = np.load(path, allow_pickle=False)
    if not np.issubdtype(a.dtype, np.number) or not np.isfinite(a).all():
        raise ValueError(f"{path}: expected finite numbers, got dtype {a.dtype} (or NaN/Inf)")
    basis = HairLatentBasis.load_default()
    if a.size == basis.latent_dim:
        strands, _ = basis.decode(torch.as_tensor(a, dtype=torch.float64).reshape(-1))
        return strands.to(torch.float32)[None]
    if a.ndim in (3, 4) and a.shape[-1] == 3:
        t = torch.as_tensor(a, dtype=torch.float32)
        return t if a.ndim == 4 else t[None]
    raise ValueError(f"{path}: expected strands (M, N, 3), (T, M, N, 3) or a latent of {basis.latent_dim} numbers, "
                     f"got shape {a.shape}")


def _equal_counts(hair, num_vertices: int | None):
    """(T, M, N, 3) tensor from a tensor or a list of strands, resampled to `num_vertices` if given.

    A list of strands with unequal vertex counts is resampled by arc length to the largest
    count when `num_vertices` is None.
    """
    import numpy as np
    import torch

    from hairwarp.scene.hairstyles import resample_strands

    if isinstance(hair, list):
        counts = {len(a) for a in hair}
        if num_vertices is None and len(counts) == 1:
            return torch.as_tensor(np.stack(hair))[None]
        return resample_strands(hair, num_vertices or max(counts))[None]
    if num_vertices is not None and num_vertices != hair.shape[2]:
        t, m, n, _ = hair.shape
        return resample_strands(hair.reshape(t * m, n, 3), num_vertices).reshape(t, m, num_vertices, 3)
    return hair


def run(args) -> int:
    from hairwarp.io.export import export_frames, write_hair_obj, write_hair_ply, write_mesh_obj, write_mesh_ply
    from hairwarp.io.hair_data import write_hair_data
    from hairwarp.io.usd import write_usd

    if args.num_vertices is not None and args.num_vertices < 2:
        raise ValueError(f"--num-vertices: expected an integer >= 2, got {args.num_vertices}")
    if args.fps is not None and not args.fps > 0:
        raise ValueError(f"--fps: expected a positive number, got {args.fps}")
    out_suffix = os.path.splitext(args.output)[1].lower()
    if not args.all_frames and out_suffix not in HAIR_OUTPUTS:
        raise ValueError(f"output: expected a file ending in {', '.join(HAIR_OUTPUTS)}, got {args.output!r} "
                         "(or pass --all-frames with a folder)")
    if args.body_out is not None and os.path.splitext(args.body_out)[1].lower() not in (".obj", ".ply"):
        raise ValueError(f"--body-out: expected a file ending in .obj or .ply, got {args.body_out!r}")
    hair, body_v, faces, fps = _read(args.input, args.units)
    written = []
    if out_suffix == ".data" and isinstance(hair, list) and args.num_vertices is None and not args.all_frames:
        write_hair_data(args.output, hair)  # strands of any counts, as they are
        written.append(args.output)
        frames = None
    else:
        frames = _equal_counts(hair, args.num_vertices)
    if frames is not None:
        t = frames.shape[0]
        if not 0 <= args.frame < t:
            raise ValueError(f"--frame: the input has {t} frame(s); frame {args.frame} is outside it")
        if args.all_frames:
            written += export_frames(args.output, frames, body_v, faces, fmt=args.format, binary=not args.ascii)
        elif out_suffix in USD:
            written.append(write_usd(args.output, frames, body_v, faces, fps=args.fps or fps or 60.0,
                                     up_axis=args.up_axis))
        elif out_suffix == ".data":
            write_hair_data(args.output, frames[args.frame])
            written.append(args.output)
        elif out_suffix == ".obj":
            written.append(write_hair_obj(args.output, frames[args.frame]))
        else:
            written.append(write_hair_ply(args.output, frames[args.frame], binary=not args.ascii))
    if args.body_out is not None:
        if body_v is None:
            raise ValueError(f"--body-out: {args.input!r} holds no body mesh (only USD files written with one do)")
        b = body_v[min(args.frame, len(body_v) - 1)]
        if args.body_out.lower().endswith(".obj"):
            written.append(write_mesh_obj(args.body_out, b, faces))
        else:
            written.append(write_mesh_ply(args.body_out, b, faces, binary=not args.ascii))
    shown = written if len(written) <= 4 else written[:2] + [f"... {len(written) - 3} more ..."] + written[-1:]
    print(f"wrote {', '.join(shown)}")
    return 0
