"""Where the inertial method's time per frame goes: the static network's equilibrium, the step's
rollout and its body pass, on a held-out motion at full size (torch.profiler, CPU and device).

    python tools/profile_inertial.py --device cuda --motions whiplash,wavy_amass --out OUT

For each motion: `InertialMethod().simulate` once to warm up (kernels built, graphs captured), then
once under the profiler. Writes OUT/profile_inertial.json: per motion the method's own times (the
step's ms a frame, the equilibrium's), the profiled wall and device-busy time a frame, the host
reads a frame (`aten::item` and `aten::_local_scalar_dense`, each a wait for the device), each
kernel's device time a frame and each host op's own time a frame, largest first.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

# Host ops that wait for the device (a read of a device value).
HOST_READS = ("aten::item", "aten::_local_scalar_dense")


def _host_ops(profile, per: float, top: int) -> tuple[dict[str, float], dict[str, float]]:
    """({op: own host time a frame [us]}, {host read op: calls a frame}) of a finished profile."""
    own, reads = {}, {}
    for event in profile.key_averages():
        if event.self_cpu_time_total:
            own[event.key] = event.self_cpu_time_total / per
        if event.key in HOST_READS:
            reads[event.key] = event.count / per
    ranked = sorted(own.items(), key=lambda kv: -kv[1])[:top]
    return dict(ranked), reads


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--motions", default="whiplash,wavy_amass",
                   help="held-out labels of tools/train_inertial.py")
    p.add_argument("--strand-stride", type=int, default=1, help="every k-th scalp root (1: the full 1 024)")
    p.add_argument("--seed", type=int, default=0, help="unused; kept for the command line's habits")
    p.add_argument("--out", default="profile_inertial_out")
    args = p.parse_args(argv)
    from diagnose_networks import write_json
    from train_inertial import EVALUATION, _evaluation_scene

    from hairwarp.methods.inertial import InertialMethod
    from hairwarp.runtime import kernel_device_times, machine_description, synchronize

    device = torch.device(args.device)
    os.makedirs(args.out, exist_ok=True)
    record = {"machine": machine_description(device), "command": "python tools/profile_inertial.py "
              + " ".join(argv if argv is not None else sys.argv[1:]), "motions": {}}
    known = {e[0]: e for e in EVALUATION}
    for name in args.motions.split(","):
        if name not in known:
            raise SystemExit(f"--motions: {name!r} is not one of {', '.join(known)}")
        label, style, pose, start, duration = known[name]
        scene = _evaluation_scene(label, style, pose, start, duration, args.strand_stride, args.out)
        frames = scene.frames(device=device)
        count = frames.num_frames
        InertialMethod().simulate(frames)  # warm-up: kernels, graphs
        activities = [torch.profiler.ProfilerActivity.CPU]
        if device.type == "cuda":
            activities.append(torch.profiler.ProfilerActivity.CUDA)
        synchronize(device)
        start_time = time.perf_counter()
        with torch.profiler.profile(activities=activities) as prof:
            result = InertialMethod().simulate(frames)
            synchronize(device)
        wall = time.perf_counter() - start_time
        kernels = kernel_device_times(prof, per=count)
        host, reads = _host_ops(prof, count, 30)
        entry = {"frames": count, "strands": int(frames.rigid.positions.shape[1]),
                 "vertices": int(frames.rigid.positions.shape[2]),
                 "step_ms_per_frame": result.info.get("step_ms"),
                 "method_ms_per_frame": result.time_ms,
                 "wall_ms_per_frame_under_profiler": wall * 1e3 / count,
                 "device_busy_ms_per_frame": sum(kernels.values()) / 1e3,
                 "host_reads_per_frame": reads,
                 "kernels_us_per_frame": dict(list(kernels.items())[:40]),
                 "host_ops_own_us_per_frame": host}
        record["motions"][name] = entry
        print(f"{name}: {count} frames, the step {entry['step_ms_per_frame']:.1f} ms a frame "
              f"(the method {entry['method_ms_per_frame']:.1f}), under the profiler "
              f"{entry['wall_ms_per_frame_under_profiler']:.1f} ms a frame, device busy "
              f"{entry['device_busy_ms_per_frame']:.2f} ms, host reads a frame {reads}", flush=True)
        for k, us in list(entry["kernels_us_per_frame"].items())[:15]:
            print(f"    device {us:8.1f} us  {k[:100]}")
        for k, us in list(host.items())[:15]:
            print(f"    host   {us:8.1f} us  {k[:100]}")
    write_json(args.out, "profile_inertial.json", record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
