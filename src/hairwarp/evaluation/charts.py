"""The speed-versus-accuracy chart (PNG) from a harness results record.

One row of panels per static scene: time per drape [ms] on a log x axis against penetration %
(left) and against the energy gap (E - E*) / (E0 - E*) on a log y axis (right). Optimizers
(Adam, L-BFGS, the converged reference) are curves over their iterations, drawn from their
history (penetration where it was recorded, every `record_every` iterations; the energy gap at
every iteration); one-shot methods (the networks) are points; the rigid placement, which
costs nothing, is a dashed horizontal line; a network finished by L-BFGS ("static+refine")
is a curve in its network's colour that starts at the network's time. The device is named in
the title.
"""

from __future__ import annotations

import os

# Energy gaps below this are drawn on it (log axis; the optimum itself has gap 0).
GAP_FLOOR = 1e-6

_STYLE = {"rigid": ("0.4", "--"), "adam": ("tab:orange", "-"), "lbfgs": ("tab:blue", "-"),
          "reference": ("tab:green", "-"), "static": ("tab:red", None), "dynamic": ("tab:purple", None),
          "quaffure": ("tab:brown", None)}


def _color(name: str, index: int) -> str:
    if name in _STYLE:
        return _STYLE[name][0]
    base = name.split("+")[0]
    if base in _STYLE:  # a composed method ("static+refine") in its network's colour
        return _STYLE[base][0]
    return f"C{index % 10}"


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
