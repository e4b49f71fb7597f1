"""Scenes built from files made outside the project, measured as a user would measure them.

Writes, with plain numpy / struct (none of hairwarp's writers), into --out:

- `groom_cm.data`: a USC-HairSalon `.data` groom (little-endian int32 strand count, then per
  strand an int32 vertex count and that many float32 x, y, z). Its strands start as a
  procedural hairstyle of the default body (the only hair this machine has), then are made
  foreign: every strand resampled by arc length to its own vertex count (40-64), shuffled,
  jittered (a smooth wiggle growing from the root plus sub-millimetre noise), 1-vertex
  bald-root markers mixed in as USC-HairSalon files have them, and the whole groom put on
  "another head": scaled, rotated, moved to a world with the feet at the origin, written in
  centimetres (y up by default; `--up z` writes z up). Loading it needs the ICP fit
  (`--fit auto`, the default) and `--data-units` (auto finds cm).
- `motion_amass.npz`: an AMASS-format SMPL+H motion (`poses` T x 156, `trans` T x 3,
  `betas` 16, `dmpls` T x 8, `gender`, `mocap_framerate` 120), z up as AMASS is, the body
  facing the first of `--headings` degrees about the vertical (`motion_amass_h<deg>.npz` for
  the others) and its pelvis ~0.9 m above the floor: it stands still, looks over its left
  shoulder and back, and bends forward with a nod, with mocap-like jitter on every joint.

Then it builds the scenes from those files through `hairwarp.build_scene` (the code behind
`hairwarp drape` / `hairwarp simulate`), runs the methods with the options those commands use,
scores them with the commands' own metrics (`run_and_score`), and writes OUT/foreign_scenes.json
and OUT/foreign_scenes.md (per scene and method: penetration % mean / worst frame, length
change % mean / worst frame, ms/frame, and the share of the rigid placement's penetration
removed) and one picture per scene (the dynamic network's result; red = inside the body).

    python tools/foreign_scenes.py --out /tmp/foreign                 # 3 scenes, 256 strands, ~2 min on 2 cores
    python tools/foreign_scenes.py --out /tmp/foreign --headings 30,0,90,180   # + the heading sweep (~9 min)
    python tools/foreign_scenes.py --out /tmp/foreign --scenes data_amass --methods rigid,dynamic

Results (2-core CPU) and what they showed: docs/characters.md, "Foreign files, measured".

Each row is also one command line (its "command" in the JSON), e.g.
    hairwarp simulate --hairstyle OUT/groom_cm.data --pose OUT/motion_amass.npz --method dynamic --strand-stride 4
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import struct
import sys
import time

import numpy as np

# Scene name -> (hairstyle: "groom" = the written .data, else a preset; pose: "motion" = the
# written AMASS file, else "rest"; simulate (True) or drape (False)).
SCENES = {
    "data_rest": ("groom", "rest", False),
    "data_amass": ("groom", "motion", True),
    "preset_amass": ("long_straight", "motion", True),
}
METHODS = ("rigid", "static", "dynamic", "auto")
# Column groups of an AMASS SMPL+H `poses` row: 22 body joints, then 2 x 15 hand joints.
SMPLH_COLUMNS = 156
NUM_BODY_JOINTS = 22
JOINT = {"pelvis": 0, "left_hip": 1, "right_hip": 2, "spine1": 3, "spine2": 6, "spine3": 9, "neck": 12,
         "left_collar": 13, "right_collar": 14, "head": 15, "left_shoulder": 16, "right_shoulder": 17,
         "left_elbow": 18, "right_elbow": 19}


# ------------------------------------------------------------------ plain numpy rotations


def rotation(axis: str, angle) -> np.ndarray:
    """(..., 3, 3) rotation matrices by `angle` [rad] about a coordinate axis."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = {"x": [[o, z, z], [z, c, -s], [z, s, c]],
            "y": [[c, z, s], [z, o, z], [-s, z, c]],
            "z": [[c, -s, z], [s, c, z], [z, z, o]]}[axis]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_axis_angle(m: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle vectors (angle in [0, pi]) of (..., 3, 3) rotation matrices.

    Through the quaternion, taken from the largest of its four components (Shepperd), so
    rotations near 180 degrees (a body facing backwards) come out exact.
    """
    m = np.asarray(m, dtype=np.float64)
    tr = np.trace(m, axis1=-2, axis2=-1)
    d = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    k = d.argmax(axis=-1)
    q = np.empty(m.shape[:-2] + (4,))  # w, x, y, z
    s01, s10 = m[..., 0, 1], m[..., 1, 0]
    s02, s20 = m[..., 0, 2], m[..., 2, 0]
    s12, s21 = m[..., 1, 2], m[..., 2, 1]
    cands = [
        np.stack([1 + tr, s21 - s12, s02 - s20, s10 - s01], axis=-1),
        np.stack([s21 - s12, 1 + 2 * m[..., 0, 0] - tr, s01 + s10, s02 + s20], axis=-1),
        np.stack([s02 - s20, s01 + s10, 1 + 2 * m[..., 1, 1] - tr, s12 + s21], axis=-1),
        np.stack([s10 - s01, s02 + s20, s12 + s21, 1 + 2 * m[..., 2, 2] - tr], axis=-1),
    ]
    for i, c in enumerate(cands):
        q = np.where((k == i)[..., None], c, q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(n, q[..., 0])
    scale = np.where(n > 1e-12, angle / np.where(n > 1e-12, n, 1.0), 2.0)
    return v * scale[..., None]


# ------------------------------------------------------------------ the .data groom


def write_usc_data(path: str, strands) -> None:
    """A USC-HairSalon `.data` file: int32 count, per strand int32 n and n x 3 float32 (LE)."""
    with open(path, "wb") as f:
        f.write(struct.pack("<i", len(strands)))
        for s in strands:
            s = np.asarray(s, dtype="<f4").reshape(-1, 3)
            f.write(struct.pack("<i", len(s)))
            f.write(s.tobytes())


def resample_by_arc_length(points: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) points evenly spaced by arc length along the polyline `points` (k, 3)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, k]) for k in range(3)], axis=1)


def foreign_strands(strands_m: np.ndarray, rng: np.random.Generator, *, vertex_range=(40, 64),
                    wiggle_mm: float = 1.5, noise_mm: float = 0.2, bald_fraction: float = 0.05,
                    scale: float = 1.06, rotation_deg=(3.0, 4.0, 0.0),
                    offset_m=(0.012, 1.128, -0.015)) -> list[np.ndarray]:
    """Strands (M, N, 3) [m, y up] as another tool's groom on another head, in metres, y up.

    Each strand: resampled to a random vertex count in `vertex_range`, a smooth wiggle of
    `wiggle_mm` growing from zero at the root plus `noise_mm` white noise (not on the root);
    the groom: scaled by `scale` and rotated by `rotation_deg` (about x, y, z) about its mean
    root, moved by `offset_m` (the default puts the default body's feet at the origin); then
    `bald_fraction` 1-vertex bald-root markers mixed in and the strand order shuffled.
    """
    strands_m = np.asarray(strands_m, dtype=np.float64)
    out = []
    for s in strands_m:
        n = int(rng.integers(vertex_range[0], vertex_range[1] + 1))
        p = resample_by_arc_length(s, n)
        u = np.linspace(0.0, 1.0, n)[:, None]
        k = np.arange(1, 4)[None, :]
        phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
        amp = rng.normal(size=(3, 3)) / k.T
        wiggle = np.stack([(amp[d] * np.sin(2 * np.pi * k * u + phase[d])).sum(1) for d in range(3)], axis=1)
        p = p + 1e-3 * wiggle_mm * u * wiggle / 2.0
        p[1:] += 1e-3 * noise_mm * rng.normal(size=(n - 1, 3))
        out.append(p)
    centre = np.mean([s[0] for s in out], axis=0)
    r = rotation("z", math.radians(rotation_deg[2])) @ rotation("y", math.radians(rotation_deg[1])) \
        @ rotation("x", math.radians(rotation_deg[0]))
    out = [(scale * (s - centre)) @ r.T + centre + np.asarray(offset_m) for s in out]
    bald = [out[i][:1] + 1e-3 * rng.normal(size=(1, 3))
            for i in rng.choice(len(out), size=int(round(bald_fraction * len(out))), replace=False)]
    everything = out + bald
    order = rng.permutation(len(everything))
    return [everything[i] for i in order]


def to_file_axes(strands_m: list[np.ndarray], units: str = "cm", up: str = "y") -> list[np.ndarray]:
    """Metres, y up -> the file's units and up axis (z up: (x, y, z) -> (x, -z, y))."""
    factor = {"m": 1.0, "cm": 100.0, "mm": 1000.0}[units]
    out = []
    for s in strands_m:
        q = s if up == "y" else np.stack([s[:, 0], -s[:, 2], s[:, 1]], axis=1)
        out.append(factor * q)
    return out


def source_hairstyle(name: str = "medium_wavy", seed: int = 0, strand_stride: int = 1,
                     grow: str = "body") -> np.ndarray:
    """(M, 100, 3) strands [m] of a procedural hairstyle on the default body (the groom's start)."""
    from hairwarp.builder import load_body, load_hairstyle

    body, scalp, _ = load_body("default")
    style = load_hairstyle(name, body, scalp, grow=grow, strand_stride=strand_stride, num_vertices=100, seed=seed)
    return style.strands.detach().cpu().double().numpy()


def build_groom(out: str, seed: int = 0, *, hairstyle: str = "medium_wavy", units: str = "cm", up: str = "y",
                strand_stride: int = 1, grow: str = "body", source: np.ndarray | None = None) -> str:
    """Write OUT/groom_<units>.data (see the module docstring); returns its path."""
    rng = np.random.default_rng(seed)
    if source is None:
        source = source_hairstyle(hairstyle, seed, strand_stride, grow)
    strands = to_file_axes(foreign_strands(source, rng), units, up)
    path = os.path.join(out, f"groom_{units}.data" if up == "y" else f"groom_{units}_zup.data")
    write_usc_data(path, strands)
    return path


# ------------------------------------------------------------------ the AMASS motion


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def amass_motion(seed: int = 0, *, duration: float = 1.2, fps: float = 120.0, heading_deg: float = 30.0,
                 turn_deg: float = 55.0, bend_deg: float = 35.0) -> dict:
    """The arrays of an AMASS SMPL+H `.npz` (z up): a look over the left shoulder and back, and
    a forward bend with a nod, after 0.15 s standing still; see the module docstring."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration * fps)) + 1) / fps
    frames = len(t)
    turn = math.radians(turn_deg) * (_smoothstep((t - 0.15) / 0.35) - _smoothstep((t - 0.6) / 0.35))
    bend = math.radians(bend_deg) * (_smoothstep((t - 0.45) / 0.4) - _smoothstep((t - 0.95) / 0.3))
    nod = 0.45 * bend
    mats = np.broadcast_to(np.eye(3), (frames, NUM_BODY_JOINTS, 3, 3)).copy()

    def put(joint, m):
        mats[:, JOINT[joint]] = m @ mats[:, JOINT[joint]]

    # Arms at the sides (SMPL's T-pose lowered ~65 degrees at the shoulders), elbows a little bent.
    put("left_shoulder", rotation("z", np.full(frames, -math.radians(65))))
    put("right_shoulder", rotation("z", np.full(frames, math.radians(65))))
    put("left_elbow", rotation("y", np.full(frames, 0.25)))
    put("right_elbow", rotation("y", np.full(frames, -0.25)))
    # +x turns +y toward +z: the upper body leans toward the face.
    for joint, share in (("spine1", 0.3), ("spine2", 0.35), ("spine3", 0.35)):
        put(joint, rotation("x", share * bend))
    put("spine3", rotation("y", 0.1 * turn))
    put("neck", rotation("y", 0.35 * turn) @ rotation("x", 0.4 * nod))
    put("head", rotation("y", 0.55 * turn) @ rotation("x", 0.6 * nod))
    # Mocap-like jitter: a few slow sinusoids per joint and axis, ~1 degree.
    for j in range(NUM_BODY_JOINTS):
        freq = rng.uniform(0.3, 2.0, size=(3, 3))
        ph = rng.uniform(0, 2 * np.pi, size=(3, 3))
        amp = math.radians(1.0) * rng.normal(size=(3, 3)) / 3.0
        wobble = (amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + ph[None])).sum(-1)
        mats[:, j] = rotation("x", wobble[:, 0]) @ rotation("y", wobble[:, 1]) @ rotation("z", wobble[:, 2]) \
            @ mats[:, j]
    # Root: the y-up body stood up in AMASS's z-up world (+90 degrees about x), facing `heading`.
    mats[:, 0] = rotation("z", np.full(frames, math.radians(heading_deg))) @ rotation(
        "x", np.full(frames, math.pi / 2)) @ mats[:, 0]
    poses = np.zeros((frames, SMPLH_COLUMNS))
    poses[:, : 3 * NUM_BODY_JOINTS] = matrix_to_axis_angle(mats).reshape(frames, -1)
    poses[:, 3 * NUM_BODY_JOINTS:] = rng.normal(scale=0.1, size=SMPLH_COLUMNS - 3 * NUM_BODY_JOINTS)  # relaxed hands
    trans = np.stack([0.31 + 0.015 * np.sin(2 * np.pi * 0.7 * t),
                      -0.42 + 0.01 * t + 0.04 * bend / max(math.radians(bend_deg), 1e-9),
                      0.93 + 0.004 * np.sin(2 * np.pi * 1.3 * t)], axis=1)
    return {"poses": poses, "trans": trans, "betas": rng.normal(scale=0.5, size=16),
            "dmpls": np.zeros((frames, 8)), "gender": np.array("female"),
            "mocap_framerate": np.array(fps)}


def build_motion(out: str, seed: int = 0, name: str = "motion_amass.npz", **kwargs) -> str:
    """Write OUT/<name> (see `amass_motion`); returns its path."""
    path = os.path.join(out, name)
    np.savez(path, **amass_motion(seed, **kwargs))
    return path


# ------------------------------------------------------------------ the measurements


def command_line(hair: str, pose: str, simulate: bool, method: str, stride: int, frames: int | None,
                 data_up: str = "y", checkpoint: str | None = None) -> str:
    words = ["hairwarp", "simulate" if simulate else "drape", "--hairstyle", hair, "--pose", pose,
             "--method", method, "--strand-stride", str(stride)]
    if hair.endswith(".data") and data_up != "y":
        words += ["--data-up", data_up]
    if simulate and frames:
        words += ["--frames", str(frames)]
    if checkpoint and method != "rigid":
        words += ["--checkpoint", checkpoint]
    return " ".join(words)


def summarize(metrics: dict) -> dict:
    pen = np.asarray(metrics["penetration_percent"], dtype=np.float64)
    length = np.asarray(metrics["length_change_percent"], dtype=np.float64)
    return {"penetration_mean": float(pen.mean()), "penetration_worst": float(pen.max()),
            "worst_frame": int(pen.argmax()), "length_change_mean": float(length.mean()),
            "length_change_worst": float(length.max()),
            **({"energy_mean": float(np.mean(metrics["energy"]))} if "energy" in metrics else {})}


def run_scene(name: str, hair: str, pose: str, simulate: bool, methods, *, stride: int, frames: int | None,
              seed: int, out: str, picture=(), data_up: str = "y", checkpoint: str | None = None) -> dict:
    import torch

    from hairwarp.builder import build_scene
    from hairwarp.commands.common import picture_distances, run_and_score
    from hairwarp.config import EnergyConfig
    from hairwarp.methods import MethodOptions, make

    t0 = time.perf_counter()
    window = dict(start=0.0, num_frames=frames) if simulate else dict(frame=0)
    scene = build_scene(hair, "default", pose, strand_stride=stride, num_vertices=100, seed=seed,
                        data_up=data_up, **window)
    build_s = time.perf_counter() - t0
    cpu = torch.device("cpu")
    scene_frames = scene.frames(device=cpu)
    config = EnergyConfig()
    # The options `hairwarp simulate` / `hairwarp drape` pass (their defaults).
    options = MethodOptions(energy_config=config, max_iterations=100 if simulate else 500, patience=50,
                            reference_max_iterations=100 if simulate else 500, refine=0, progress=False,
                            checkpoint=checkpoint)
    record = {"scene": name, "hairstyle": hair, "pose": pose, "kind": "simulate" if simulate else "drape",
              "strands": scene.hairstyle.num_strands, "vertices": int(scene.hairstyle.strands.shape[1]),
              "frames": scene.num_frames, "fps": scene.motion.fps, "build_s": build_s,
              "fit": scene.hairstyle.info.get("fit") if getattr(scene.hairstyle, "info", None) else None,
              "methods": {}}
    print(f"[{name}] {record['strands']} strands x {record['vertices']} vertices, {record['frames']} frame(s) "
          f"at {scene.motion.fps:g} fps (built in {build_s:.1f} s)", flush=True)
    rigid = None
    for m in methods:
        torch.manual_seed(seed)
        t1 = time.perf_counter()
        try:
            result, metrics, sd, _ = run_and_score(make(m, options), scene_frames, config, simulate=simulate)
        except Exception as exc:  # report and go on with the other methods
            record["methods"][m] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"[{name}] {m}: FAILED {type(exc).__name__}: {exc}", flush=True)
            continue
        wall = time.perf_counter() - t1
        row = summarize(metrics["method"])
        if rigid is None:
            rigid = summarize(metrics["rigid"])
            record["rigid_placement"] = rigid
        row["removed_percent"] = (100.0 * (1.0 - row["penetration_mean"] / rigid["penetration_mean"])
                                  if rigid["penetration_mean"] > 0 else None)
        row["ms_per_frame"] = result.time_ms
        row["wall_s"] = wall
        row["info"] = {k: v for k, v in result.info.items() if isinstance(v, (int, float, str, list, type(None)))}
        row["per_frame"] = metrics["method"]
        row["command"] = command_line(hair, pose, simulate, m, stride, frames, data_up, checkpoint)
        record["methods"][m] = row
        ms = "-" if result.time_ms is None else f"{result.time_ms:.1f}"
        print(f"[{name}] {m:8s} penetration {row['penetration_mean']:6.2f} % (worst {row['penetration_worst']:6.2f}), "
              f"length {row['length_change_mean']:6.2f} % (worst {row['length_change_worst']:6.2f}), "
              f"{ms} ms/frame, {wall:.1f} s", flush=True)
        if picture and (m in picture or "all" in picture):
            from hairwarp.render.preview import render_drape, render_sequence

            body_v = scene_frames.posed.vertices.detach().cpu()
            faces = scene.body.faces.cpu()
            path = os.path.join(out, f"{name.replace(' ', '_')}_{m}.png")
            title = f"{name}, {m}: red = inside the body"
            if simulate:
                render_sequence(path, result.positions.cpu(), body_v, faces, signed_distance=picture_distances(sd).cpu(),
                                frames=6, fps=scene.motion.fps, title=title)
            else:
                render_drape(path, result.positions[0].cpu(), body_v[0], faces,
                             signed_distance=picture_distances(sd[0]).cpu(), title=title)
            record.setdefault("pictures", []).append(path)
    return record


def markdown(records: list[dict]) -> str:
    lines = ["| scene | strands x vertices, frames | method | penetration % mean / worst frame | "
             "rigid's penetration removed | length change % mean / worst frame | ms/frame |",
             "|---|---|---|---:|---:|---:|---:|"]
    for r in records:
        size = f"{r['strands']} x {r['vertices']}, {r['frames']}"
        for m, row in r["methods"].items():
            if "error" in row:
                lines.append(f"| {r['scene']} | {size} | {m} | failed: {row['error'][:80]} | | | |")
                continue
            removed = "-" if m == "rigid" or row["removed_percent"] is None else f"{row['removed_percent']:.0f} %"
            ms = "-" if row["ms_per_frame"] is None else f"{row['ms_per_frame']:.1f}"
            lines.append(f"| {r['scene']} | {size} | {m} | {row['penetration_mean']:.2f} / "
                         f"{row['penetration_worst']:.2f} | {removed} | {row['length_change_mean']:.2f} / "
                         f"{row['length_change_worst']:.2f} | {ms} |")
    return "\n".join(lines)


def file_md5(path: str) -> str:
    import hashlib

    with open(path, "rb") as f:
        return hashlib.md5(f.read()).hexdigest()


def checkpoint_digests() -> dict:
    """md5 of the shipped checkpoints (a run is only comparable with one on the same files)."""
    from hairwarp.methods.networks import SHIPPED, shipped_checkpoint

    out = {}
    for name in sorted({f for files in SHIPPED.values() for f in files}):
        path = shipped_checkpoint(name)
        if path:
            out[name] = file_md5(path)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output folder (the foreign files, pictures, JSON, markdown)")
    p.add_argument("--seed", type=int, default=0, help="seed of the files' randomness and the presets (default: 0)")
    p.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, of {', '.join(SCENES)} (default: all)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated (default: {','.join(METHODS)})")
    p.add_argument("--strand-stride", type=int, default=4,
                   help="keep every K-th strand of the groom / scalp (default: 4, about 256 strands)")
    p.add_argument("--frames", type=int, default=None, help="simulate at most this many frames (default: all)")
    p.add_argument("--hairstyle", default="medium_wavy", help="preset the .data groom starts from (default: medium_wavy)")
    p.add_argument("--grow", choices=("head", "body"), default="head",
                   help="the .data groom's source preset grown around the head alone, as grooms made on a "
                        "bare head (USC-HairSalon's) are, or around this body (default: head)")
    p.add_argument("--units", choices=("m", "cm", "mm"), default="cm", help=".data units (default: cm)")
    p.add_argument("--up", choices=("y", "z"), default="y", help=".data up axis (default: y)")
    p.add_argument("--headings", default="30",
                   help="comma-separated headings of the AMASS body about the world's vertical [deg]: one motion "
                        "file and one run of the motion scenes each (default: 30)")
    p.add_argument("--sweep-methods", default="rigid,static,dynamic,auto",
                   help="methods of the motion scenes at the headings after the first (default: all four)")
    p.add_argument("--duration", type=float, default=1.2, help="length of the AMASS motion [s] (default: 1.2)")
    p.add_argument("--picture", default="dynamic",
                   help="comma-separated methods drawn for each scene, 'all', or '' for none (default: dynamic)")
    p.add_argument("--checkpoint", default=None,
                   help="network methods: this checkpoint file instead of the shipped one (default: shipped)")
    p.add_argument("--files-only", action="store_true", help="write the foreign files and stop")
    args = p.parse_args(argv)

    import torch

    torch.set_num_threads(1)  # as the commands do by default (--threads 1)
    os.makedirs(args.out, exist_ok=True)
    t0 = time.perf_counter()
    digests = checkpoint_digests()
    groom = build_groom(args.out, args.seed, hairstyle=args.hairstyle, units=args.units, up=args.up,
                        grow=args.grow)
    try:
        headings = [float(h) for h in args.headings.split(",") if h.strip()]
    except ValueError:
        p.error(f"--headings: expected comma-separated numbers, got {args.headings!r}")
    if not headings:
        p.error("--headings: give at least one heading")
    motions = {h: build_motion(args.out, args.seed, duration=args.duration, heading_deg=h,
                               name="motion_amass.npz" if i == 0 else f"motion_amass_h{h:g}.npz")
               for i, h in enumerate(headings)}
    print(f"wrote {groom} and {', '.join(motions.values())} ({time.perf_counter() - t0:.1f} s)", flush=True)
    if args.files_only:
        return 0
    scenes = [s for s in args.scenes.split(",") if s]
    methods = [m for m in args.methods.split(",") if m]
    sweep_methods = [m for m in args.sweep_methods.split(",") if m]
    for s in scenes:
        if s not in SCENES:
            p.error(f"--scenes: unknown scene {s!r}; expected some of {', '.join(SCENES)}")
    records = []
    for i, heading in enumerate(headings):
        for s in scenes:
            hair, pose, simulate = SCENES[s]
            if pose != "motion" and i > 0:
                continue  # a rest-pose scene does not depend on the motion's heading
            name = f"{s} h{heading:g}" if pose == "motion" else s
            record = run_scene(name, groom if hair == "groom" else hair, motions[heading] if pose == "motion" else pose,
                               simulate, methods if i == 0 else sweep_methods, stride=args.strand_stride,
                               frames=args.frames, seed=args.seed, out=args.out,
                               picture=[m for m in args.picture.split(",") if m] if i == 0 else (),
                               data_up=args.up, checkpoint=args.checkpoint)
            record["heading_deg"] = heading if pose == "motion" else None
            records.append(record)
    table = markdown(records)
    print(table)
    if checkpoint_digests() != digests:
        print("WARNING: a shipped checkpoint changed on disk during the run; the rows may mix two networks")
    report = {"command": " ".join(["python", "tools/foreign_scenes.py"] + (argv or sys.argv[1:])),
              "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, torch threads 1",
              "files": {"groom": os.path.basename(groom),
                        "motions": {f"{h:g}": os.path.basename(m) for h, m in motions.items()}},
              "checkpoints_md5": digests, "checkpoints_md5_after": checkpoint_digests(),
              "checkpoint": args.checkpoint, "checkpoint_md5": file_md5(args.checkpoint) if args.checkpoint else None,
              "seconds": time.perf_counter() - t0, "scenes": records}
    from hairwarp.runtime import jsonable

    with open(os.path.join(args.out, "foreign_scenes.json"), "w") as f:
        json.dump(jsonable(report), f, indent=1)
    with open(os.path.join(args.out, "foreign_scenes.md"), "w") as f:
        f.write(table + "\n")
    print(f"wrote foreign_scenes.json, foreign_scenes.md into {args.out} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
