"""How the chain step's three constants set its swing: a grid over G, beta and the tension, chosen on
training clips, judged on held-out motions.

Question it answers: the shipped inertial step is the chain step as initialised (G = 0.98, beta =
0.9, a hanging strand's tension); training it by rollouts has not moved it at full size
(docs/network_diagnosis.md, fifteenth to seventeenth sessions). Its swing lags the physics' and is
smaller (amplitude 0.40-0.76 on the held-out motions). Are the constants the limit: would less
drag (beta), a weaker pull to the equilibrium (G) or another tension swing like the physics?

    python3 tools/inertial_sweep.py --device cuda --out OUT                   # full size, ~10 min of an H100
    python3 tools/inertial_sweep.py --device cpu --strand-stride 16 --clips-per-style 1 \\
        --scenes whiplash --gates 0.98,0.995 --retentions 0.9,0.98 --tensions 1 --out OUT   # a smoke run

Per clip the physics (method "physics"), the rigid placement and the equilibrium (the static
network as the inertial method runs it, without the body pass) are computed once and cached in
OUT/clips/. Each setting is an untrained `InertialStep(InertialConfig(coupling="chain", ...))`
rolled out on every clip, with either damping (`--dampings`: beta damps the velocity, a drag that
makes hair carried at a steady speed trail its equilibrium by G (1 - beta) / (1 - G) frames of the
head's motion, or only the velocity relative to the head's). The setting is chosen on the training
clips alone (random head moves of `hairwarp.scene.motion.random_head_moves`, the step's training
data); the held-out motions (`tools/train_inertial.py evaluate`'s six) are only reported.
`--choose goals` (the default) takes the setting that meets the most goals on the training clips,
ties broken by the training loss: per clip, the swing goals of the networks' issue (correlation
>= 0.8, amplitude ratio 0.75-1.33) and the worst strands (p99 over the strands of the distance to
the physics, at the worst frame) no farther than the rigid placement's, the outer strands that fly
out in the demo's picture (twentieth session; the nineteenth chose by the two swing goals).
`--choose loss` takes the lowest training loss of `hairwarp.training.inertial` (swing error + 0.3 x
position error) over the same loss of the equilibrium alone, averaged over the clips. The two
disagree (the nineteenth session's run: the loss ranks the initial constants first, whose swing
meets the swing goals on 5 of 16 clip-goals, where 8 of 16 are met by lighter damping): the position
term is mostly the equilibrium's offset, which no constant of the step removes. The chosen
setting and the shipped step are then run as the method "inertial" (with the body pass) on the
held-out motions for penetration and length (`--no-method-rows` skips it).

The same rule on each hairstyle's training clips alone gives one setting per hairstyle; in the
nineteenth session's run they fell in order of strand length (bob: beta 0.98, tension x0.5;
medium wavy: 0.95, x1; long straight and long curly: 0.9, x2; G 0.99 for all). OUT/lengthwise_inertial.pt
is a chain step whose constants follow the strand length through those anchors
(`hairwarp.models.inertial.fit_constants_by_length`); `--lengthwise-from OUT/inertial_sweep.json`
writes it from an earlier run without the clips.

`--body-holds` and `--body-hold-distances` sweep the hold along the body's normal
(`InertialConfig.body_hold`, `body_hold_distance`; a hold of 0 is one setting); the clips then
also cache the equilibrium's distance and normal to the body, capped at the largest distance
(the twenty-third session's run: docs/network_diagnosis.md, T9).

Writes OUT/inertial_sweep.json, OUT/inertial_sweep.md, OUT/chosen_inertial.pt (the chosen
constants as a step checkpoint), OUT/lengthwise_inertial.pt and OUT/inertial_sweep.png (the
objective over G x beta); with `--state-pushed` also OUT/chosen_state_pushed_inertial.pt (the
chosen constants with `InertialConfig.keep_out_state` and `keep_out_equilibrium`), run as a third
method row, and one more checkpoint and row per other `--keep-out-velocities` value
(OUT/chosen_state_pushed_V_inertial.pt, `InertialConfig.keep_out_velocity`). `--rows` picks the
method rows to run.

    python3 tools/inertial_sweep.py --lengthwise-from docs/network_diagnosis/inertial_sweep_session19_h100.json --out OUT
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

STYLES = ("long_straight", "medium_wavy", "long_curly", "bob")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def _trajectories(scene, device, path, hold_cap: float | None = None) -> dict:
    """{"rigid", "physics", "equilibrium"} (T, M, N, 3) float32 of a scene, cached at `path`; with
    `hold_cap` [m] also "hold_distance" (T, M, N) and "hold_normal" (T, M, N, 3), the equilibrium's
    distance to the body (capped there) and the body's outward direction (`InertialConfig.body_hold`).
    """
    from hairwarp.methods import MethodOptions, make
    from hairwarp.methods.networks import NetworkMethod
    from hairwarp.ops import hair_body_signed_distance_and_normal

    data = torch.load(path, weights_only=True) if os.path.isfile(path) else None
    if data is not None and (hold_cap is None or float(data.get("hold_cap", torch.tensor(0.0))) >= hold_cap):
        return data
    start = time.perf_counter()
    frames = scene.frames(device=device)
    if data is None:
        # The equilibrium as the inertial method takes it: the static network without the body pass.
        equilibrium = NetworkMethod("static", MethodOptions(keep_out=False)).simulate(frames)
        data = {"rigid": frames.rigid.positions.detach().float(),
                "physics": make("physics").simulate(frames).positions.detach().float(),
                "equilibrium": equilibrium.positions.detach().float()}
    if hold_cap is not None:
        distances, normals, first = [], [], 0
        for chunk in frames.chunks():
            x = data["equilibrium"][first:first + chunk.num_frames].to(device, chunk.rigid.positions.dtype)
            distance, normal = hair_body_signed_distance_and_normal(x, chunk.body_mesh, max_distance=hold_cap)
            distances.append(distance.float().cpu())
            normals.append(normal.float().cpu())
            first += chunk.num_frames
        data["hold_distance"], data["hold_normal"] = torch.cat(distances), torch.cat(normals)
        data["hold_cap"] = torch.tensor(float(hold_cap))
    data = {k: v.cpu() for k, v in data.items()}
    torch.save(data, path)
    print(f"{os.path.basename(path)}: {tuple(data['rigid'].shape)} in {time.perf_counter() - start:.1f} s", flush=True)
    return data


def _step(gate: float, retention: float, tension: float, damping: str = "absolute", speed: float | None = None,
          bending: float = 0.0, body_hold: float = 0.0, body_hold_distance: float = 0.02, keep_out_state: bool = False,
          keep_out_equilibrium: bool = False, keep_out_velocity: str = "pushed", projection_damping: float = 0.0,
          curl_gate: float | None = None, curl_bending: float = 1.0):
    from hairwarp.models.inertial import InertialConfig, InertialStep

    return InertialStep(InertialConfig(coupling="chain", damping=damping, gate_init=gate, retention_init=retention,
                                       tension_init=tension, equilibrium_speed=speed, bending=bending,
                                       body_hold=body_hold, body_hold_distance=body_hold_distance,
                                       keep_out_state=keep_out_state, keep_out_equilibrium=keep_out_equilibrium,
                                       keep_out_velocity=keep_out_velocity, projection_damping=projection_damping,
                                       curl_gate=curl_gate, curl_bending=curl_bending))


def _fixed(args) -> dict:
    """What every setting shares with the shipped step (unless the command line says otherwise), so
    that the grid's row of the shipped constants is the shipped step.
    """
    return {"projection_damping": args.projection_damping, "curl_gate": args.curl_gate,
            "curl_bending": args.curl_bending}


def _key(r: dict) -> tuple:
    return (r["gate"], r["retention"], r["tension"], r.get("damping", "absolute"), r.get("equilibrium_speed"),
            r.get("bending", 0.0), r.get("body_hold", 0.0), r.get("body_hold_distance", 0.02))


def _speeds(text: str) -> list[float | None]:
    return [None if v == "none" else float(v) for v in text.split(",") if v]


def _loss(x, clip) -> float:
    """The training loss of `hairwarp.training.inertial` (swing + 0.3 x position, [m^2])."""
    from hairwarp.training.inertial import InertialTrainingConfig, swing_of

    cfg = InertialTrainingConfig()
    swing = (swing_of(x, clip["rigid"]) - swing_of(clip["physics"], clip["rigid"])).square().sum(-1).mean()
    position = (x - clip["physics"]).square().sum(-1).mean()
    return float(cfg.swing_weight * swing + cfg.position_weight * position)


def _scores(x, clip) -> dict:
    from hairwarp.metrics import motion_fidelity

    fid = motion_fidelity(x, clip["physics"], clip["rigid"])
    return {"loss": _loss(x, clip), "mean_distance_mm": fid["mean_distance_mm"],
            "strand_distance_p99_mm": fid["strand_distance_p99_mm"],
            "swing_correlation": fid["swing_correlation"], "swing_amplitude_ratio": fid["swing_amplitude_ratio"],
            "largest_step_mm": fid["largest_step_mm"]}


def _offset_rates(clip) -> dict:
    """How fast the physics' and the equilibrium's offsets from the rigid placement move, per strand
    and frame (the mean over a strand's moving vertices) [mm per frame]: mean, 99.9th percentile,
    max. The static network's drape can jump where the hair cannot (`InertialConfig.equilibrium_speed`).
    """
    from hairwarp.config import NUM_FIXED_VERTICES

    out = {}
    for name in ("physics", "equilibrium"):
        offset = (clip[name] - clip["rigid"])[:, :, NUM_FIXED_VERTICES:]
        rate = ((offset[1:] - offset[:-1]).norm(dim=-1).mean(dim=-1) * 1e3).flatten().double().cpu()
        out[name] = {"mean": float(rate.mean()), "p999": float(rate.quantile(0.999)), "max": float(rate.max())}
    return out


def _goals_met(row: dict, rigid_row: dict | None = None) -> int:
    """How many goals a clip's row meets: the swing's correlation >= 0.8 and amplitude 0.75-1.33,
    and, given the rigid placement's row, worst strands (p99 of the strand distance to the physics)
    no farther than the rigid placement's (the demo's outer strands that fly out)."""
    corr, amp = row["swing_correlation"], row["swing_amplitude_ratio"]
    met = int(corr is not None and corr >= 0.8) + int(amp is not None and 0.75 <= amp <= 1.33)
    if rigid_row is not None:
        met += int(row["strand_distance_p99_mm"] <= rigid_row["strand_distance_p99_mm"])
    return met


def _summary(rows: dict, key: str) -> float | None:
    values = [r[key] for r in rows.values() if r.get(key) is not None]
    return sum(values) / len(values) if values else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0, help="unused by the grid; kept for the command line's habits")
    parser.add_argument("--out", required=True)
    parser.add_argument("--strand-stride", type=int, default=1, help="every k-th scalp root (1: the full 1 024)")
    parser.add_argument("--styles", default=",".join(STYLES), help="hairstyles of the training clips")
    parser.add_argument("--clips-per-style", type=int, default=2)
    parser.add_argument("--scenes", default=None, help="held-out labels of tools/train_inertial.py (default: all six)")
    parser.add_argument("--gates", default="0.98,0.99,0.995,0.999", help="G values")
    parser.add_argument("--retentions", default="0.9,0.95,0.98,0.99", help="beta values")
    parser.add_argument("--tensions", default="0.5,1,2", help="tension factors (x a hanging strand's)")
    parser.add_argument("--dampings", default="absolute,relative",
                        help="what beta damps (InertialConfig.damping): the velocity, or the one relative to the head")
    parser.add_argument("--equilibrium-speeds", default="none",
                        help="InertialConfig.equilibrium_speed values [m/s], 'none' for unlimited")
    parser.add_argument("--bendings", default="0", help="InertialConfig.bending values")
    parser.add_argument("--projection-damping", type=float, default=None,
                        help="InertialConfig.projection_damping of every setting (default: the shipped step's, so "
                             "that the grid's row of the shipped constants is the shipped step)")
    parser.add_argument("--curl-gate", default=None,
                        help="InertialConfig.curl_gate of every setting, 'none' for the MLP's G on every strand "
                             "(default: the shipped step's)")
    parser.add_argument("--curl-bending", type=float, default=None,
                        help="InertialConfig.curl_bending of every setting (default: the shipped step's)")
    parser.add_argument("--body-holds", default="0", help="InertialConfig.body_hold values (kappa; 0: no hold)")
    parser.add_argument("--body-hold-distances", default="0.02",
                        help="InertialConfig.body_hold_distance values [m] (swept where body_hold > 0)")
    parser.add_argument("--no-method-rows", action="store_true",
                        help="skip running the chosen and the shipped step as the method on the held-out motions")
    parser.add_argument("--state-pushed", action="store_true",
                        help="also run the chosen step with InertialConfig.keep_out_state and keep_out_equilibrium "
                             "(the body pass acting on the step's state and its equilibrium) as a method row")
    parser.add_argument("--keep-out-velocities", default="pushed",
                        help="with --state-pushed: InertialConfig.keep_out_velocity values, a method row each")
    parser.add_argument("--rows", default=None,
                        help="the method rows to run, comma-separated (default: shipped, chosen and the state-pushed ones)")
    parser.add_argument("--choose", default="goals", choices=("goals", "loss"),
                        help="how the training clips choose the setting (module docstring)")
    parser.add_argument("--lengthwise-from", default=None, metavar="JSON",
                        help="skip the clips and the grid: read an earlier run's inertial_sweep.json and write "
                             "OUT/lengthwise_inertial.pt from it (module docstring)")
    args = parser.parse_args(argv)
    if args.projection_damping is None:
        args.projection_damping = _shipped_config().projection_damping
    elif not 0.0 <= args.projection_damping <= 1.0:
        parser.error(f"--projection-damping: expected a number in [0, 1], got {args.projection_damping}")
    if args.curl_gate is None:
        args.curl_gate = _shipped_config().curl_gate
    elif args.curl_gate.lower() == "none":
        args.curl_gate = None
    else:
        try:
            args.curl_gate = float(args.curl_gate)
        except ValueError:
            parser.error(f"--curl-gate: expected a number in (0, 1) or 'none', got {args.curl_gate!r}")
        if not 0.0 < args.curl_gate < 1.0:
            parser.error(f"--curl-gate: expected a number in (0, 1) or 'none', got {args.curl_gate}")
    if args.curl_bending is None:
        args.curl_bending = _shipped_config().curl_bending
    elif not 0.0 <= args.curl_bending <= 1.0:
        parser.error(f"--curl-bending: expected a number in [0, 1], got {args.curl_bending}")
    fixed = _fixed(args)

    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import InertialMethod
    from hairwarp.metrics import frame_metrics_of
    from hairwarp.models.checkpoint import save_checkpoint
    from hairwarp.training.inertial import ClipSpec, clip_scene
    from train_inertial import EVALUATION, _evaluation_scene

    device = torch.device(args.device)
    os.makedirs(args.out, exist_ok=True)
    if args.lengthwise_from:
        with open(args.lengthwise_from) as f:
            record = json.load(f)
        _save_lengthwise(record["settings"], record["train_clips"], record["equilibrium"], args)
        return 0
    cache = os.path.join(args.out, "clips")
    os.makedirs(cache, exist_ok=True)
    tag = f"s{args.strand_stride}"
    holds, hold_distances = _floats(args.body_holds), _floats(args.body_hold_distances)
    hold_cap = max(hold_distances) if any(holds) else None
    train = {}
    for i, style in enumerate(args.styles.split(",")):
        for j in range(args.clips_per_style):
            spec = ClipSpec(style, "head_moves", 100 * i + j, 0.0, 1.5)
            train[spec.key] = _trajectories(clip_scene(spec, args.strand_stride, 100), device,
                                            os.path.join(cache, f"train_{spec.key}_{tag}.pt"), hold_cap)
    labels = args.scenes.split(",") if args.scenes else [e[0] for e in EVALUATION]
    held_scenes, held = {}, {}
    for label, style, pose, start, duration in EVALUATION:
        if label in labels:
            held_scenes[label] = _evaluation_scene(label, style, pose, start, duration, args.strand_stride, args.out)
            held[label] = _trajectories(held_scenes[label], device, os.path.join(cache, f"held_{label}_{tag}.pt"),
                                        hold_cap)

    def on_device(clip):
        return {k: v.to(device) for k, v in clip.items()}

    baseline = {name: _scores(on_device(c)["equilibrium"], on_device(c)) for name, c in {**train, **held}.items()}
    rigid_rows = {n: _scores(on_device(c)["rigid"], on_device(c)) for n, c in {**train, **held}.items()}
    # A hold of 0 is one setting whatever its distance.
    hold_settings = [(k, d) for k in holds for d in (hold_distances if k else hold_distances[:1])]
    grid = [(*head, *hold) for head, hold in itertools.product(
        itertools.product(_floats(args.gates), _floats(args.retentions), _floats(args.tensions),
                          args.dampings.split(","), _speeds(args.equilibrium_speeds), _floats(args.bendings)),
        hold_settings)]
    results = []
    from tqdm.auto import tqdm

    with torch.no_grad():
        for setting in tqdm(grid, desc="settings", dynamic_ncols=True):
            gate, retention, tension, damping, speed, bending, body_hold, hold_distance = setting
            step = _step(*setting, **fixed).to(device)
            rows = {}
            for name, clip in {**train, **held}.items():
                clip = on_device(clip)
                hold = (clip["hold_distance"], clip["hold_normal"]) if body_hold else None
                rows[name] = _scores(step.rollout(clip["equilibrium"], clip["rigid"], hold=hold), clip)
            objective = sum(rows[n]["loss"] / baseline[n]["loss"] for n in train) / len(train)
            results.append({"gate": gate, "retention": retention, "tension": tension, "damping": damping,
                            "equilibrium_speed": speed, "bending": bending, "body_hold": body_hold,
                            "body_hold_distance": hold_distance, "train_objective": objective, "rows": rows})
    for r in results:
        r["train_swing_goals_met"] = sum(_goals_met(r["rows"][n], rigid_rows[n]) for n in train)
    if args.choose == "goals":
        results.sort(key=lambda r: (-r["train_swing_goals_met"], r["train_objective"]))
    else:
        results.sort(key=lambda r: r["train_objective"])
    chosen = results[0]
    shipped_config = _shipped_config()
    shipped_key = (shipped_config.gate_init, shipped_config.retention_init, shipped_config.tension_init,
                   shipped_config.damping, shipped_config.equilibrium_speed, shipped_config.bending,
                   shipped_config.body_hold, shipped_config.body_hold_distance)
    if not shipped_config.body_hold:
        shipped_key = (*shipped_key[:-1], hold_distances[0])  # a hold of 0 is one setting (above)
    shipped = next((r for r in results if _key(r) == shipped_key), None)
    save_checkpoint(os.path.join(args.out, "chosen_inertial.pt"),
                    _step(*_key(chosen), **fixed).float(),
                    extra={"chosen_by": f"tools/inertial_sweep.py --choose {args.choose}",
                           "train_objective": chosen["train_objective"],
                           "train_swing_goals_met": chosen["train_swing_goals_met"]})

    pushed_rows = {}
    if args.state_pushed:
        for velocity in args.keep_out_velocities.split(","):
            name = "chosen_state_pushed" + ("" if velocity == "pushed" else f"_{velocity}")
            pushed_rows[name] = os.path.join(args.out, f"{name}_inertial.pt")
            save_checkpoint(pushed_rows[name],
                            _step(*_key(chosen), keep_out_state=True, keep_out_equilibrium=True,
                                  keep_out_velocity=velocity, **fixed).float(),
                            extra={"chosen_by": f"tools/inertial_sweep.py --choose {args.choose}, keep_out_state and "
                                                f"keep_out_equilibrium on, keep_out_velocity {velocity}"})

    _save_lengthwise(results, list(train), baseline, args, rigid_rows)

    # The chosen step and the shipped one as the method runs them (the body pass included).
    method_rows = {}
    runs = () if args.no_method_rows else (("shipped", None), ("chosen", os.path.join(args.out, "chosen_inertial.pt")),
                                           *pushed_rows.items())
    if args.rows is not None:
        wanted = args.rows.split(",")
        runs = tuple(r for r in runs if r[0] in wanted)
    for name, checkpoint in runs:
        for label, scene in held_scenes.items():
            frames = scene.frames(device=device)
            result = InertialMethod(MethodOptions(checkpoint=checkpoint)).simulate(frames)
            metrics, _ = frame_metrics_of({name: result.positions}, frames)[name]
            clip = on_device(held[label])
            method_rows.setdefault(name, {})[label] = {
                **_scores(result.positions.float(), clip),
                "penetration_percent_mean": sum(metrics["penetration_percent"]) / len(metrics["penetration_percent"]),
                "penetration_percent_max": max(metrics["penetration_percent"]),
                "length_change_percent_max": max(metrics["length_change_percent"]),
                "step_ms": result.info.get("step_ms")}
    machine = torch.cuda.get_device_name() if device.type == "cuda" else "CPU"
    size = tuple(next(iter(held.values()))["rigid"].shape[1:3]) if held else None
    record = {"command": " ".join(["python3", "tools/inertial_sweep.py", *(argv or sys.argv[1:])]), "device": machine,
              "size": size, "choose": args.choose, **fixed,
              "train_clips": list(train), "held_out": list(held),
              "equilibrium": baseline, "rigid": rigid_rows, "settings": results, "method_rows": method_rows,
              "offset_rates_mm_per_frame": {n: _offset_rates(c) for n, c in {**train, **held}.items()}}
    with open(os.path.join(args.out, "inertial_sweep.json"), "w") as f:
        json.dump(record, f, indent=1)
    text = _markdown(record, shipped)
    with open(os.path.join(args.out, "inertial_sweep.md"), "w") as f:
        f.write(text)
    print(text)
    _plot(results, os.path.join(args.out, "inertial_sweep.png"), machine, size)
    return 0


def _shipped_config():
    """The `InertialConfig` of the shipped step (the constants it was made with)."""
    from hairwarp.methods.inertial import load_inertial_step

    return load_inertial_step(None, torch.device("cpu")).config


def _save_lengthwise(results: list[dict], train: list[str], baseline: dict, args, rigid_rows: dict | None = None) -> list:
    """Choose a setting per hairstyle of the training clips (the same rule on that hairstyle's
    clips alone), and write OUT/lengthwise_inertial.pt: a chain step whose constants follow the
    hairstyles' median strand length (`fit_constants_by_length`). Returns the anchors
    [(L [m], G, beta, tension, hairstyle)].
    """
    from hairwarp.models.checkpoint import save_checkpoint
    from hairwarp.models.inertial import fit_constants_by_length
    from hairwarp.training.inertial import ClipSpec, clip_scene

    styles: dict[str, list[str]] = {}
    for name in train:
        styles.setdefault(name.split("_head_moves")[0], []).append(name)
    anchors = []
    for style, names in styles.items():
        def rank(r, names=names):
            objective = sum(r["rows"][n]["loss"] / baseline[n]["loss"] for n in names) / len(names)
            goals = sum(_goals_met(r["rows"][n], rigid_rows[n] if rigid_rows else None) for n in names)
            return (-goals, objective) if args.choose == "goals" else (objective,)

        # One damping, equilibrium speed and bending for the whole step: those chosen over all the clips.
        best = min((r for r in results if _key(r)[3:] == _key(results[0])[3:]), key=rank)
        rigid = clip_scene(ClipSpec(style, "head_moves", 0, 0.0, 0.05), 8, 100).frames().rigid.positions[0]
        length = float((rigid[:, 1:] - rigid[:, :-1]).norm(dim=-1).sum(-1).median())
        anchors.append((length, best["gate"], best["retention"], best["tension"], style))
    anchors.sort()
    step = _step(0.98, 0.9, 1.0, *_key(results[0])[3:], **_fixed(args))
    error = fit_constants_by_length(step, [a[:4] for a in anchors])
    save_checkpoint(os.path.join(args.out, "lengthwise_inertial.pt"), step.float(),
                    extra={"chosen_by": f"tools/inertial_sweep.py --choose {args.choose}, per hairstyle",
                           "anchors": anchors, "fit_max_logit_error": error})
    for a in anchors:
        print(f"{a[4]}: median strand length {a[0]:.3f} m -> G {a[1]:g}, beta {a[2]:g}, tension x{a[3]:g}")
    print(f"lengthwise step written (largest logit error of the fit {error:.3f})", flush=True)
    return anchors


def _fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def _markdown(record: dict, shipped: dict | None) -> str:
    train, held = record["train_clips"], record["held_out"]
    lines = [f"# Chain step constants ({record['device']}, strands x vertices {record['size']})", "",
             f"`{record['command']}`", "",
             f"Chosen by `--choose {record['choose']}`. Train swing goals met: clips x goals (correlation >= 0.8, "
             "amplitude 0.75-1.33). Training objective: mean over the training clips of the loss over the equilibrium's "
             "loss (lower is better). Held out: mean distance to the physics [mm] over the mean of the rigid "
             "placement's, mean swing correlation, mean amplitude ratio, worst strands (p99 of the strand "
             "distance, worst frame) over the rigid placement's, averaged over the motions.", "",
             "| G | beta | tension | damping | equilibrium speed [m/s] | bending | body hold (kappa @ m) | "
             "train goals met | train objective | "
             "train corr | train amp | "
             "train p99 / rigid | held-out dist / rigid | held-out corr | held-out amp | held-out p99 / rigid |",
             "|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    rigid_mean = _summary({n: record["rigid"][n] for n in held}, "mean_distance_mm") if held else None
    shown = record["settings"][:12] + ([shipped] if shipped and shipped not in record["settings"][:12] else [])
    for r in shown:
        tr = {n: r["rows"][n] for n in train}
        ho = {n: r["rows"][n] for n in held}
        dist = _summary(ho, "mean_distance_mm") if held else None
        lines.append(f"| {r['gate']:g} | {r['retention']:g} | {r['tension']:g} | {r.get('damping', 'absolute')} | "
                     f"{_fmt(r.get('equilibrium_speed'), 'g')} | {r.get('bending', 0.0):g} | "
                     f"{_hold_text(r)} | "
                     f"{r['train_swing_goals_met']} / {3 * len(train)} | "
                     f"{r['train_objective']:.3f} | "
                     f"{_fmt(_summary(tr, 'swing_correlation'))} | {_fmt(_summary(tr, 'swing_amplitude_ratio'))} | "
                     f"{_fmt(_p99_ratio(r, record, train))} | "
                     f"{_fmt(None if dist is None else dist / rigid_mean)} | {_fmt(_summary(ho, 'swing_correlation'))} | "
                     f"{_fmt(_summary(ho, 'swing_amplitude_ratio'))} | {_fmt(_p99_ratio(r, record, held))} |"
                     + (" shipped" if r is shipped else ""))
    lines += ["", "How fast the offset from the rigid placement moves, per strand and frame [mm]: mean / 99.9th "
              "percentile / max", "", "| clip | physics | equilibrium |", "|---|---|---|"]
    for name, rates in record.get("offset_rates_mm_per_frame", {}).items():
        cells = [" / ".join(f"{rates[k][q]:.1f}" for q in ("mean", "p999", "max")) for k in ("physics", "equilibrium")]
        lines.append(f"| {name} | {cells[0]} | {cells[1]} |")
    if not record["method_rows"]:
        return "\n".join(lines) + "\n"
    lines += ["", "Held-out motions through the method (body pass included): mean distance [mm] (x rigid), "
              "correlation, amplitude, worst strands p99 [mm], largest move a frame [mm], inside % mean / max, "
              "length change % max, step time [ms a frame]", "",
              "| scene | rigid [mm] | " + " | ".join(record["method_rows"]) + " |",
              "|---|---:|" + "---|" * len(record["method_rows"])]
    for label in held:
        rigid = record["rigid"][label]["mean_distance_mm"]
        cells = []
        for name in record["method_rows"]:
            r = record["method_rows"][name][label]
            cells.append(f"{r['mean_distance_mm']:.1f} ({r['mean_distance_mm'] / rigid:.2f}x), "
                         f"{_fmt(r['swing_correlation'], '.3f')}, {_fmt(r['swing_amplitude_ratio'])}, "
                         f"{r['strand_distance_p99_mm']:.1f}, {_fmt(r.get('largest_step_mm'), '.1f')}, "
                         f"{r['penetration_percent_mean']:.3f} / {r['penetration_percent_max']:.3f}, "
                         f"{r['length_change_percent_max']:.3f}, {_fmt(r.get('step_ms'), '.1f')}")
        lines.append(f"| {label} | {rigid:.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _hold_text(r: dict) -> str:
    return f"{r['body_hold']:g} @ {r['body_hold_distance']:g}" if r.get("body_hold") else "-"


def _p99_ratio(r: dict, record: dict, names: list[str]) -> float | None:
    """Mean over `names` of the setting's worst-strand distance over the rigid placement's."""
    ratios = [r["rows"][n]["strand_distance_p99_mm"] / record["rigid"][n]["strand_distance_p99_mm"] for n in names
              if "strand_distance_p99_mm" in r["rows"][n] and record["rigid"][n]["strand_distance_p99_mm"] > 0]
    return sum(ratios) / len(ratios) if ratios else None


def _plot(results: list[dict], path: str, machine: str, size) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tensions = sorted({r["tension"] for r in results})
    gates = sorted({r["gate"] for r in results})
    retentions = sorted({r["retention"] for r in results})
    dampings = sorted({r.get("damping", "absolute") for r in results})
    fig, axes = plt.subplots(len(dampings), len(tensions), figsize=(4.2 * len(tensions), 3.6 * len(dampings)),
                             squeeze=False)
    by: dict[tuple, float] = {}  # the best objective over the equilibrium speeds, bendings and holds
    for r in results:
        by[_key(r)[:4]] = min(by.get(_key(r)[:4], float("inf")), r["train_objective"])
    for ax, (damping, tension) in zip(axes.flat, itertools.product(dampings, tensions)):
        grid = [[by.get((g, b, tension, damping), float("nan")) for g in gates] for b in retentions]
        image = ax.imshow(grid, origin="lower", cmap="viridis")
        ax.set_xticks(range(len(gates)), [f"{g:g}" for g in gates])
        ax.set_yticks(range(len(retentions)), [f"{b:g}" for b in retentions])
        for (i, j), v in ((ij, grid[ij[0]][ij[1]]) for ij in itertools.product(range(len(retentions)), range(len(gates)))):
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="w", fontsize=7)
        ax.set_title(f"{damping} damping, tension x{tension:g}\ntrain objective (best over speed, bending, hold)",
                     fontsize=9)
        ax.set(xlabel="G", ylabel="beta")
        fig.colorbar(image, ax=ax, fraction=0.046)
    fig.text(0.01, 0.01, f"tools/inertial_sweep.py, {machine},\nstrands x vertices {size}; lower is better", fontsize=7)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
