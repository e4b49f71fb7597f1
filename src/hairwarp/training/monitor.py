"""Learning curves of the static trainer: what the loss terms ask of the drape, and held-out scores.

Every `curve_every` steps (and at step 0 and at the end of the schedule) the trainer records,
into `<out>/learning_curve.json` (and a figure `<out>/learning_curve.png`):

- on the step's training batch: the gradient norm of each energy term with respect to the
  predicted deformation map D (`|dE_term/dD|` of the batch-mean loss, the quantity the network
  is trained to follow), the cosine of each term's gradient with the total's, the mean vertex
  displacement from the rigid placement by vertex index (mm), and the share of vertices inside
  the body before (rigid) and after (network) the drape: how deep the training starts are;
- on held-out comparison scenes (`hairwarp.evaluation.scenes`, never drawn by the sampler;
  the layers keep training below evaluation, so the caller hands the trainer the scene
  factory, `comparison_scene`, as `scene_factory`):
  penetration %, length change %, total static energy and, when a reference energy E* was
  computed at setup (`curve_reference_iterations` L-BFGS iterations over the free vertices
  from the rigid placement), the energy gap (E - E*) / (E0 - E*) (1: the rigid placement, 0: the
  reference), the energy ratio E / E*, the mean / p95 distance to the reference's drape and how
  much higher the tips hang than its tips [mm] (`hairwarp.metrics.static_fidelity`), plus the
  displacement by vertex index.

The record is a pure function of the weights and the step's batch, so a resumed run writes the
same entries as an uninterrupted one (the file is read back on resume and entries past the
resumed step are dropped).
"""

from __future__ import annotations

import json
import os
import time

import torch

from hairwarp.config import ALL_TERMS
from hairwarp.energy import total_energy
from hairwarp.models import apply_deformation, length_projection_of
from hairwarp.models.contact_features import network_deformation

CURVE_NAME = "learning_curve.json"
CURVE_FIGURE = "learning_curve.png"
# Terms the static loss never holds.
_STATIC_SKIP = ("inertia",)


def _terms(energy) -> list[str]:
    weights = energy.weights()
    return [t for t in ALL_TERMS if t not in _STATIC_SKIP and weights.get(t, 0.0) != 0.0]


def term_gradients(deformation: torch.Tensor, rigid: torch.Tensor, root_uv: torch.Tensor, inputs, energy,
                   length_projection: str = "none") -> dict:
    """Gradient norms of each term of the batch-mean static energy with respect to the map D.

    Args:
        deformation: (B, H, W, N, 3) the predicted map (detached here).
        rigid, root_uv, inputs: the batch's rigid placement, root UVs and energy inputs.
        energy: the `EnergyConfig` of the step (its b_p).
        length_projection: the network's (`length_projection_of`).

    Returns:
        {"norm": {term: |dE/dD|}, "cosine_with_total": {term: cos}, "total_norm": float,
        "norm_by_vertex": {term: [N floats]}: the gradient norm per vertex index, summed over
        cells and batch}.
    """
    d = deformation.detach().clone().requires_grad_(True)
    grads = {}
    for term in _terms(energy):
        x = apply_deformation(rigid, d, root_uv, length_projection)
        value = total_energy(x, inputs, energy, terms=(term,)).total.mean()
        (g,) = torch.autograd.grad(value, d, allow_unused=True)
        grads[term] = torch.zeros_like(d) if g is None else g.detach()
    total = sum(grads.values())
    tn = float(total.norm())
    out = {"norm": {}, "cosine_with_total": {}, "total_norm": tn, "norm_by_vertex": {}}
    for term, g in grads.items():
        n = float(g.norm())
        out["norm"][term] = n
        out["cosine_with_total"][term] = float((g * total).sum()) / max(n * tn, 1e-30)
        out["norm_by_vertex"][term] = g.norm(dim=-1).pow(2).sum(dim=(0, 1, 2)).sqrt().tolist()
    return out


def displacement_by_vertex(x: torch.Tensor, rigid: torch.Tensor) -> list[float]:
    """Mean |x - rigid| [mm] by vertex index, over batch and strands."""
    return ((x - rigid).norm(dim=-1).mean(dim=(0, 1)) * 1e3).tolist()


class HeldOutScenes:
    """Comparison scenes prepared once for a network's evaluation during training.

    Args:
        names: scene names (`hairwarp.evaluation.scenes.SCENE_NAMES`, static scenes).
        factory: `hairwarp.evaluation.scenes.comparison_scene` (or one like it:
            factory(name, strand_stride=..., num_vertices=...) -> a comparison scene).
        num_vertices: N of the network (the scenes are resampled to it).
        strand_stride: None for full size, else one scalp root in k (`root_subset`).
        energy: the `EnergyConfig` the scores use (b_p of the run's end).
        reference_iterations: L-BFGS iterations over the free vertices for E* (0: no energy gap).
        grid: (H, W) of the network's deformation map (unused by the vertex reference).
        device, dtype: where the network runs.
    """

    def __init__(self, names, factory, num_vertices: int, strand_stride, energy, reference_iterations: int, grid,
                 device, dtype):
        from hairwarp.scene.hair_latent import HairLatentBasis

        self.energy = energy
        self.scenes = []
        basis = HairLatentBasis.load_default()
        start = time.perf_counter()
        for name in names:
            scene = factory(name, strand_stride=strand_stride, num_vertices=num_vertices)
            if scene.is_motion:
                raise ValueError(f"curve_scenes: {name} is a motion scene; the learning curve scores static scenes")
            frames = scene.frames(device=device, dtype=dtype)
            style = scene.scene.hairstyle
            z = basis.encode(style.strands.double(), style.root_uv.double()).reshape(1, -1)
            b = frames.rigid.positions.shape[0]
            item = {
                "name": name, "size": dict(scene.size), "frames": frames,
                "z": z.to(device=device, dtype=dtype).expand(b, -1),
                "betas": frames.betas.to(dtype), "poses": frames.poses.to(dtype),
                "root_uv": style.root_uv.to(device=device, dtype=dtype),
            }
            rigid = frames.rigid.positions
            item["rigid_scores"] = self._scores(rigid, item, None)
            item["reference_energy"] = None
            if reference_iterations > 0:
                item["reference_energy"], item["reference_scores"] = self._reference(item, reference_iterations, grid)
            self.scenes.append(item)
        self.setup_s = time.perf_counter() - start

    def _scores(self, x, item, reference_energy) -> dict:
        from hairwarp.metrics import length_change_percent, penetration_percent, static_fidelity

        frames = item["frames"]
        with torch.no_grad():
            energy = total_energy(x, frames.inputs, self.energy).total
            out = {
                "penetration_percent": float(penetration_percent(x, frames.body_mesh).mean()),
                "length_change_percent": float(length_change_percent(x, frames.inputs.rest_lengths).mean()),
                "energy": float(energy.mean()),
            }
            e0 = item.get("rigid_energy")
            if reference_energy is not None and e0 is not None:
                gap = (energy - reference_energy) / (e0 - reference_energy).abs().clamp_min(1e-30)
                out["energy_gap"] = float(gap.mean())
            optimum = item.get("reference_positions")
            if optimum is not None and reference_energy is not None:
                # The shape against the reference drape (`hairwarp.metrics.static_fidelity`): E / E*,
                # the distance to it and how much higher the tips hang [mm].
                out.update(static_fidelity(x, optimum, energy.sum(), reference_energy.sum()))
            if "rigid_energy" not in item:
                item["rigid_energy"] = energy.detach()
        return out

    def _reference(self, item, iterations: int, grid):
        """E* per frame: the L-BFGS baseline over the free vertices from the rigid placement
        (`hairwarp.solvers.direct.optimize_drape`, the harness's L-BFGS). torch's own L-BFGS over
        the free map stalls at the rigid placement on table1 (docs/training_diagnosis.md), which
        made the gap read as zero. `grid` is kept for the signature; the vertices need none.
        """
        from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

        frames = item["frames"]
        rigid = frames.rigid.positions
        solver = DirectOptimizationConfig(method="lbfgs", max_iterations=iterations, patience=50)
        x = optimize_drape(rigid, frames.inputs, self.energy, solver).positions
        with torch.no_grad():
            e = total_energy(x, frames.inputs, self.energy).total.detach()
        item["reference_positions"] = x.detach()
        return e, self._scores(x, item, e)

    def evaluate(self, model, clip=None) -> dict:
        """Scores of `model`'s drapes on every scene: {name: {penetration_percent, ...}}."""
        was_training = model.training
        model.eval()
        out = {}
        try:
            with torch.no_grad():
                for item in self.scenes:
                    rigid = item["frames"].rigid.positions
                    dmap = network_deformation(model, item["z"], item["betas"], item["poses"], rigid,
                                               item["root_uv"], item["frames"].inputs.body, clip)
                    x = apply_deformation(rigid, dmap, item["root_uv"], length_projection_of(model))
                    scores = self._scores(x, item, item["reference_energy"])
                    scores["displacement_by_vertex_mm"] = displacement_by_vertex(x, rigid)
                    out[item["name"]] = scores
        finally:
            model.train(was_training)
        return out

    def describe(self) -> dict:
        """Per scene: size, rigid scores and the reference's (when computed)."""
        return {item["name"]: {"size": item["size"], "rigid": item["rigid_scores"],
                               "reference": item.get("reference_scores")} for item in self.scenes}


class LearningCurve:
    """The learning-curve record of a static trainer (see the module docstring).

    Args:
        trainer: the `StaticTrainer` (its config's `curve_*` fields set what is recorded).
        scene_factory: builds the held-out scenes (`hairwarp.evaluation.scenes.comparison_scene`);
            None records the training-batch figures only.
    """

    def __init__(self, trainer, scene_factory=None):
        cfg = trainer.config
        self.trainer = trainer
        self.scene_factory = scene_factory
        self.every = int(cfg.curve_every)
        self.entries: list[dict] = []
        self._scenes = None
        self.path = None if trainer.out is None else os.path.join(trainer.out, CURVE_NAME)
        if self.path is not None and os.path.isfile(self.path) and trainer.step > 0:
            with open(self.path, encoding="utf-8") as f:
                old = json.load(f)
            self.entries = [e for e in old.get("entries", []) if e["step"] <= trainer.step]

    @property
    def enabled(self) -> bool:
        return self.every > 0

    def due(self, step: int) -> bool:
        """Whether the state after `step` completed steps is recorded."""
        if not self.enabled:
            return False
        if any(e["step"] == step for e in self.entries):
            return False
        return step % self.every == 0 or step == self.trainer.total_steps

    def scenes(self) -> HeldOutScenes:
        if self._scenes is None:
            from hairwarp.training.config import energy_config

            cfg = self.trainer.config
            tr = self.trainer
            energy = energy_config(cfg.energy, barrier_join_fraction=cfg.bp_end)
            net = tr.model.config
            self._scenes = HeldOutScenes(cfg.curve_scenes, self.scene_factory, cfg.data.num_vertices,
                                         cfg.curve_strand_stride, energy, cfg.curve_reference_iterations,
                                         (net.grid_height, net.grid_width), tr.device, tr.dtype)
        return self._scenes

    def record(self, step: int) -> dict:
        """Record the state after `step` completed steps (on the batch of step `step`)."""
        from hairwarp.metrics import penetration_percent
        from hairwarp.training.config import energy_config

        tr = self.trainer
        start = time.perf_counter()
        sched_step = min(step, tr.total_steps - 1)
        s = tr.schedule(sched_step)
        batch = tr.next_batch(sched_step)
        energy = energy_config(tr.config.energy, barrier_join_fraction=s["bp"])
        model = tr.model
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad():
                dmap = network_deformation(model, batch.z, batch.betas, batch.poses, batch.rigid, batch.root_uv,
                                           batch.inputs.body, s["clip"])
                x = apply_deformation(batch.rigid, dmap, batch.root_uv, length_projection_of(model))
                loss = total_energy(x, batch.inputs, energy)
        finally:
            model.train(was_training)
        grads = term_gradients(dmap, batch.rigid, batch.root_uv, batch.inputs, energy, length_projection_of(model))
        train = {
            "bp": s["bp"], "phase": s["phase"], "loss": float(loss.total.mean()),
            "terms": {k: float(v.mean()) for k, v in loss.terms.items()},
            "gradient": grads,
            "displacement_by_vertex_mm": displacement_by_vertex(x, batch.rigid),
            "map_abs_max_m": float(dmap.abs().max()),
        }
        if batch.inputs.body is not None:
            with torch.no_grad():
                train["rigid_penetration_percent"] = penetration_percent(batch.rigid, batch.inputs.body).tolist()
                train["penetration_percent"] = penetration_percent(x, batch.inputs.body).tolist()
        entry = {"step": step, "train": train}
        if self.trainer.config.curve_scenes and self.scene_factory is not None:
            entry["held_out"] = self.scenes().evaluate(model, clip=s["clip"])
        entry["record_s"] = time.perf_counter() - start
        self.entries = [e for e in self.entries if e["step"] != step] + [entry]
        self.entries.sort(key=lambda e: e["step"])
        return entry

    def to_dict(self) -> dict:
        cfg = self.trainer.config
        out = {"kind": self.trainer.kind, "curve_every": self.every, "config": cfg.to_dict(),
               "entries": self.entries}
        if self._scenes is not None:
            out["scenes"] = self._scenes.describe()
        elif self.path is not None and os.path.isfile(self.path):
            with open(self.path, encoding="utf-8") as f:
                old = json.load(f)
            if "scenes" in old:
                out["scenes"] = old["scenes"]
        return out

    def write(self) -> None:
        """Write the JSON record and its figure (rank 0 with an output folder only)."""
        if self.path is None or not self.trainer.is_main or not self.enabled:
            return
        data = self.to_dict()
        tmp = self.path + ".tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f)
        os.replace(tmp, self.path)
        try:
            plot_curve(data, os.path.join(self.trainer.out, CURVE_FIGURE))
        except ImportError:  # matplotlib is optional
            pass


def plot_curve(data: dict, path: str) -> None:
    """The figure of a learning-curve record: held-out scores, gradient norms, displacements."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    entries = data["entries"]
    if not entries:
        return
    steps = [e["step"] for e in entries]
    fig = Figure(figsize=(16, 8))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 3).ravel()
    scenes = data.get("scenes", {})
    names = list(entries[-1].get("held_out", {}))
    for i, name in enumerate(names):
        c = f"C{i}"
        vals = [e["held_out"][name] for e in entries if name in e.get("held_out", {})]
        st = [e["step"] for e in entries if name in e.get("held_out", {})]
        ax[0].plot(st, [v["penetration_percent"] for v in vals], c, label=name)
        ax[1].plot(st, [v["length_change_percent"] for v in vals], c, label=name)
        ratio = "energy_ratio" in vals[-1]
        if ratio or "energy_gap" in vals[-1]:
            key = "energy_ratio" if ratio else "energy_gap"
            ax[2].plot(st, [v.get(key, float("nan")) for v in vals], c, label=name)
        info = scenes.get(name, {})
        if info.get("rigid"):
            ax[0].axhline(info["rigid"]["penetration_percent"], color=c, ls="--", lw=0.8)
        if info.get("reference"):
            ax[0].axhline(info["reference"]["penetration_percent"], color=c, ls=":", lw=0.8)
        ax[5].plot(vals[-1]["displacement_by_vertex_mm"], c, label=f"{name} (held out)")
    ax[0].set(xlabel="step", ylabel="penetration [%]", title="held out (--: rigid, : L-BFGS map)")
    ax[1].set(xlabel="step", ylabel="length change [%]", title="held out")
    with_ratio = any("energy_ratio" in v for v in entries[-1].get("held_out", {}).values())
    ax[2].set(xlabel="step", ylabel="E / E*" if with_ratio else "energy gap",
              title="held out: E / E* (the reference drape's)" if with_ratio else "held out: (E - E*) / (E0 - E*)")
    if with_ratio:  # an untrained network starts tens of times above E*: the trained end needs a log scale
        ax[2].set_yscale("log")
    for term in entries[-1]["train"]["gradient"]["norm"]:
        ax[3].semilogy(steps, [max(e["train"]["gradient"]["norm"].get(term, 0.0), 1e-12) for e in entries],
                       label=term)
    ax[3].set(xlabel="step", ylabel="|dE_term / dD|", title="training batch: gradient w.r.t. the map")
    rigid_pen = [sum(e["train"].get("rigid_penetration_percent", [0])) /
                 max(len(e["train"].get("rigid_penetration_percent", [0])), 1) for e in entries]
    net_pen = [sum(e["train"].get("penetration_percent", [0])) /
               max(len(e["train"].get("penetration_percent", [0])), 1) for e in entries]
    ax[4].plot(steps, rigid_pen, "k--", label="batch: rigid")
    ax[4].plot(steps, net_pen, "k-", label="batch: network")
    ax4b = ax[4].twinx()
    ax4b.semilogy(steps, [e["train"]["bp"] for e in entries], "C3", label="b_p")
    ax[4].set(xlabel="step", ylabel="training batch penetration [%]", title="training batch (b_p in red)")
    ax[5].plot(entries[-1]["train"]["displacement_by_vertex_mm"], "k", label="training batch")
    ax[5].set(xlabel="vertex index", ylabel="mean |x - rigid| [mm]", title=f"at step {steps[-1]}")
    for a in ax:
        a.grid(alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.suptitle(f"learning curve ({data.get('kind', '')})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


__all__ = ["CURVE_FIGURE", "CURVE_NAME", "HeldOutScenes", "LearningCurve", "displacement_by_vertex",
           "plot_curve", "term_gradients"]
