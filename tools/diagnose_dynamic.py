"""Why does the dynamic network leave more hair inside the body than the static one on a motion?

On a motion comparison scene (torso_bend by default; whiplash as the control), with a dynamic
checkpoint (the shipped one by default), per frame: penetration % and length change % of

- "rigid", "static" (the frozen static network inside the checkpoint, one drape per frame),
  "dynamic" (the frames in order, GRU state carried: the harness's "dynamic");
- "motion x S": the dynamic network with its motion descriptors scaled by S (0: no motion);
- "reset R": the GRU restarted from zero at every frame and run over the last R frames only
  (R = 1: no history at all; R = 7: as long as a training sequence, 3 warm-up + 4 rollout);
- the pieces of D_dyn = F_pred_dyn(I_sd(H_static, C_dyn)): "dyn head on H_static" (the path
  Eq. 4 regularises, no I_sd) and "static head on I_sd(H_static, C_dyn)";

where the penetrating vertices are (vertex index along the strand, the body part: the joint of
largest skin weight of the nearest body vertex, the root's side of the head, depth), the static
energy (Eq. 5) and the inertia term (Eq. 16) of each drape sequence, and, with --draws, what
the shipped dynamic run's batches held (motion shares, forward lean of the torso_bend frames,
long hair), with --hair-variants the first scene's motion with other hair (the decode of its
hair latent, blends towards the scene's hair, the preset not grown around the body), and with
--training-samples the networks on training-like sequences of the scene's motion. Writes
OUT/diagnose_dynamic_<scene>.json and, for the first scene, OUT/diagnose_dynamic.png.

    python tools/diagnose_dynamic.py --scenes torso_bend,whiplash --draws 373 --hair-variants \
        --training-samples 3 --out OUT
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import os
import sys

import numpy as np
import torch

# The shipped dynamic run: 3 warm-up + 4 rollout frames, frame interval 2..5, batch 32.
_WARMUP, _ROLLOUT, _SUBSAMPLE, _BATCH = 3, 4, (2, 5), 32
# Joints whose x rotations add up to the forward lean of the procedural torso bend.
_LEAN_JOINTS = ("pelvis", "spine1", "spine2", "spine3")


def lean_deg(poses: torch.Tensor) -> np.ndarray:
    """Forward lean of the upper body [deg] of torso_bend-style poses (T, 66)."""
    from hairwarp.scene.skeleton import JOINT

    p = poses.reshape(-1, 22, 3).double()
    return torch.rad2deg(sum(p[:, JOINT[j], 0] for j in _LEAN_JOINTS)).numpy()


def dynamic_variant(sim, frames, *, motion_scale: float = 1.0, reset: int | None = None,
                    path: str = "full") -> torch.Tensor:
    """Drapes (T, M, N, 3) of the dynamic network under one variant (see the module docstring)."""
    from hairwarp.models.deformation import apply_deformation
    from hairwarp.models.layers import reshape_map
    from hairwarp.scene.motion import motion_descriptor_windows

    scene = frames.scene
    dyn = sim.dynamic
    cfg = dyn.config.static
    rigid = frames.rigid.positions
    t = rigid.shape[0]
    poses = scene.motion.poses[frames.frame_indices.cpu()].to(rigid.device)
    betas = frames.betas[:1]
    z = sim.latent(scene.hairstyle, rigid.device, rigid.dtype)
    root_uv = scene.hairstyle.root_uv.to(rigid.device)
    motion = motion_descriptor_windows(poses.double().cpu(), betas[0].double().cpu(), 1.0 / scene.motion.fps,
                                       dyn.config.window, include_betas=False).to(rigid)[None] * motion_scale
    contact = dyn.contact_features(rigid, root_uv, frames.body_mesh)
    with torch.no_grad():
        if path != "full":
            h = dyn.static._features(z.expand(t, -1), betas.expand(t, -1), poses, contact)
            if path == "dyn_head_on_static":
                flat = dyn.head(h)
            else:  # "static_head_on_fused"
                codes, hidden = [], torch.zeros(1, cfg.model_dim, dtype=rigid.dtype, device=rigid.device)
                for i in range(t):
                    hidden = dyn._encode_motion(motion[:, i], betas, hidden)
                    codes.append(hidden)
                flat = dyn.static.head(dyn._fuse(h, torch.cat(codes)))
            maps = reshape_map(flat, cfg.grid_height, cfg.grid_width, cfg.num_vertices)
        elif reset is None:
            maps = dyn.simulate(z, betas, poses[None], motion, contact=contact[None]).deformation_map[0]
        else:
            maps = torch.stack([
                dyn.simulate(z, betas, poses[None, max(0, i - reset + 1):i + 1], motion[:, max(0, i - reset + 1):i + 1],
                             contact=contact[None, max(0, i - reset + 1):i + 1]).deformation_map[0, -1]
                for i in range(t)])
    return apply_deformation(rigid, maps, root_uv, cfg.length_projection)


def where_inside(x, frames, part_of_vertex, joint_names, root_side) -> dict:
    """Where the vertices inside the body are: index decile, body part, root side, depth."""
    from hairwarp.ops import hair_body_signed_distance

    sd = hair_body_signed_distance(x, frames.body_mesh)
    inside = sd < 0
    inside[:, :, :2] = False  # the fixed vertices are not the method's doing
    f, m, n = torch.nonzero(inside, as_tuple=True)
    parts = []
    for i in range(x.shape[0]):
        sel = f == i
        if bool(sel.any()):
            nearest = torch.cdist(x[i, m[sel], n[sel]], frames.posed.vertices[i]).argmin(1)
            parts.append(part_of_vertex[nearest])
    parts = torch.cat(parts) if parts else torch.zeros(0, dtype=torch.long)
    depth = -sd[inside] * 1e3
    n_vertices = x.shape[2]
    return {
        "count": int(inside.sum()),
        "strands": int(torch.unique(m).numel()),
        "vertex_index_decile": torch.bincount(n * 10 // n_vertices, minlength=10).tolist(),
        "body_part": {joint_names[j]: int((parts == j).sum()) for j in torch.unique(parts).tolist()},
        "root_side": {s: int(sum(root_side[i] == s for i in m.tolist())) for s in ("back", "middle", "front")},
        "depth_mm_median": float(depth.median()) if depth.numel() else None,
        "depth_mm_p90": float(depth.quantile(0.9)) if depth.numel() else None,
    }


def energies(x, frames, scene) -> dict:
    """Static energy (Eq. 5, b_p 0.01) per frame and the inertia term (Eq. 16, h = 1/fps) of a sequence."""
    from hairwarp.config import EnergyConfig
    from hairwarp.energy import total_energy

    cfg = EnergyConfig(time_step=1.0 / scene.fps)
    with torch.no_grad():
        e = total_energy(x, frames.inputs, cfg)
        later = scene.frames(list(range(2, x.shape[0])), device=x.device)
        inputs = dataclasses.replace(later.inputs, prev=x[1:-1], prev2=x[:-2])
        inertia = total_energy(x[2:], inputs, cfg, dynamic=True, terms=("inertia",)).total
    return {"static_energy_per_frame": e.total.tolist(),
            "terms_mean": {k: float(v.mean()) for k, v in e.terms.items()},
            "inertia_mean": float(inertia.mean())}


def training_draws(steps: int, seed: int = 0) -> dict:
    """The clips and hairstyles the shipped dynamic run drew (no hair placed): `sequence_batch`'s
    draws replayed for `steps` steps of batch 32."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import train_shipped
    from hairwarp.training import data as D

    sampler = D.TrainingSampler(train_shipped.data_config(), seed=seed)
    frames = _WARMUP + _ROLLOUT
    threshold = sampler.dynamic_threshold(frames, _SUBSAMPLE, 500, 0.5)
    long_pool = set(sampler.long_hairstyles(train_shipped.PHASE3_HAIRSTYLES))
    motions = collections.Counter()
    lean, long_hair = [], []
    for step in range(steps):
        g = sampler.generator(D._STREAM_SEQUENCE, step)
        clips = []
        for _ in range(_BATCH):
            best, best_score = None, -math.inf
            for _ in range(D._SEQUENCE_TRIES):
                clip = sampler._draw_clip(g, frames, _SUBSAMPLE)
                if clip is None:
                    continue
                score = sampler.clip_score(clip, frames)
                if score > best_score:
                    best, best_score = clip, score
                if score >= threshold:
                    break
            clips.append(best)
        ids = [int(i) for i in g.integers(0, train_shipped.PHASE3_HAIRSTYLES, size=_BATCH)]
        for clip, hairstyle in zip(clips, ids):
            name = sampler.entries[clip[0]].name.split("#")[0]
            motions[name] += 1
            if name == "torso_bend":
                idx = torch.as_tensor(sampler._clip_frames(clip, frames)[_WARMUP:])
                a = lean_deg(sampler.entries[clip[0]].motion.poses[idx])
                lean.extend(a.tolist())
                long_hair.extend([hairstyle in long_pool] * len(a))
    # Share of torso_bend clips that pass the dynamic-score filter, against all motions.
    g = np.random.default_rng(1)
    passed = collections.defaultdict(list)
    for _ in range(2000):
        clip = sampler._draw_clip(g, frames, _SUBSAMPLE)
        if clip is not None:
            passed[sampler.entries[clip[0]].name.split("#")[0]].append(sampler.clip_score(clip, frames) >= threshold)
    return {"steps": steps, "batch": _BATCH, "sequences": sum(motions.values()), "motions": dict(motions),
            "threshold": threshold, "pass_rate": {k: float(np.mean(v)) for k, v in passed.items()},
            "long_hairstyles": len(long_pool), "pool": train_shipped.PHASE3_HAIRSTYLES,
            "torso_bend_rollout_lean_deg": lean, "torso_bend_rollout_long_hair": long_hair}


def hair_variants(sim, name: str, strand_stride: int, device) -> dict:
    """The scene's motion with other hair: the preset grown without the body, the decode of the
    scene's hair latent, and the blends decode + a (grown - decode): rigid / static / dynamic
    penetration % each (the networks read the hair through z = encode(strands) only)."""
    import hairwarp.evaluation.scenes as scenes
    from hairwarp.metrics import penetration_percent
    from hairwarp.scene.hairstyles import generate_hairstyle, hairstyle_preset
    from hairwarp.scene.scene import Scene

    spec = scenes.SCENE_SPECS[name]
    base, grown = scenes._grown_hairstyle(spec.hairstyle)
    motion = scenes.comparison_scene(name, strand_stride=strand_stride).scene.motion
    free = generate_hairstyle(base.scalp, hairstyle_preset(spec.hairstyle, seed=scenes.SCENE_SEED),
                              num_vertices=grown.strands.shape[1])
    basis = sim.basis
    z = basis.encode(grown.strands.double(), grown.root_uv.double())
    decoded, _ = basis.decode(z, scalp=base.scalp)
    grid = basis.nearest_strands(grown.root_uv)  # grid root -> strand
    order = torch.empty_like(grid)
    order[grid] = torch.arange(grid.numel())
    decoded = decoded[order].float()
    keep = torch.arange(0, grown.num_strands, strand_stride)
    err = (decoded - grown.strands).norm(dim=-1)
    out = {"decode_error_mm": {"mean": float(err.mean() * 1e3), "tip_mean": float(err[:, -1].mean() * 1e3),
                               "tip_p90": float(err[:, -1].quantile(0.9) * 1e3)}, "rows": {}}
    styles = {}
    if free.num_strands == grown.num_strands:
        styles["preset grown without the body"] = free.strands
    for a in (0.0, 0.25, 0.5, 0.75, 1.0):
        styles[f"decode + {a:g} (grown - decode)"] = decoded + a * (grown.strands - decoded)
    for label, strands in styles.items():
        hair = dataclasses.replace(grown, strands=strands.contiguous()).subset(keep)
        frames = Scene(body=base.body, scalp=base.scalp, hairstyle=hair, motion=motion, name=name).frames(device=device)
        with torch.no_grad():
            drapes = {"rigid": frames.rigid.positions, "static": sim.drape(frames), "dynamic": sim.simulate(frames)}
        out["rows"][label] = {k: float(penetration_percent(x, frames.body_mesh).mean()) for k, x in drapes.items()}
        print(f"{name:11s} hair: {label:34s} " + "  ".join(f"{k} {v:.2f} %" for k, v in out["rows"][label].items()),
              flush=True)
    return out


def training_samples(checkpoint: str | None, steps: int, motion: str = "torso_bend", batch: int = 8) -> dict:
    """Rigid / static / dynamic penetration % on training-like sequences: the checkpoint's own
    dynamic-training data (its stored config) restricted to `motion` played as recorded (k = 1,
    nominal motion), long corpus hairstyles only (P_init = decode(z), as training sees them),
    64 strands, the rollout frames of `steps` batches of `batch` sequences."""
    from hairwarp.methods.networks import DYNAMIC_CHECKPOINT, shipped_checkpoint
    from hairwarp.metrics import penetration_percent
    from hairwarp.models.checkpoint import load_checkpoint
    from hairwarp.training import DynamicTrainer, DynamicTrainingConfig
    from hairwarp.training.config import energy_config
    from hairwarp.training.dynamic import dynamic_loss

    path = checkpoint or shipped_checkpoint(DYNAMIC_CHECKPOINT)
    base = DynamicTrainingConfig.from_dict(load_checkpoint(path, "cpu").extra["training_config"])
    cfg = base.replace(batch_size=batch, hairstyles=128, long_hair_fraction=1.0, subsample_min=1, subsample_max=1,
                       dynamic_filter=False, data=base.data.replace(strand_stride=4, motions=[motion], motion_variants=1))
    trainer = DynamicTrainer(cfg, init=path)
    model = trainer.model.eval()
    energy = energy_config(cfg.energy, barrier_join_fraction=cfg.barrier_join_fraction, time_step=1.0 / cfg.data.fps)
    pen = collections.defaultdict(list)
    for step in range(steps):
        seq = trainer.next_batch(step)
        b, r, w = seq.batch_size, seq.rollout_frames, seq.warmup_frames
        with torch.no_grad():
            _, _, positions = dynamic_loss(model, seq, energy, None, cfg.inertia_time_step)
            rigid = seq.rollout.rigid
            contact = model.static.contact_features(rigid, seq.rollout.root_uv, seq.rollout.inputs.body)
            static = model.static.drape(seq.z.repeat_interleave(r, 0), seq.betas.repeat_interleave(r, 0),
                                        seq.poses[:, w:].reshape(b * r, -1), rigid, seq.rollout.root_uv, None, contact)
        for name, x in (("rigid", rigid), ("static", static), ("dynamic", positions.reshape(rigid.shape))):
            pen[name].extend(penetration_percent(x, seq.rollout.inputs.body).tolist())
    out = {k: {"mean": float(np.mean(v)), "max": float(np.max(v)), "frames": len(v)} for k, v in pen.items()}
    print(f"training-like {motion} sequences (long decoded hair, k = 1): "
          + "  ".join(f"{k} {v['mean']:.2f} % (max {v['max']:.2f})" for k, v in out.items()), flush=True)
    return out


def figure(path, scene, record, draws):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 3, figsize=(19, 8.5))
    a = ax[0, 0]
    styles = {"rigid": ("k", "-"), "static": ("tab:blue", "-"), "dynamic": ("tab:red", "-"),
              "reset 1": ("tab:orange", "--"), "motion x0": ("tab:purple", ":"),
              "dyn head on H_static": ("tab:green", "-."), "static head on I_sd": ("tab:brown", "--")}
    for name, (c, ls) in styles.items():
        if name in record["variants"]:
            a.plot(record["variants"][name]["penetration_per_frame"], color=c, ls=ls,
                   label=f"{name} ({record['variants'][name]['penetration_mean']:.2f} %)")
    a.set_xlabel(f"frame ({scene} window, 60 fps)")
    a.set_ylabel("penetration %")
    a.set_title(f"a) {scene}: penetration per frame")
    twin = a.twinx()
    twin.plot(record["lean_deg"], color="0.6", lw=3, alpha=0.4)
    twin.set_ylabel("forward lean [deg] (grey)")
    a.legend(fontsize=7, loc="upper left")
    b = ax[0, 1]
    width = 0.27
    for k, (name, c) in enumerate((("rigid", "k"), ("static", "tab:blue"), ("dynamic", "tab:red"))):
        dec = record["where"][name]["vertex_index_decile"]
        b.bar(np.arange(10) + (k - 1) * width, dec, width, color=c, label=name)
    b.set_xticks(range(10), [f"{10 * i}-{10 * i + 9}" for i in range(10)], fontsize=7)
    b.set_xlabel("vertex index along the strand (root 0, tip 99)")
    b.set_ylabel("vertices inside, summed over frames")
    b.set_title("b) where along the strands")
    b.legend(fontsize=8)
    c = ax[1, 0]
    parts = sorted({p for n in ("rigid", "static", "dynamic") for p in record["where"][n]["body_part"]})
    for k, (name, col) in enumerate((("rigid", "k"), ("static", "tab:blue"), ("dynamic", "tab:red"))):
        c.bar(np.arange(len(parts)) + (k - 1) * width, [record["where"][name]["body_part"].get(p, 0) for p in parts],
              width, color=col, label=name)
    c.set_xticks(range(len(parts)), parts, rotation=30, fontsize=7)
    c.set_ylabel("vertices inside, summed over frames")
    c.set_title("c) body part (joint of the nearest body vertex)")
    c.legend(fontsize=8)
    d = ax[1, 1]
    if draws:
        lean = np.asarray(draws["torso_bend_rollout_lean_deg"])
        long_hair = np.asarray(draws["torso_bend_rollout_long_hair"], dtype=bool)
        bins = np.linspace(-5, 100, 22)
        total = draws["sequences"] * _ROLLOUT
        d.hist(lean, bins, color="0.7", label=f"torso_bend rollout frames ({len(lean)} of {total})")
        d.hist(lean[long_hair], bins, color="tab:red",
               label=f"... with hair >= 0.4 m ({int(long_hair.sum())}, {100 * long_hair.sum() / total:.2f} %)")
        lo, hi = min(record["lean_deg"]), max(record["lean_deg"])
        d.axvspan(lo, hi, color="tab:blue", alpha=0.12, label=f"{scene} scene: lean {lo:.0f}-{hi:.0f} deg")
        d.set_xlabel("forward lean of the upper body [deg]")
        d.set_ylabel("rollout frames")
        d.set_title(f"d) the shipped dynamic run's draws ({draws['steps']} steps x {draws['batch']})")
        d.legend(fontsize=7)
    else:
        d.axis("off")
    e = ax[0, 2]
    hair = record.get("hair_variants")
    if hair:
        blends = [(float(k.split(" + ")[1].split(" ")[0]), v) for k, v in hair["rows"].items() if k.startswith("decode")]
        a = [x for x, _ in blends]
        for name, col in (("rigid", "k"), ("static", "tab:blue"), ("dynamic", "tab:red")):
            e.plot(a, [v[name] for _, v in blends], "o-", color=col, label=name)
        e.set_yscale("log")
        e.set_xlabel("hair = decode(z) + a (scene's grown hair - decode(z))")
        e.set_ylabel("penetration %, mean over frames")
        free = hair["rows"].get("preset grown without the body")
        note = "" if free is None else (f"\npreset not grown around the body: rigid {free['rigid']:.1f}, "
                                        f"static {free['static']:.2f}, dynamic {free['dynamic']:.2f} %")
        e.set_title(f"e) {scene}: the same motion, other hair (a = 1: the scene){note}", fontsize=9)
        e.legend(fontsize=8)
    else:
        e.axis("off")
    f = ax[1, 2]
    where = record["where"]["dynamic"]
    dec = where["vertex_index_decile"]
    f.axis("off")
    lines = [f"{v}: {r['penetration_mean']:.2f} % (length {r['length_change_mean']:.3f} %)"
             for v, r in record["variants"].items()]
    f.text(0.0, 1.0, f"f) {scene}, penetration % (mean over frames)\n" + "\n".join(lines)
           + f"\n\ndynamic: inside vertices {where['count']}, tips (index >= 70) "
           f"{100 * sum(dec[7:]) / max(1, sum(dec)):.0f} %, depth median {where['depth_mm_median']:.1f} mm",
           va="top", family="monospace", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    from hairwarp.evaluation.scenes import comparison_scene
    from hairwarp.methods.networks import load_simulator
    from hairwarp.metrics import length_change_percent, penetration_percent
    from hairwarp.runtime import machine_name, resolve_device
    from hairwarp.scene.body import default_body

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scenes", default="torso_bend,whiplash")
    p.add_argument("--strand-stride", type=int, default=4, help="4: the harness's reduced size (256 strands)")
    p.add_argument("--checkpoint", default=None, help="a dynamic checkpoint (default: the shipped one)")
    p.add_argument("--draws", type=int, default=0, help="replay this many steps of the shipped run's draws (373)")
    p.add_argument("--hair-variants", action="store_true",
                   help="first scene: also its motion with other hair (decode of its latent, blends, not grown)")
    p.add_argument("--training-samples", type=int, default=0,
                   help="also score this many batches of 8 training-like sequences of each scene's motion "
                        "(long decoded corpus hair, k = 1)")
    p.add_argument("--out", default="hairwarp-out")
    args = p.parse_args(argv)
    device = resolve_device(args.device, argument="--device")
    os.makedirs(args.out, exist_ok=True)
    sim = load_simulator("dynamic", args.checkpoint, device)
    body = default_body()
    part_of_vertex = body.model.weights.argmax(1).to(device)
    joint_names = list(body.joint_names)
    draws = training_draws(args.draws) if args.draws else None
    for k, name in enumerate(args.scenes.split(",")):
        scene = comparison_scene(name, strand_stride=args.strand_stride)
        frames = scene.frames(device=device)
        roots = scene.scene.hairstyle.strands[:, 0]
        z0 = float(roots[:, 2].mean())
        root_side = ["back" if z < z0 - 0.03 else "front" if z > z0 + 0.03 else "middle" for z in roots[:, 2].tolist()]
        with torch.no_grad():
            drapes = {"rigid": frames.rigid.positions, "static": sim.drape(frames), "dynamic": sim.simulate(frames)}
        for s in (0.0, 0.5, 2.0):
            drapes[f"motion x{s:g}"] = dynamic_variant(sim, frames, motion_scale=s)
        for r in (1, _WARMUP + _ROLLOUT):
            drapes[f"reset {r}"] = dynamic_variant(sim, frames, reset=r)
        drapes["dyn head on H_static"] = dynamic_variant(sim, frames, path="dyn_head_on_static")
        drapes["static head on I_sd"] = dynamic_variant(sim, frames, path="static_head_on_fused")
        record = {"scene": scene.describe(), "machine": machine_name(device), "command": " ".join(sys.argv),
                  "checkpoint": args.checkpoint or "shipped", "variants": {},
                  "lean_deg": lean_deg(scene.scene.motion.poses).tolist(), "where": {}, "energy": {}}
        static = drapes["static"]
        for v, x in drapes.items():
            pen = penetration_percent(x, frames.body_mesh)
            lc = length_change_percent(x, frames.inputs.rest_lengths)
            third = max(1, x.shape[0] // 3)
            record["variants"][v] = {
                "penetration_mean": float(pen.mean()), "penetration_max": float(pen.max()),
                "penetration_first_third": float(pen[:third].mean()), "penetration_last_third": float(pen[-third:].mean()),
                "length_change_mean": float(lc.mean()), "penetration_per_frame": pen.tolist(),
                "distance_to_static_mm": float((x - static).norm(dim=-1).mean() * 1e3),
            }
            print(f"{name:11s} {v:22s} pen {pen.mean():5.2f} % (max {pen.max():5.2f}, first third "
                  f"{pen[:third].mean():5.2f}, last third {pen[-third:].mean():5.2f})  length {lc.mean():.3f} %  "
                  f"|x - static| {record['variants'][v]['distance_to_static_mm']:.1f} mm", flush=True)
        for v in ("rigid", "static", "dynamic"):
            record["where"][v] = where_inside(drapes[v], frames, part_of_vertex, joint_names, root_side)
            record["energy"][v] = energies(drapes[v], frames, scene)
            e = record["energy"][v]
            print(f"{name:11s} {v:8s} where {json.dumps(record['where'][v])}\n"
                  f"{'':11s} {'':8s} static energy mean {np.mean(e['static_energy_per_frame']):.3f} "
                  f"(contact {e['terms_mean']['hair_body_contact']:.3f}), inertia {e['inertia_mean']:.2e}", flush=True)
        if k == 0 and args.hair_variants:
            record["hair_variants"] = hair_variants(sim, name, args.strand_stride, device)
        if args.training_samples:
            record["training_samples"] = training_samples(args.checkpoint, args.training_samples, name)
        if draws:
            record["training_draws"] = draws
        with open(os.path.join(args.out, f"diagnose_dynamic_{name}.json"), "w") as f:
            json.dump(record, f, indent=1)
        if k == 0:
            figure(os.path.join(args.out, "diagnose_dynamic.png"), name, record, draws)
    if draws:
        lean = np.asarray(draws["torso_bend_rollout_lean_deg"])
        long_hair = np.asarray(draws["torso_bend_rollout_long_hair"], dtype=bool)
        print(json.dumps({k: draws[k] for k in ("sequences", "motions", "threshold", "pass_rate", "long_hairstyles")}))
        print(f"torso_bend rollout frames {lean.size}; lean >= 40 deg: {(lean >= 40).sum()}, of which long hair "
              f"{(long_hair & (lean >= 40)).sum()} (of {draws['sequences'] * _ROLLOUT} rollout frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
