"""Pose hairwarp's default body and place the scalp's hair roots on it (Eq. 1).

    python examples/pose_body.py [--out ./hairwarp-out]

Writes `pose_body.png`: the rest body and a posed one (head turned and tilted, left arm
raised, right arm lowered), front and side views, with short root stubs (1 cm along the
scalp normal) rigidly placed on the head.
"""

from __future__ import annotations

import argparse
import os
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from hairwarp.scene.body import default_body  # noqa: E402
from hairwarp.scene.placement import rigid_placement  # noqa: E402
from hairwarp.scene.scalp import build_scalp  # noqa: E402

# Orthographic views: (screen x axis, screen y axis, towards the viewer), in world axes.
VIEWS = {
    "front": (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),
    "side": (np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])),
}


def draw_mesh(ax, vertices, faces, view, color=(0.85, 0.72, 0.6)):
    """Flat-shaded painter's-algorithm drawing of a triangle mesh."""
    sx, sy, towards = VIEWS[view]
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-20
    facing = normal @ towards
    order = np.argsort(tri.mean(1) @ towards)
    order = order[facing[order] > 0]
    shade = 0.3 + 0.7 * facing[order]
    polys = np.stack([tri[order] @ sx, tri[order] @ sy], -1)
    colors = np.array(color)[None] * shade[:, None]
    # Edges drawn in the face colour hide the anti-aliasing seams between triangles.
    ax.add_collection(PolyCollection(polys, facecolors=colors, edgecolors=colors, linewidths=0.3))


def draw_strands(ax, strands, view, color="#3a2410"):
    sx, sy, _ = VIEWS[view]
    for s in strands:
        ax.plot(s @ sx, s @ sy, color=color, lw=0.6)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="./hairwarp-out", help="output folder")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)

    t0 = time.perf_counter()
    body = default_body()
    t1 = time.perf_counter()
    scalp = build_scalp(body, resolution=32)
    t2 = time.perf_counter()
    print(f"default body: V={body.num_vertices} F={body.num_faces} loaded in {t1 - t0:.3f} s; "
          f"scalp of {scalp.num_roots} roots in {t2 - t1:.3f} s")

    # SMPL axis-angle poses [rad]: joint k's rotation is entries 3k..3k+2 (world axes at rest).
    poses = torch.zeros(2, 66)
    poses[1, 3 * 12:3 * 12 + 3] = torch.tensor([0.15, 0.25, 0.0])  # neck: nod and turn
    poses[1, 3 * 15:3 * 15 + 3] = torch.tensor([0.0, 0.45, 0.2])  # head: turn left, tilt
    poses[1, 3 * 16:3 * 16 + 3] = torch.tensor([0.0, 0.0, 1.1])  # left shoulder: arm up
    poses[1, 3 * 17:3 * 17 + 3] = torch.tensor([0.0, 0.0, 1.2])  # right shoulder: arm down
    poses[1, 3 * 19:3 * 19 + 3] = torch.tensor([0.0, 1.2, 0.0])  # right elbow: bend forward
    posed = body.pose(poses=poses)
    stubs = scalp.positions[:, None] + torch.tensor([0.0, 0.01])[None, :, None] * scalp.normals[:, None]
    hair = rigid_placement(stubs, posed, body, scalp)
    t3 = time.perf_counter()
    print(f"posed {posed.batch_size} frames and placed the roots in {t3 - t2:.3f} s; "
          f"largest root offset dt_s0 {hair.root_offsets.norm(dim=-1).max() * 1000:.3f} mm")

    faces = body.faces.long().numpy()
    fig, axes = plt.subplots(2, 2, figsize=(10, 10))
    for row, title in enumerate(["rest pose", "head turned, arms moved"]):
        v = posed.vertices[row].numpy()
        for col, view in enumerate(["front", "side"]):
            ax = axes[row, col]
            draw_mesh(ax, v, faces, view)
            draw_strands(ax, hair.positions[row, ::3].numpy(), view)
            ax.set_aspect("equal")
            ax.autoscale_view()
            ax.set_title(f"{title} ({view})")
            ax.set_xlabel("m")
    fig.tight_layout()
    path = os.path.join(args.out, "pose_body.png")
    fig.savefig(path, dpi=90)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
