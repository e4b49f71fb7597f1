"""Probe: can the body pass free the vertices it leaves where two body parts meet?

The body pass (`hairwarp.methods.keep_out`) pushes along the signed distance's gradient; where
the arm meets the torso that push takes a vertex out of one part into the other, and a few stay
inside. The probe turns each strand's first such vertex about its predecessor (the segment's
length kept) to the outside direction nearest its own (the direction blended with 26 axis and
diagonal directions at five weights, and those 26 alone), the rest of the strand following
(follow-the-leader), for a number of rounds, then runs the pass again. Measured on the demo's
scene (long straight hair grown around the body, a one-second head turn), the inertial step's
rollout. Not in the library: see docs/network_diagnosis.md, "Eighteenth session".

    python3 tools/keep_out_pinch_probe.py --strand-stride 4 --rounds 12     # ~2 min on 2 cores
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import time

import torch


def _directions(like: torch.Tensor) -> torch.Tensor:
    axes = [torch.tensor(v) for v in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(v)]
    return torch.stack([v / v.norm() for v in axes]).to(like)  # (26, 3)


def step_around_pinches(x, rigid, body, *, margin: float, rounds: int) -> torch.Tensor:
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.ops import follow_the_leader, hair_body_signed_distance

    axes = _directions(x)
    weights = torch.tensor([0.25, 0.5, 1.0, 2.0, 4.0], dtype=x.dtype, device=x.device)
    for _ in range(rounds):
        d = hair_body_signed_distance(x, body)
        inside = d < 0
        inside[..., :NUM_FIXED_VERTICES] = False
        if not bool(inside.any()):
            break
        b_count, _, n = d.shape
        index = torch.arange(n, device=x.device).expand_as(d)
        first = torch.where(inside, index, torch.full_like(index, n)).min(-1).values
        bs, ms = torch.nonzero(first < n, as_tuple=True)
        i = first[bs, ms]
        before, at = x[bs, ms, i - 1], x[bs, ms, i]
        length = (rigid[bs, ms, i] - rigid[bs, ms, i - 1]).norm(dim=-1, keepdim=True)
        own = (at - before) / (at - before).norm(dim=-1, keepdim=True).clamp_min(1e-12)
        blends = (own[:, None, None] + weights[None, :, None, None] * axes[None, None]).reshape(len(i), -1, 3)
        turns = torch.cat([blends, axes[None].expand(len(i), -1, -1)], 1)
        turns = turns / turns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        candidates = before[:, None] + length[:, None] * turns  # (S, K, 3)
        # One query for every frame: (B, S_max, K, 3), padded with a root (outside the body).
        slot = torch.zeros_like(bs)
        for b in range(b_count):
            chosen = bs == b
            slot[chosen] = torch.arange(int(chosen.sum()), device=x.device)
        grid = x[:, :1, :1].expand(b_count, int(slot.max()) + 1, candidates.shape[1], 3).clone()
        grid[bs, slot] = candidates
        clearance = hair_body_signed_distance(grid, body)[bs, slot]
        score = torch.where(clearance >= 0.5 * margin, (turns * own[:, None]).sum(-1), clearance - 10.0)
        x = x.clone()
        x[bs, ms, i] = candidates[torch.arange(len(i), device=x.device), score.argmax(-1)]
        x = follow_the_leader(rigid, x, check=False)
    return x


def main(argv=None) -> int:
    import hairwarp as hw
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import load_inertial_step
    from hairwarp.methods.keep_out import KEEP_OUT_MARGIN, keep_out_of_body
    from hairwarp.methods.networks import NetworkMethod
    from hairwarp.metrics import frame_metrics_of

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--strand-stride", type=int, default=4)
    p.add_argument("--rounds", type=int, default=12)
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="keep_out_pinch_out")
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    device = torch.device(args.device)
    scene = hw.default_scene("long_straight", "head_turn", duration=1.0, strand_stride=args.strand_stride,
                             grow_around_body=True)
    frames = scene.frames(device=device)
    rigid = frames.rigid.positions
    equilibrium = NetworkMethod("static", MethodOptions(keep_out=False)).simulate(frames)
    with torch.no_grad():
        rollout = load_inertial_step(None, device).rollout(equilibrium.positions.to(rigid.dtype), rigid)
    passed, probed = rollout.clone(), rollout.clone()
    seconds = {"pass": 0.0, "probe": 0.0}
    start = 0
    for chunk in frames.chunks():
        rows = slice(start, start + chunk.num_frames)
        start = rows.stop
        t0 = time.perf_counter()
        passed[rows] = keep_out_of_body(rollout[rows].clone(), rigid[rows], chunk.body_mesh)
        t1 = time.perf_counter()
        turned = step_around_pinches(passed[rows], rigid[rows], chunk.body_mesh, margin=KEEP_OUT_MARGIN,
                                     rounds=args.rounds)
        probed[rows] = keep_out_of_body(turned, rigid[rows], chunk.body_mesh)
        seconds["pass"] += t1 - t0
        seconds["probe"] += time.perf_counter() - t1
    record = {"size": list(rigid.shape), "rounds": args.rounds, "seconds": seconds, "rows": {}}
    for name, x in (("pass", passed), ("pass + probe", probed)):
        metrics = frame_metrics_of({"x": x}, frames)["x"][0]
        inside, length = metrics["penetration_percent"], metrics["length_change_percent"]
        record["rows"][name] = row = {"inside_percent_mean": sum(inside) / len(inside), "inside_percent_max": max(inside),
                                      "length_change_percent_max": max(length)}
        print(f"{name}: inside {row['inside_percent_mean']:.4f} / {row['inside_percent_max']:.4f} %, length change "
              f"{row['length_change_percent_max']:.4f} %", flush=True)
    print(f"pass {seconds['pass']:.1f} s, probe {seconds['probe']:.1f} s for {rigid.shape[0]} frames")
    with open(os.path.join(args.out, "keep_out_pinch_probe.json"), "w") as f:
        json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
