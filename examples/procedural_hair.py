"""Grow three preset hairstyles on a synthetic scalp and draw them from the side and the front.

    python examples/procedural_hair.py --out ./hairwarp-out

Writes `procedural_hair.png` into the output folder. The head proxy (the ellipsoid fitted to the
scalp, which the strands must stay outside) is drawn in grey.
"""

from __future__ import annotations

import argparse
import os
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hairwarp.scene.hairstyles import fit_head_ellipsoid, generate_hairstyle, sphere_cap_scalp  # noqa: E402


def draw(ax, strands, head, view, title, every=2):
    """Strands behind the head, then the head proxy, then the strands in front of it."""
    # view "side": seen from +x, z to the right (the face looks right); "front": seen from +z.
    a, depth = (2, 0) if view == "side" else (0, 2)
    t = np.linspace(0, 2 * np.pi, 200)
    mean_depth = strands[:, :, depth].mean(axis=1)
    order = np.argsort(mean_depth)
    behind = mean_depth[order] < head.centre[depth]
    for k, s in enumerate(strands[order]):
        if k % every == 0:
            ax.plot(s[:, a], s[:, 1], lw=0.4, color="saddlebrown" if behind[k] else "peru", alpha=0.7,
                    zorder=1 if behind[k] else 3)
    ax.fill(head.centre[a] + head.radii[a] * np.cos(t), head.centre[1] + head.radii[1] * np.sin(t),
            color="0.8", zorder=2)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.set_xlim(head.centre[a] - 0.3, head.centre[a] + 0.3)
    ax.set_ylim(head.centre[1] - 0.65, head.centre[1] + 0.2)


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="./hairwarp-out")
    parser.add_argument("--presets", nargs="+", default=["short_straight", "long_curly", "bangs"])
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    scalp = sphere_cap_scalp()
    head = fit_head_ellipsoid(scalp)
    fig, axes = plt.subplots(2, len(args.presets), figsize=(4 * len(args.presets), 9))
    for col, name in enumerate(args.presets):
        start = time.perf_counter()
        style = generate_hairstyle(scalp, name)
        ms = 1000 * (time.perf_counter() - start)
        s = style.strands.numpy()
        print(f"{name}: {style.num_strands} strands, {len(style.filtered)} filtered, {ms:.0f} ms")
        draw(axes[0, col], s, head, "side", f"{name} (side, face +z right)")
        draw(axes[1, col], s, head, "front", f"{name} (front)")
    fig.tight_layout()
    path = os.path.join(args.out, "procedural_hair.png")
    fig.savefig(path, dpi=110)
    print("wrote", path)


if __name__ == "__main__":
    main()
