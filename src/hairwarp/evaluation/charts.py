"""The speed-versus-accuracy chart (PNG) from a harness results record, and the swing plot.

One row of panels per static scene: time per drape [ms] on a log x axis against penetration %
(left) and against the energy gap (E - E*) / (E0 - E*) on a log y axis (right). Optimizers
(Adam, L-BFGS, the converged reference) are curves over their iterations, drawn from their
history (penetration where it was recorded, every `record_every` iterations; the energy gap at
every iteration); one-shot methods (the networks) are points; the rigid placement, which
costs nothing, is a dashed horizontal line; a network finished by L-BFGS ("static+refine")
is a curve in its network's colour that starts at the network's time. The device is named in
the title.

The swing plot (`swing_plot`) draws each method's mean tip offset from the rigid placement over
a motion against the physics simulation's (DESIGN.md, "What good means").
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    import torch

# Energy gaps below this are drawn on it (log axis; the optimum itself has gap 0).
GAP_FLOOR = 1e-6

_STYLE = {"rigid": ("0.4", "--"), "adam": ("tab:orange", "-"), "lbfgs": ("tab:blue", "-"),
          "reference": ("tab:green", "-"), "static": ("tab:red", None), "dynamic": ("tab:purple", None),
          "quaffure": ("tab:brown", None), "inertial": ("tab:cyan", None)}


# Colours of methods without a style of their own: none of the styled methods' colours.
_OTHER_COLORS = ("tab:olive", "tab:pink", "navy", "teal", "gold", "tab:gray")


def _color(name: str, index: int) -> str:
    if name in _STYLE:
        return _STYLE[name][0]
    base = name.split("+")[0]
    if base in _STYLE:  # a composed method ("static+refine") in its network's colour
        return _STYLE[base][0]
    return _OTHER_COLORS[index % len(_OTHER_COLORS)]


def speed_accuracy_chart(record: dict, path: str, *, scenes: list[str] | None = None) -> str:
    """Draw the chart of `record` (from `run_comparison`) into `path` (PNG).

    Args:
        record: the harness results.
        path: output file (.png).
        scenes: static scenes to draw (default: every static scene of the record).

    Returns:
        The path written.

    Raises:
        ValueError: `path` not ending in .png, or `scenes` naming no static scene of the record.
    """
    # An Agg canvas of our own: the caller's pyplot state and backend stay as they are.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not str(path).lower().endswith(".png"):
        raise ValueError(f"path: expected a .png file, got {path!r}")
    static = [e for e in record["scenes"] if e["kind"] == "static"]
    if scenes is not None:
        static = [e for e in static if e["name"] in scenes]
    if not static:
        raise ValueError("scenes: the record holds no static scene to chart")
    fig = Figure(figsize=(12, 3.6 * len(static)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(static), 2, squeeze=False)
    for row, entry in enumerate(static):
        ax_pen, ax_gap = axes[row]
        size = entry["size"]
        for i, r in enumerate(entry["results"]):
            name, color = r["method"], _color(r["method"], i)
            if r["time_ms"] is None:  # the rigid placement: no cost, a reference level
                if r["penetration_percent"] is not None:
                    ax_pen.axhline(r["penetration_percent"], color=color, ls="--", lw=1, label=f"{name} (no cost)")
                if r.get("energy_gap") is not None:
                    ax_gap.axhline(max(r["energy_gap"], GAP_FLOOR), color=color, ls="--", lw=1, label=f"{name} (no cost)")
                continue
            history = r.get("history") or []
            batch = r.get("batch", 1)
            if history:
                # The start (time 0) has no place on a log axis: the rigid line stands for it.
                t = [h["time_s"] * 1e3 / batch for h in history]
                pen = [(tt, h["penetration"]) for tt, h in zip(t, history) if "penetration" in h and tt > 0]
                gap = [(tt, max(h["energy_gap"], GAP_FLOOR)) for tt, h in zip(t, history)
                       if h.get("energy_gap") is not None and tt > 0]
                if pen:
                    ax_pen.plot(*zip(*pen), color=color, lw=1.5, label=name)
                if gap:
                    ax_gap.plot(*zip(*gap), color=color, lw=1.5, label=name)
                # The returned drape (the best iterate) as a marker at the run's total time.
                ax_pen.plot([r["time_ms"]], [r["penetration_percent"]], "o", color=color, ms=5)
                if r.get("energy_gap") is not None:
                    ax_gap.plot([r["time_ms"]], [max(r["energy_gap"], GAP_FLOOR)], "o", color=color, ms=5)
            else:
                ax_pen.plot([r["time_ms"]], [r["penetration_percent"]], "D", color=color, ms=8, label=name)
                if r.get("energy_gap") is not None:
                    ax_gap.plot([r["time_ms"]], [max(r["energy_gap"], GAP_FLOOR)], "D", color=color, ms=8, label=name)
        title = f"{entry['name']} ({size['strands']}x{size['vertices']}, {size['frames']} drape(s))"
        ax_pen.set_title(title, fontsize=10)
        ax_gap.set_title(title, fontsize=10)
        for ax in (ax_pen, ax_gap):
            ax.set_xscale("log")
            ax.set_xlabel("time per drape [ms] (log)")
            ax.grid(True, which="both", alpha=0.3)
        ax_pen.set_ylabel("penetration [%]")
        ax_gap.set_yscale("log")
        ax_gap.set_ylabel(f"energy gap (E-E*)/(E0-E*) (floor {GAP_FLOOR:g})")
        ax_pen.legend(fontsize=8, loc="best")
        if ax_gap.get_legend_handles_labels()[0]:
            ax_gap.legend(fontsize=8, loc="best")
        else:  # no energy gap without the optimum E*: say how to get one rather than draw an empty panel
            ax_gap.text(0.5, 0.5, "no energy gap: add 'reference' to --methods\n(it computes the optimum E*)",
                        transform=ax_gap.transAxes, ha="center", va="center", fontsize=10, color="0.4")
    machine = record["machine"]
    fig.suptitle(f"Speed versus accuracy on {machine['device_name']} (scenes v{record['scenes_version']})", fontsize=12)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def swing_plot(curves: dict[str, torch.Tensor | np.ndarray], path: str, *, fps: float, physics: str = "physics",
               title: str | None = None) -> str:
    """Draw the methods' mean tip offsets over a motion: x, y and z stacked, in mm against time.

    Args:
        curves: method name -> (T, 3) mean tip offset from the rigid placement [m] (torch tensor
            or numpy array, from `hairwarp.metrics.mean_tip_offset`), all of the same T.
        path: output file (.png).
        fps: frames per second of the motion [1/s] (frame t is drawn at t / fps seconds).
        physics: the name of the physics curve, drawn black and thicker (when present).
        title: figure title (default: a description of the plot).

    Returns:
        The path written.

    Raises:
        ValueError: `curves` empty, a curve not (T, 3), curves of different lengths or not
            finite; `fps` not positive; `path` not ending in .png.
    """
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from hairwarp._validate import check_positive

    if not str(path).lower().endswith(".png"):
        raise ValueError(f"path: expected a .png file, got {path!r}")
    fps = check_positive("fps", fps)
    if not curves:
        raise ValueError("curves: expected at least one curve, got none")
    arrays, length = {}, None
    for name, c in curves.items():
        a = c.detach().cpu().double().numpy() if hasattr(c, "detach") else np.asarray(c, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise ValueError(f"curves[{name!r}]: expected shape (T, 3) with T > 0, got {a.shape}")
        if length is not None and a.shape[0] != length:
            raise ValueError(f"curves[{name!r}]: expected {length} frames like the curves before it, got {a.shape[0]}")
        if not np.isfinite(a).all():
            raise ValueError(f"curves[{name!r}]: contains NaN or Inf")
        arrays[name], length = a * 1e3, a.shape[0]
    t = np.arange(length) / fps
    fig = Figure(figsize=(10, 7.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    for i, (name, a) in enumerate(arrays.items()):
        is_physics = name == physics
        for k, ax in enumerate(axes):
            ax.plot(t, a[:, k], color="black" if is_physics else _color(name, i), lw=2.5 if is_physics else 1.3,
                    ls=_STYLE.get(name, (None, None))[1] or "-", zorder=3 if is_physics else 2,
                    label=name if k == 0 else None)
    for ax, axis in zip(axes, "xyz"):
        ax.set_ylabel(f"{axis} offset [mm]")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(title or "Mean tip offset from the rigid placement", fontsize=12)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
