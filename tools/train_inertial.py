"""Train the inertial step on physics clips, then judge it on held-out motions at full size.

    python tools/train_inertial.py train --device cuda --out OUT                 # clips + training
    python tools/train_inertial.py train --device cuda --out OUT --resume OUT    # more steps, same run
    python tools/train_inertial.py evaluate --device cuda --checkpoint OUT/hairformer_inertial.pt --out OUT

`train`: the training clips are grown preset hairstyles under random head moves
(`hairwarp.scene.motion.random_head_moves`, 1.5 s each), simulated by the physics at 256 strands;
the learning curve follows the comparison scenes whiplash and torso_bend at the same size (never
trained on). Writes OUT/run/ (clips/, checkpoint.pt, log.jsonl), OUT/hairformer_inertial.pt (the
step to ship) and OUT/curve_inertial.png.

`evaluate`: held-out motions at full size (1 024 strands x 100 vertices unless --strand-stride):
the comparison scenes whiplash and torso_bend, and scenes unlike the training clips (procedural
nod, sway walk and arm raise on other hairstyles, and an AMASS-format file written by
tools/foreign_scenes.py). Per scene: the physics once, then rigid, static, dynamic (the paper's
network) and inertial against it: distance to the physics, tip swing, its amplitude ratio and
correlation, penetration, length change, ms/frame (`--oracle`: also each frame's static optimum,
alone and as the step's equilibrium; `--physics-repeat`: the physics again, against itself; `--scenes
LABEL=HAIRSTYLE:POSE:START:DURATION`: a scene of one's own). Writes OUT/evaluate_inertial.json and
.md and one swing plot per scene.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

STYLES = ("long_straight", "medium_wavy", "long_curly", "bob")
# The comparison scenes whiplash and torso_bend at the training size (`clip_scene`'s docstring).
HELD_OUT_CURVE = (("medium_wavy", "whiplash", None, 0.35, 1.0), ("long_straight", "torso_bend", None, 0.3, 1.3))
# Held-out motions of `evaluate`: (label, hairstyle, pose, start, duration); pose "scene" is the
# comparison scene of that name; "amass" the AMASS-format file of tools/foreign_scenes.py.
EVALUATION = (
    ("whiplash", "whiplash", "scene", None, None),
    ("torso_bend", "torso_bend", "scene", None, None),
    ("bob_nod", "bob", "nod", 0.0, 2.0),
    ("curly_sway_walk", "long_curly", "sway_walk", 0.0, 2.0),
    ("long_arm_raise", "long_straight", "arm_raise", 0.5, 1.5),
    ("wavy_amass", "medium_wavy", "amass", 0.0, None),
)
METHODS = ("rigid", "static", "dynamic", "inertial")


def train(args) -> int:
    from hairwarp.models.checkpoint import save_checkpoint
    from hairwarp.training.inertial import ClipSpec, InertialTrainer, InertialTrainingConfig, read_log
    from train_shipped import _number_or_text

    run = os.path.join(args.out, args.run_name)
    cache = os.path.join(args.out, "clips")
    if args.resume:
        trainer = InertialTrainer(out=run, device=args.device, resume=args.resume, clip_cache=cache)
        if args.steps:
            trainer.config.steps = args.steps
    else:
        clips = [ClipSpec(style, "head_moves", 100 * i + j, 0.0, 1.5)
                 for i, style in enumerate(args.styles.split(",")) for j in range(args.clips_per_style)]
        model = ({k: _number_or_text(v) for k, v in (item.split("=", 1) for item in args.model.split(","))}
                 if args.model else {})
        config = InertialTrainingConfig(clips=clips, held_out=[ClipSpec(*c) for c in HELD_OUT_CURVE],
                                        strand_stride=args.strand_stride, steps=args.steps,
                                        equilibrium=args.equilibrium,
                                        learning_rate=args.lr, eval_every=args.eval_every, model=model,
                                        grad_clip=args.grad_clip, projection_max_gain=args.projection_max_gain)
        trainer = InertialTrainer(config, out=run, device=args.device, seed=args.seed, clip_cache=cache)
    start = time.perf_counter()
    trainer.train()
    seconds = time.perf_counter() - start
    save_checkpoint(os.path.join(args.out, f"{args.run_name}_inertial.pt"), trainer.model.cpu().float())
    log = read_log(run)
    last = next(r for r in reversed(log) if "held_out" in r)
    print(json.dumps({"steps": trainer.step_count, "train_seconds": seconds, "held_out": last["held_out"]}, indent=1))
    _plot_curve(log, os.path.join(args.out, f"{args.run_name}_curve.png"))
    return 0


def _plot_curve(log: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].semilogy([r["step"] for r in log], [r["loss"] for r in log])
    axes[0].set(title="training loss (swing + 0.3 position) [m^2]", xlabel="step")
    points = [r for r in log if "held_out" in r]
    for key in points[0]["held_out"]:
        steps = [r["step"] for r in points]
        label = key
        axes[1].plot(steps, [r["held_out"][key]["swing_correlation"] for r in points], "o-", label=label)
        axes[1].axhline(points[0]["held_out"][key]["equilibrium_swing_correlation"], ls=":", lw=1)
        axes[2].plot(steps, [r["held_out"][key]["mean_distance_mm"] for r in points], "o-", label=label)
    axes[1].set(title="held out: tip swing correlation with the physics", xlabel="step")
    axes[2].set(title="held out: mean distance to the physics [mm]", xlabel="step")
    axes[1].legend()
    fig.text(0.01, 0.01, "dotted: the static network alone; python tools/train_inertial.py train", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def evaluation_specs(scenes: str | None) -> list[tuple]:
    """The (label, hairstyle, pose, start, duration) of `--scenes`: EVALUATION's labels, or scenes
    of one's own as LABEL=HAIRSTYLE:POSE:START:DURATION (a preset hairstyle and procedural pose,
    start and duration in seconds). None: all of EVALUATION.

    Raises:
        ValueError: naming `--scenes`, for a label EVALUATION lacks or a malformed scene.
    """
    known = {spec[0]: spec for spec in EVALUATION}
    if not scenes:
        return list(EVALUATION)
    specs = []
    for item in scenes.split(","):
        if item in known:
            specs.append(known[item])
            continue
        label, _, body = item.partition("=")
        parts = body.split(":")
        try:
            if not label or len(parts) != 4:
                raise ValueError
            specs.append((label, parts[0], parts[1], float(parts[2]), float(parts[3])))
        except ValueError:
            raise ValueError(f"--scenes: expected labels of {sorted(known)} or LABEL=HAIRSTYLE:POSE:START:DURATION, "
                             f"got {item!r}") from None
    return specs


def _evaluation_scene(label, style, pose, start, duration, stride, out):
    import hairwarp as hw
    from hairwarp.evaluation.scenes import comparison_scene

    if pose == "scene":
        return comparison_scene(style, strand_stride=stride).scene
    if pose == "amass":
        from foreign_scenes import build_motion

        os.makedirs(os.path.join(out, "files"), exist_ok=True)
        pose = build_motion(os.path.join(out, "files"), seed=3)
    frames = None if duration is None else int(round(duration * 60)) + 1
    return hw.build_scene(style, pose=pose, strand_stride=stride, start=start, num_frames=frames)


class _Given:
    """An equilibrium already computed (`--oracle`): `simulate` returns it."""

    def __init__(self, result):
        self.result = result

    def simulate(self, frames):
        return self.result


def _fidelity_row(result, physics, rigid) -> dict:
    """A method's motion metrics against the physics (`motion_fidelity`) and its ms/frame."""
    from hairwarp.metrics import motion_fidelity

    fid = motion_fidelity(result.positions, physics, rigid)
    row = {k: fid[k] for k in ("mean_distance_mm", "max_distance_mm", "strand_distance_p99_mm", "swing_mm",
                               "physics_swing_mm", "swing_amplitude_ratio", "swing_correlation",
                               "swing_correlation_by_axis", "bulk_swing_correlation")}
    row["ms_per_frame"] = result.time_ms
    return row


def evaluate(args) -> int:
    from hairwarp.evaluation.charts import swing_plot
    from hairwarp.methods import MethodOptions, make
    from hairwarp.metrics import frame_metrics_of, mean_tip_offset

    device = torch.device(args.device)
    records = []
    for label, style, pose, start, duration in evaluation_specs(args.scenes):
        scene = _evaluation_scene(label, style, pose, start, duration, args.strand_stride, args.out)
        frames = scene.frames(device=device)
        t0 = time.perf_counter()
        physics = make("physics").simulate(frames)
        physics_s = time.perf_counter() - t0
        rigid = frames.rigid.positions
        positions, rows = {"physics": physics.positions}, {}
        if args.physics_repeat:
            # The same physics again: on a GPU its contact sums add in another order, and a motion
            # whose contacts amplify round-off (the bob's nod) ends elsewhere. What no method can
            # be asked to match better than the physics matches itself.
            repeat = make("physics").simulate(frames)
            positions["physics_repeat"] = repeat.positions
            rows["physics_repeat"] = _fidelity_row(repeat, physics.positions, rigid)
        variants = dict(item.split("=", 1) for item in args.variants.split(",")) if args.variants else {}
        if args.oracle:
            # What a perfect static network would give: each frame's static optimum (the physics'
            # drape from the rigid placement), alone and as the step's equilibrium.
            optimum = make("physics").drape(frames)
            positions["optimum"] = optimum.positions
            rows["optimum"] = _fidelity_row(optimum, physics.positions, rigid)
        methods = ("rigid", *(m for m in args.methods.split(",") if m and m != "rigid"))
        for name in (*methods, *variants, *(("inertial_optimum",) if args.oracle else ())):
            checkpoint = {"inertial": args.checkpoint, "inertial_optimum": args.checkpoint, "static": args.static_checkpoint,
                          **variants}.get(name)
            static_checkpoint = args.static_checkpoint
            if name in variants and "@" in checkpoint:  # STEP@STATIC: this row's own static network
                checkpoint, static_checkpoint = checkpoint.split("@", 1)
            step_row = name in variants or name == "inertial_optimum"
            method = make("inertial" if step_row else name, MethodOptions(checkpoint=checkpoint or None))
            if (name == "inertial" or name in variants) and static_checkpoint:
                method.equilibrium = make("static", MethodOptions(checkpoint=static_checkpoint))
            if name == "inertial_optimum":
                method.equilibrium = _Given(optimum)
            result = method.simulate(frames)
            positions[name] = result.positions
            rows[name] = _fidelity_row(result, physics.positions, rigid)
        per_frame = frame_metrics_of(positions, frames)
        for name, (metrics, _) in per_frame.items():
            row = rows.setdefault(name, {"ms_per_frame": physics.time_ms})
            row["penetration_percent_mean"] = sum(metrics["penetration_percent"]) / len(metrics["penetration_percent"])
            row["penetration_percent_max"] = max(metrics["penetration_percent"])
            row["length_change_percent_max"] = max(metrics["length_change_percent"])
        rows["physics"]["seconds"] = physics_s
        size = {"strands": int(rigid.shape[1]), "vertices": int(rigid.shape[2]), "frames": int(rigid.shape[0])}
        records.append({"scene": label, "hairstyle": style, "pose": pose, "size": size, "rows": rows})
        curves = {n: mean_tip_offset(p, rigid).cpu() for n, p in positions.items() if n != "rigid"}
        for name, curve in curves.items():
            # The swing plot's curves less their means, RMS per axis [mm]: how far the hair as a
            # whole swings each way (a curly walk's vertical bounce, docs/network_diagnosis.md T22).
            bulk = curve - curve.mean(dim=0)
            rows[name]["bulk_swing_by_axis_mm"] = (bulk.square().mean(dim=0).sqrt() * 1e3).tolist()
        machine = torch.cuda.get_device_name() if device.type == "cuda" else "CPU"
        swing_plot(curves, os.path.join(args.out, f"swing_inertial_{label}.png"), fps=float(scene.motion.fps),
                   title=f"{label}: {size['strands']} strands x {size['vertices']}, {machine}")
        print(label, json.dumps(rows, indent=None, default=float), flush=True)
    with open(os.path.join(args.out, "evaluate_inertial.json"), "w") as f:
        json.dump({"device": str(device), "records": records, "command": " ".join(sys.argv)}, f, indent=1)
    with open(os.path.join(args.out, "evaluate_inertial.md"), "w") as f:
        f.write(_markdown(records))
    print(_markdown(records))
    return 0


def _fmt(v, spec=".1f"):
    return "-" if v is None else format(v, spec)


def _markdown(records) -> str:
    lines = ["| scene | method | to physics mean / max [mm] | swing [mm] (physics) | amplitude ratio | correlation | "
             "correlation x / y / z | bulk correlation | inside % mean / max | length change % max | ms/frame |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for rec in records:
        for name, row in rec["rows"].items():
            lines.append(
                f"| {rec['scene']} | {name} | {_fmt(row.get('mean_distance_mm'))} / {_fmt(row.get('max_distance_mm'))} | "
                f"{_fmt(row.get('swing_mm'))} ({_fmt(row.get('physics_swing_mm'))}) | "
                f"{_fmt(row.get('swing_amplitude_ratio'), '.2f')} | {_fmt(row.get('swing_correlation'), '.3f')} | "
                f"{' / '.join(_fmt(c, '.2f') for c in row.get('swing_correlation_by_axis') or (None,) * 3)} | "
                f"{_fmt(row.get('bulk_swing_correlation'), '.2f')} | "
                f"{_fmt(row['penetration_percent_mean'], '.3f')} / {_fmt(row['penetration_percent_max'], '.3f')} | "
                f"{_fmt(row['length_change_percent_max'], '.3f')} | {_fmt(row.get('ms_per_frame'), '.2f')} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="simulate the clips and train the step")
    t.add_argument("--styles", default=",".join(STYLES), help="hairstyle presets of the training clips")
    t.add_argument("--clips-per-style", type=int, default=4)
    t.add_argument("--strand-stride", type=int, default=4, help="every k-th scalp root (4: 256 strands)")
    t.add_argument("--steps", type=int, default=300)
    t.add_argument("--lr", type=float, default=3e-3)
    t.add_argument("--eval-every", type=int, default=50)
    t.add_argument("--grad-clip", type=float, default=0.0, help="clip the gradient's norm to this (0: off)")
    t.add_argument("--projection-max-gain", type=float, default=0.0,
                   help="cap follow-the-leader's adjoint gain at this in training (0: exact; the chain step: 3)")
    t.add_argument("--resume", default=None, help="a run folder or checkpoint.pt to continue")
    t.add_argument("--run-name", default="run", help="OUT/<name>/ holds the run, OUT/<name>_inertial.pt the step")
    t.add_argument("--model", default="", help="InertialConfig fields, e.g. damping=absolute,coupling=chain")
    t.add_argument("--equilibrium", default="static", choices=("static", "optimum"),
                   help="E(t) of the clips: the static network, or each frame's static optimum")
    e = sub.add_parser("evaluate", help="held-out motions against the physics")
    e.add_argument("--checkpoint", default=None, help="the step (None: the shipped one)")
    e.add_argument("--static-checkpoint", default=None,
                   help="a static network for the rows static and inertial (None: the shipped one)")
    e.add_argument("--strand-stride", type=int, default=1)
    e.add_argument("--scenes", default=None,
                   help="comma-separated labels (default: all), or scenes of one's own as "
                        "LABEL=HAIRSTYLE:POSE:START:DURATION, e.g. walk=long_straight:sway_walk:0:2")
    e.add_argument("--variants", default="",
                   help="more inertial steps as rows: name=STEP[@STATIC],... (STEP empty: the shipped step; "
                        "@STATIC: that row's static network, else --static-checkpoint's)")
    e.add_argument("--methods", default=",".join(METHODS), help="the methods' rows (rigid is always one)")
    e.add_argument("--physics-repeat", action="store_true",
                   help="also the row physics_repeat: the physics run again, against the first run (on a GPU "
                        "the contact sums' order differs between runs: how far the physics is from itself)")
    e.add_argument("--oracle", action="store_true",
                   help="also the rows optimum (each frame's static optimum, the physics' drape) and "
                        "inertial_optimum (the step with those as its equilibrium)")
    for p in (t, e):
        p.add_argument("--device", default="cpu")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.command == "evaluate":
        try:
            evaluation_specs(args.scenes)  # a malformed scene refused before any work
        except ValueError as error:
            parser.error(str(error))
    os.makedirs(args.out, exist_ok=True)
    torch.manual_seed(args.seed)
    return train(args) if args.command == "train" else evaluate(args)


if __name__ == "__main__":
    raise SystemExit(main())
