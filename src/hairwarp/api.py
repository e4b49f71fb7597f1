"""The small public face: drape or simulate a scene with any method by name.

import hairwarp as hw
scene = hw.default_scene("bob", strand_stride=8)
r = hw.drape(scene, method="lbfgs", max_iterations=50)
r.positions                      # (M, N, 3) [m]
r.metrics["penetration_percent"], r.metrics["length_change_percent"]
hw.simulate(hw.default_scene("bob", "head_turn"), method="dynamic").positions   # (T, M, N, 3)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from hairwarp.methods import MethodOptions, make
from hairwarp.runtime import resolve_device


@dataclass
class Result:
    """What `drape` and `simulate` return.

    Attributes:
        positions: (M, N, 3) for a drape, (T, M, N, 3) for a simulation: hair positions [m].
        metrics: Table 1's figures of the result: "penetration_percent" (share of the moving
            vertices inside the body) and "length_change_percent" (mean |l / l0 - 1|), each the
            mean over frames, with "per_frame" lists and the rigid placement's figures under
            "rigid" for comparison.
        time_ms: the method's wall time per frame [ms] (None for the rigid placement).
        method: the method's name; info: its facts (iterations, stop reason, ...).
        frames: the scene frames the method ran on (posed bodies, rigid placement, energy
            inputs): what export and pictures need.
        guide_positions: for a scene simulated through guides (`Scene.guides`), the guides the
            method ran on, (K, N, 3) or (T, K, N, 3) [m]; `positions` then holds every strand
            of the groom, `metrics` are over all strands and `metrics["guides"]` over the
            guides. None otherwise.
    """

    positions: torch.Tensor
    metrics: dict
    time_ms: float | None
    method: str
    info: dict = field(default_factory=dict)
    frames: object = None
    guide_positions: torch.Tensor | None = None

    def write_usd(self, path: str) -> str:
        """Write the hair (and the posed body) as USD (.usda text or .usd/.usdc binary); returns the path."""
        from hairwarp.io.usd import write_usd

        from hairwarp.scene.guides import GUIDE_WIDTH, strand_width

        frames = self.frames
        fps = float(frames.scene.motion.fps)
        guides = frames.scene.guides
        width = GUIDE_WIDTH if guides is None else strand_width(guides.num_strands, guides.num_guides)
        return write_usd(path, self.positions.detach().cpu(), frames.posed.vertices.detach().cpu().squeeze(0),
                         frames.scene.body.faces.cpu(), fps=fps, widths=width)


def _options(method_options: MethodOptions | None, **changes) -> MethodOptions:
    from dataclasses import fields, replace

    options = method_options or MethodOptions()
    known = {f.name for f in fields(MethodOptions)}
    unknown = sorted(set(changes) - known)
    if unknown:
        raise ValueError(f"{unknown[0]}: not an option of the methods; expected one of {sorted(known)}")
    return replace(options, **{k: v for k, v in changes.items() if v is not None})


def _summary(per_frame: dict, rigid: dict) -> dict:
    def mean(values):
        return float(sum(values) / len(values))

    return {"penetration_percent": mean(per_frame["penetration_percent"]),
            "length_change_percent": mean(per_frame["length_change_percent"]),
            "per_frame": per_frame,
            "rigid": {"penetration_percent": mean(rigid["penetration_percent"]),
                      "length_change_percent": mean(rigid["length_change_percent"]), "per_frame": rigid}}


def _against(frames, out, reference: str, options: MethodOptions, *, simulate: bool) -> dict:
    """The fidelity metrics of `out` against `reference` run on the same frames."""
    from hairwarp import metrics as M

    ref = make(reference, options)
    truth = ref.simulate(frames) if simulate else ref.drape(frames)
    if simulate:
        found = M.motion_fidelity(out.positions, truth.positions, frames.rigid.positions)
    else:
        found = M.drape_fidelity(out.positions, truth.positions, frames.inputs, options.config())
    return {"reference": ref.name, "reference_time_ms": truth.time_ms, **found}


def _run(scene, frames, method: str, options: MethodOptions, *, simulate: bool, reference: str | None = None) -> Result:
    from hairwarp.metrics import frame_metrics_of

    m = make(method, options)
    out = m.simulate(frames) if simulate else m.drape(frames)
    scored = frame_metrics_of({"method": out.positions, "rigid": frames.rigid.positions}, frames)
    (per_frame, sd), (rigid, rigid_sd) = scored["method"], scored["rigid"]
    metrics = _summary(per_frame, rigid)
    positions, guides = out.positions, None
    if scene.guides is not None:
        from hairwarp.metrics import groom_metrics

        groom = groom_metrics(frames, out.positions, sd)
        groom_rigid = groom_metrics(frames, frames.rigid.positions, rigid_sd, body_pass=False)
        metrics = {**_summary(groom["per_frame"], groom_rigid["per_frame"]), "guides": metrics,
                   "body_pass": groom["body_pass"]}
        positions, guides = groom["positions"], out.positions
    if reference is not None:
        metrics["against_reference"] = _against(frames, out, reference, options, simulate=simulate)
    if not simulate:
        positions, guides = positions[0], None if guides is None else guides[0]
    return Result(positions=positions, metrics=metrics, time_ms=out.time_ms, method=m.name,
                  info=dict(out.info), frames=frames, guide_positions=guides)


def drape(scene, method: str = "auto", *, frame: int = 0, device: str | torch.device = "cpu",
          options: MethodOptions | None = None, reference: str | None = None, **option_changes) -> Result:
    """Drape one frame of a scene with a method from `hairwarp.methods.available()`.

    Args:
        scene: a `Scene` (`hairwarp.default_scene`, `hairwarp.build_scene`).
        method: a registered name, or "<name>+refine" / "<name>+settle" (default "auto": the static network
            finished by a few L-BFGS iterations, never worse than the rigid placement).
        frame: which frame of the scene's motion to drape.
        device: "cpu" or "cuda[:N]".
        options: a `MethodOptions` to start from.
        reference: a method to measure against ("reference": the converged optimum; "physics"):
            `metrics["against_reference"]` then holds `hairwarp.metrics.static_fidelity`
            (energy ratio E / E*, mean / p95 vertex distance and tip height difference [mm]).
        **option_changes: fields of `MethodOptions` (max_iterations, patience, refine,
            checkpoint, energy_config, progress, ...).

    Returns:
        Result with positions (M, N, 3) [m] and metrics.
    """
    device = resolve_device(device)
    frames = scene.frames([frame], device=device)
    return _run(scene, frames, method, _options(options, **option_changes), simulate=False, reference=reference)


def simulate(scene, method: str = "auto", *, device: str | torch.device = "cpu",
             options: MethodOptions | None = None, reference: str | None = None, **option_changes) -> Result:
    """Simulate every frame of a scene's motion, in order (see `drape` for the arguments).

    `reference` ("physics" or "reference": the physics simulation) puts
    `hairwarp.metrics.motion_fidelity` into `metrics["against_reference"]`: the distance to the
    physics per frame [mm] and the tips' swing beyond the rigid placement, its amplitude ratio
    and correlation with the physics's.

    Returns:
        Result with positions (T, M, N, 3) [m] and metrics (means over frames).
    """
    device = resolve_device(device)
    frames = scene.frames(device=device)
    return _run(scene, frames, method, _options(options, **option_changes), simulate=True, reference=reference)
