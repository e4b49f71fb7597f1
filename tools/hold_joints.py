"""Set the joints a checkpoint's static network does not read from Theta (`StaticConfig.held_joints`).

The weights are kept as they are; only the config changes. "limbs" (arms from the collars down and
legs from the hips down) is the shipped setting since the twenty-eighth session
(docs/network_diagnosis.md, T21); "none" reads every joint, as the paper's network does.

    python tools/hold_joints.py src/hairwarp/assets/hairformer_dynamic.pt --joints limbs --out OUT.pt
    python tools/hold_joints.py OUT.pt --joints none --out PAPER_INPUTS.pt
    python tools/hold_joints.py IN.pt --joints left_shoulder,right_shoulder --out OUT.pt
"""

from __future__ import annotations

import argparse
import sys

import torch

ARMS = ("left_collar", "right_collar", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
        "left_wrist", "right_wrist")
LEGS = ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_foot", "right_foot")
NAMED = {"none": (), "arms": ARMS, "legs": LEGS, "limbs": ARMS + LEGS}


def main(argv=None) -> int:
    from hairwarp.models.config import StaticConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a static or dynamic checkpoint")
    p.add_argument("--joints", required=True, help=f"one of {', '.join(NAMED)}, or comma-separated joint names")
    p.add_argument("--out", required=True, help="where to write the checkpoint")
    args = p.parse_args(argv)
    joints = NAMED.get(args.joints, tuple(j for j in args.joints.split(",") if j))
    payload = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    config = payload["config"]["static"] if payload.get("kind") == "dynamic" else payload["config"]
    config["held_joints"] = list(joints)
    StaticConfig.from_dict(config)  # a bad name fails here, naming the field
    torch.save(payload, args.out)
    print(f"{args.out}: {payload.get('kind')} checkpoint, held joints {list(joints) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
