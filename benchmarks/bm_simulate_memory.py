"""`hairwarp simulate`'s peak memory and time against the motion's length (issue 30, item 5).

The issue's scene, as a user has it: an SMPL-format body of 49 overlapping closed primitives
(`tools/primitive_body.py`), a `.data` groom of `--strands` strands made on another head
(`tools/foreign_scenes.py`: centimetres, 40-64 vertices a strand, bald-root markers), and an
AMASS-format motion of `--seconds` seconds at 120 fps (resampled to 60 fps by the loader). For
each of `--frames` it runs `hairwarp simulate` on them with the command's defaults (method auto),
each in a process of its own, and reads that process's peak resident memory (`os.wait4`'s
`ru_maxrss`), its wall time and the method's ms/frame from simulate_metrics.json.

    python benchmarks/bm_simulate_memory.py --out /tmp/mem --frames 20,60,180 --json docs/results/simulate_memory_cpu.json

`--label` names the run in the JSON (a run of another checkout: PYTHONPATH=<checkout>/src).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
TOOLS = os.path.join(HERE, os.pardir, "tools")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="hairwarp-out", help="folder for the scene's files and the commands' outputs")
    p.add_argument("--frames", default="20,60,180", help="motion lengths simulated, comma-separated")
    p.add_argument("--strands", type=int, default=600, help="strands of the groom (default 600, the issue's)")
    p.add_argument("--seconds", type=float, default=3.0, help="length of the AMASS motion written [s]")
    p.add_argument("--label", default="", help="what this run measures (e.g. 'before', 'after')")
    p.add_argument("--json", default=None, help="append this run's figures to this JSON file")
    p.add_argument("--extra", default="", help="more flags for `hairwarp simulate`, space-separated")
    return p


def scene_files(out: str, strands: int, seconds: float) -> dict:
    """Write (once) the body, the groom and the motion into `out`; their paths."""
    sys.path.insert(0, TOOLS)
    import foreign_scenes

    os.makedirs(out, exist_ok=True)
    paths = {"body": os.path.join(out, "body.npz"), "groom": os.path.join(out, "groom_cm.data"),
             "motion": os.path.join(out, "motion_amass.npz")}
    if not os.path.exists(paths["body"]):
        subprocess.run([sys.executable, os.path.join(TOOLS, "primitive_body.py"), "--out", paths["body"],
                        "--no-check"], check=True)
    if not os.path.exists(paths["groom"]):
        source = foreign_scenes.source_hairstyle("medium_wavy", 0, 1, "body")
        pick = np.linspace(0, source.shape[0] - 1, strands).round().astype(int)
        foreign_scenes.build_groom(out, 0, source=source[pick])
    if not os.path.exists(paths["motion"]):
        foreign_scenes.build_motion(out, 0, duration=seconds)
    return paths


def run_command(argv: list[str], log: str) -> dict:
    """Wall time [s] and peak resident memory [MB] of one command, a child process of its own."""
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    load = os.getloadavg()[0]  # other work on the machine slows the command: say how busy it was
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    return {"command": " ".join(argv), "returncode": os.waitstatus_to_exitcode(status), "wall_s": wall,
            "peak_rss_mb": usage.ru_maxrss / 1024.0, "cpu_s": usage.ru_utime + usage.ru_stime,
            "load_average_1min": [load, os.getloadavg()[0]]}


def main(argv=None) -> dict:
    args = _parser().parse_args(argv)
    from hairwarp.runtime import machine_description

    paths = scene_files(args.out, args.strands, args.seconds)
    runs = []
    for frames in [int(f) for f in args.frames.split(",")]:
        out = os.path.join(args.out, f"simulate_{frames}")
        cmd = [sys.executable, "-m", "hairwarp.cli", "simulate", "--body", paths["body"], "--hairstyle",
               paths["groom"], "--pose", paths["motion"], "--frames", str(frames), "--no-progress", "--out", out]
        cmd += args.extra.split()
        run = run_command(cmd, os.path.join(args.out, f"simulate_{frames}.log"))
        run["frames"] = frames
        metrics = os.path.join(out, "simulate_metrics.json")
        if run["returncode"] == 0 and os.path.exists(metrics):
            with open(metrics) as f:
                record = json.load(f)
            info = record.get("method_info", {})
            run.update(method=record["method"], ms_per_frame=record["ms_per_frame"], strands=record["strands"],
                       simulated_frames=record["frames"], chosen=info.get("chosen"),
                       fallback_frames=len(info.get("fallback_frames", [])),
                       penetration_percent=record["result"]["penetration_percent"],
                       rigid_penetration_percent=record["rigid"]["penetration_percent"])
            run["wall_s_per_frame"] = run["wall_s"] / record["frames"]
        print(f"{frames} frames: {run['wall_s']:.0f} s, peak {run['peak_rss_mb']:.0f} MB, "
              f"method {run.get('ms_per_frame', float('nan')):.0f} ms/frame (rc {run['returncode']})", flush=True)
        runs.append(run)
    record = {"label": args.label, "machine": machine_description("cpu"), "strands": args.strands,
              "files": paths, "runs": runs}
    if args.json:
        everything = []
        if os.path.exists(args.json):
            with open(args.json) as f:
                everything = json.load(f)
        everything.append(record)
        with open(args.json, "w") as f:
            json.dump(everything, f, indent=1)
    return record


if __name__ == "__main__":
    main()
