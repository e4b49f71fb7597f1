"""Where a method's swing parts from the physics': phase, axis, the whole groom or each strand.

Question it answers: the shipped inertial step meets the swing goals on whiplash, torso_bend and
the AMASS-format file but not on the bob's nod (correlation 0.70) or the curly walk (0.47), and no
constant of the step moves them (docs/network_diagnosis.md, T9). Is its swing late or early (a
phase the constants could set), along the wrong axis, or right for the groom as a whole and wrong
strand by strand (what the body does to each strand, which the step does not see)?

    python3 tools/swing_decomposition.py --device cpu --strand-stride 4 --scenes bob_nod,curly_sway_walk --out OUT

Per held-out scene of `tools/train_inertial.py evaluate` (the physics, the method "inertial" and
its equilibrium, the static network without the body pass, cached in OUT/clips/), the tips' swing
(`hairwarp.metrics.tip_swing`: offset from the rigid placement minus its mean over the motion)
of the step against the physics':
- the correlation with the step shifted by -15..15 frames (positive: the step later);
- per axis (x to the body's left, y up, z forward): correlation and RMS [mm] of each;
- per third of the strands by how far the tip hangs below the root in the first frame;
- the groom's mean swing (the mean over strands, what the whole groom does) and each strand's
  residual from it (what the strands do differently), correlation and RMS of each.

Writes OUT/swing_decomposition.json and prints one line per scene.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

MAX_LAG = 15


def _correlation(a: torch.Tensor, b: torch.Tensor) -> float | None:
    from hairwarp.metrics import swing_correlation

    return swing_correlation(a, b)


def _rms_mm(a: torch.Tensor) -> float:
    """RMS over frames and strands of the swing's length [mm] (`motion_fidelity`'s swing_mm)."""
    from hairwarp.metrics import swing_rms

    return swing_rms(a) * 1e3


def _pair(step: torch.Tensor, physics: torch.Tensor) -> dict:
    return {"correlation": _correlation(step, physics), "step_rms_mm": _rms_mm(step),
            "physics_rms_mm": _rms_mm(physics)}


def decompose(step: torch.Tensor, physics: torch.Tensor, rigid: torch.Tensor) -> dict:
    """The decomposition of the module docstring for (T, M, N, 3) trajectories [m]."""
    from hairwarp.metrics import swing_by_axis, tip_swing

    s, p = tip_swing(step, rigid), tip_swing(physics, rigid)  # (T, M, 3)
    frames = s.shape[0]
    lags = {}
    for lag in range(-min(MAX_LAG, frames - 2), min(MAX_LAG, frames - 2) + 1):
        a, b = (s[lag:], p[:frames - lag]) if lag >= 0 else (s[:frames + lag], p[-lag:])
        lags[lag] = _correlation(a, b)
    best = max((k for k in lags if lags[k] is not None), key=lambda k: lags[k], default=0)
    by_axis = swing_by_axis(s, p)
    axes = {name: {"correlation": by_axis["correlation"][i], "step_rms_mm": by_axis["rms_mm"][i],
                   "physics_rms_mm": by_axis["reference_rms_mm"][i]}
            for i, name in enumerate("xyz")}
    drop = rigid[0, :, 0, 1] - rigid[0, :, -1, 1]  # how far each tip hangs below its root [m]
    order = torch.argsort(drop)
    thirds = torch.tensor_split(order, 3)
    groups = {name: _pair(s[:, idx], p[:, idx]) for name, idx in zip(("tips_highest", "middle", "tips_lowest"), thirds)}
    mean_s, mean_p = s.mean(dim=1, keepdim=True), p.mean(dim=1, keepdim=True)
    return {"lag_correlation": lags, "best_lag": best, "best_lag_correlation": lags.get(best),
            "axes": axes, "strand_thirds": groups, "groom_mean": _pair(mean_s, mean_p),
            "strand_residual": _pair(s - mean_s, p - mean_p)}


def _trajectories(scene, device, path) -> dict:
    """{"rigid", "physics", "step", "equilibrium"} (T, M, N, 3) float32 on the CPU, cached at `path`."""
    from hairwarp.methods import MethodOptions, make
    from hairwarp.methods.networks import NetworkMethod

    if os.path.isfile(path):
        return torch.load(path, weights_only=True)
    frames = scene.frames(device=device)
    data = {"rigid": frames.rigid.positions,
            "physics": make("physics").simulate(frames).positions,
            "step": make("inertial").simulate(frames).positions,
            "equilibrium": NetworkMethod("static", MethodOptions(keep_out=False)).simulate(frames).positions}
    data = {k: v.detach().float().cpu() for k, v in data.items()}
    torch.save(data, path)
    return data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0, help="unused (the scenes are fixed); kept for the habits")
    parser.add_argument("--strand-stride", type=int, default=4, help="every k-th scalp root (1: the full 1 024)")
    parser.add_argument("--scenes", default=None, help="held-out labels of tools/train_inertial.py (default: all six)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)

    from hairwarp.metrics import motion_fidelity
    from train_inertial import EVALUATION, _evaluation_scene

    device = torch.device(args.device)
    os.makedirs(os.path.join(args.out, "clips"), exist_ok=True)
    labels = args.scenes.split(",") if args.scenes else [e[0] for e in EVALUATION]
    unknown = sorted(set(labels) - {e[0] for e in EVALUATION})
    if unknown:
        parser.error(f"--scenes: unknown labels {unknown}; expected some of {[e[0] for e in EVALUATION]}")
    record = {"command": " ".join(["python3", "tools/swing_decomposition.py", *(argv or sys.argv[1:])]),
              "device": torch.cuda.get_device_name() if device.type == "cuda" else "CPU", "scenes": {}}
    for label, style, pose, start, duration in EVALUATION:
        if label not in labels:
            continue
        t0 = time.perf_counter()
        scene = _evaluation_scene(label, style, pose, start, duration, args.strand_stride, args.out)
        data = _trajectories(scene, device, os.path.join(args.out, "clips", f"{label}_s{args.strand_stride}.pt"))
        fidelity = motion_fidelity(data["step"], data["physics"], data["rigid"])
        row = {"size": list(data["rigid"].shape),
               "fidelity": {k: v for k, v in fidelity.items() if not isinstance(v, list)},
               "equilibrium_correlation": motion_fidelity(data["equilibrium"], data["physics"],
                                                          data["rigid"])["swing_correlation"],
               **decompose(data["step"], data["physics"], data["rigid"]), "seconds": time.perf_counter() - t0}
        record["scenes"][label] = row
        axes = ", ".join(f"{k} {v['correlation']:+.2f} ({v['step_rms_mm']:.0f}/{v['physics_rms_mm']:.0f} mm)"
                         for k, v in row["axes"].items())
        print(f"{label} {tuple(row['size'][1:3])}: correlation {fidelity['swing_correlation']:+.2f}, best at lag "
              f"{row['best_lag']:+d} frames {row['best_lag_correlation']:+.2f}; axes {axes}; groom mean "
              f"{row['groom_mean']['correlation']:+.2f} ({row['groom_mean']['step_rms_mm']:.0f}/"
              f"{row['groom_mean']['physics_rms_mm']:.0f} mm), strand residual "
              f"{row['strand_residual']['correlation']:+.2f} ({row['strand_residual']['step_rms_mm']:.0f}/"
              f"{row['strand_residual']['physics_rms_mm']:.0f} mm)", flush=True)
        with open(os.path.join(args.out, "swing_decomposition.json"), "w") as f:
            json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
