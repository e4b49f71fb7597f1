"""Stability study: where the energy and the methods fail, measured.

Each study returns a list of rows {"study", "setting", ... measured values ..., "outcome"};
`run_stability_study` runs them all at small sizes (a few minutes on a 2-core CPU) and
`stability_markdown` renders the table of docs/stability.md. Tests in
tests/test_stability.py pin the behaviour found here.

Studies:
    barrier_trap_1d / barrier_trap_scene: the paper's quartic extrapolation (Eq. 12-14) has
        P(t0) = P'(t0) = 0 at d = -(xi + dhat): vertices started deeper stay inside; the
        monotone and quadratic (default) extrapolations push every depth out.
    barrier_precision: float32 against float64 barrier energy and gradient for d just above xi.
    stiffness: weights of stretch and hair-body contact scaled by 1e-4 .. 1e4.
    units: the same scene in metres and in centimetres, weights rescaled so that
        E_cm(100 x) = E_m(x) exactly (lengths^2 terms / 100^2, gravity / 100, barriers / 100^4).
    degenerate_strands: zero-length rest segments and coincident vertices.
    long_hair: strands stretched about their roots to 2x and 4x their length.
    time_step: the implicit-Euler reference with a time step 10x too large.
    divergence: absurd step sizes for Adam and L-BFGS.
    sign_consistency: the pseudo-normal sign of the body's signed distance against the
        winding number, for hair vertices deep inside the body.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import torch

from hairwarp.config import BARRIER_VARIANTS, NUM_FIXED_VERTICES, EnergyConfig
from hairwarp.energy import EnergyInputs, total_energy
from hairwarp import metrics as M
from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.scene.scalp import root_subset
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

# The sizes of the study's scenes (small: the study is about behaviour, not speed).
STUDY_STRAND_STRIDE = 16
STUDY_NUM_VERTICES = 24
STUDY_ITERATIONS = 150


def _tiny_frames(name: str = "table1", stride: int = STUDY_STRAND_STRIDE, nv: int = STUDY_NUM_VERTICES,
                 device="cpu", dtype=torch.float32):
    scene = comparison_scene(name, strand_stride=stride, num_vertices=nv)
    return scene, scene.frames([0], device=device, dtype=dtype)


def _drape_row(study: str, setting: str, x0, inputs, config, solver, body, rest) -> dict:
    result = optimize_drape(x0, inputs, config, solver)
    x = result.positions
    finite = bool(torch.isfinite(x).all())
    return {
        "study": study,
        "setting": setting,
        "finite": finite,
        "penetration_percent": float(M.penetration_percent(x, body).mean()) if finite else None,
        "length_change_percent": float(M.length_change_percent(x, rest).mean()) if finite else None,
        "iterations": result.iterations,
        "stop_reason": result.stop_reason,
        "loss": result.loss,
        "positions": x,
    }


# ------------------------------------------------------------------------------------ barrier
def barrier_trap_1d(depths: torch.Tensor, variant: str, config: EnergyConfig | None = None,
                    iterations: int = 200) -> torch.Tensor:
    """Minimise the hair-body barrier B(d) alone from each start distance; return the final d.

    A 1-D model of a vertex pushed straight out along the surface normal (|grad d| = 1): d
    follows -dB/dd. Gradient descent with a step normalised per start point (so a steep and a
    flat start move alike) and a backtracking halving when B would rise.

    Args:
        depths: (K,) start signed distances [m] (negative inside), float64.
        variant: "paper", "monotone" or "quadratic".
        config: xi, dhat, join fraction of hair-body contact.
        iterations: descent steps.

    Returns:
        (K,) final signed distances [m].
    """
    from hairwarp.ops.barrier import barrier

    config = config or EnergyConfig()
    xi, dhat, bp = config.hair_body_xi, config.hair_body_dhat, config.barrier_join_fraction
    d = depths.detach().to(torch.float64).clone()
    step = torch.full_like(d, 0.25 * dhat)
    for _ in range(iterations):
        d.requires_grad_(True)
        e = barrier(d, xi, dhat, bp, variant)
        (g,) = torch.autograd.grad(e.sum(), d)
        d = d.detach()
        with torch.no_grad():
            trial = d - step * torch.sign(g)
            worse = barrier(trial, xi, dhat, bp, variant) > e.detach()
            step = torch.where(worse, step * 0.5, step)
            d = torch.where(worse | (g == 0), d, trial)
    return d


def barrier_trap_study(config: EnergyConfig | None = None) -> list[dict]:
    """Which start depths stay inside (d < 0) under each barrier variant (1-D model)."""
    config = config or EnergyConfig()
    depths = -torch.linspace(0.0, 0.02, 201, dtype=torch.float64)[1:]  # 0.1 mm .. 20 mm inside
    rows = []
    for variant in BARRIER_VARIANTS:
        final = barrier_trap_1d(depths, variant, config)
        trapped = final < 0
        shallowest = float(-depths[trapped].abs().min()) if bool(trapped.any()) else None
        rows.append({
            "study": "barrier_trap_1d",
            "setting": f"{variant}, start 0.1-20 mm inside",
            "trapped_share": float(trapped.double().mean()),
            "shallowest_trapped_start_m": shallowest,
            "trap_depth_m": float(final[trapped].mean()) if bool(trapped.any()) else None,
            "local_minimum_m": -(config.hair_body_xi + config.hair_body_dhat),
            "outcome": ("starts deeper than the paper barrier's peak slide to d = -(xi + dhat) and stay"
                        if bool(trapped.any()) else "every start is pushed out"),
        })
    return rows


def barrier_trap_scene(iterations: int = STUDY_ITERATIONS, stride: int = STUDY_STRAND_STRIDE,
                       nv: int = STUDY_NUM_VERTICES) -> list[dict]:
    """L-BFGS drape of the Table 1 scene (every tip inside) under each barrier variant."""
    _, frames = _tiny_frames("table1", stride, nv)
    from hairwarp.ops import hair_body_signed_distance

    rows = []
    solver = DirectOptimizationConfig(max_iterations=iterations, patience=iterations)
    for variant in BARRIER_VARIANTS:
        config = EnergyConfig(barrier_variant=variant)
        row = _drape_row("barrier_trap_scene", f"table1 {variant}", frames.rigid.positions, frames.inputs, config,
                         solver, frames.body_mesh, frames.inputs.rest_lengths)
        d = hair_body_signed_distance(row.pop("positions"), frames.body_mesh)[..., NUM_FIXED_VERTICES:]
        deep = -(config.hair_body_xi + config.hair_body_dhat)
        row["inside_deeper_than_xi_plus_dhat_percent"] = float((d < deep).double().mean() * 100)
        rows.append(row)
    return rows


def barrier_precision(gaps: torch.Tensor, config: EnergyConfig | None = None, bp: float | None = None) -> dict:
    """float32 against float64 barrier at d = xi + gap, for tiny gaps above the hard barrier.

    Args:
        gaps: (K,) d - xi [m], float64.
        config: xi, dhat (and the join fraction unless `bp` is given).
        bp: join fraction override: a tiny one puts the log barrier itself next to xi.

    Returns:
        dict of (K,) float64 tensors: "energy32", "energy64", "grad32", "grad64",
        "energy_rel_err", "grad_rel_err" (inf/nan where float32 gave a non-finite value).
    """
    from hairwarp.ops.barrier import barrier

    config = config or EnergyConfig()
    xi, dhat = config.hair_body_xi, config.hair_body_dhat
    bp = config.barrier_join_fraction if bp is None else bp
    out = {}
    for dtype, tag in ((torch.float32, "32"), (torch.float64, "64")):
        d = (xi + gaps.to(torch.float64)).to(dtype).requires_grad_(True)
        e = barrier(d, xi, dhat, bp)
        (g,) = torch.autograd.grad(e.sum(), d)
        out["energy" + tag] = e.detach().double()
        out["grad" + tag] = g.double()
    for key in ("energy", "grad"):
        ref = out[key + "64"]
        out[key + "_rel_err"] = (out[key + "32"] - ref).abs() / ref.abs().clamp_min(1e-300)
    return out


def barrier_precision_study(config: EnergyConfig | None = None) -> list[dict]:
    """float32 near contact: d = xi + gap, gap 10 um .. 0.1 nm, default join and a log barrier down to xi.

    float32 spaces numbers near 1 mm by ~1.2e-10 m, so d itself is rounded by up to 6e-11 m:
    the error is that rounding seen through the barrier's steep gradient.
    """
    config = config or EnergyConfig()
    gaps = torch.tensor([1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10], dtype=torch.float64)
    rows = []
    for bp, label in ((config.barrier_join_fraction, "default join (log barrier from xi + 15 um)"),
                      (1e-7, "join 1e-7 (log barrier down to xi)")):
        p = barrier_precision(gaps, config, bp)
        for i, gap in enumerate(gaps.tolist()):
            e_err, g_err = float(p["energy_rel_err"][i]), float(p["grad_rel_err"][i])
            ok = math.isfinite(e_err) and math.isfinite(g_err) and max(e_err, g_err) < 1e-2
            rows.append({"study": "barrier_precision", "setting": f"{label}, d - xi = {gap:.0e} m",
                         "energy_rel_err_f32": e_err, "grad_rel_err_f32": g_err,
                         "outcome": "float32 within 1 %" if ok else "float32 off by more than 1 % (or non-finite)"})
    return rows


# ------------------------------------------------------------------------------- stiffness
def stiffness_study(factors=(1e-4, 1e-2, 1.0, 1e2, 1e4), iterations: int = STUDY_ITERATIONS) -> list[dict]:
    """Stretch and hair-body contact weights scaled by each factor, L-BFGS on Table 1."""
    _, frames = _tiny_frames()
    base = EnergyConfig()
    solver = DirectOptimizationConfig(max_iterations=iterations, patience=50)
    rows = []
    for term, field in (("stretch", "stretch_weight"), ("hair_body_contact", "hair_body_weight")):
        for f in factors:
            config = base.replace(**{field: getattr(base, field) * f})
            row = _drape_row("stiffness", f"{term} x {f:g}", frames.rigid.positions, frames.inputs, config, solver,
                             frames.body_mesh, frames.inputs.rest_lengths)
            row.pop("positions")
            rows.append(row)
    return rows


# ------------------------------------------------------------------------------------ units
def centimetre_config(config: EnergyConfig, scale: float = 100.0) -> EnergyConfig:
    """The weights that make E_scaled(scale * x) = E(x) for every hair state x.

    Terms quadratic in lengths (stretch Eq. 7, auxiliary Eq. 9, smoothness Eq. 10, inertia
    Eq. 16) take weight / scale^2; gravity (Eq. 11, linear in height) weight / scale; the
    bending angle (Eq. 8) and the root alignment (Eq. 15, unit directions) are scale-free but
    their epsilons are lengths (x scale); the barrier (Eq. 12-14) is homogeneous of degree 4
    in (d, xi, dhat), so xi, dhat x scale and weight / scale^4.
    """
    s = float(scale)
    return config.replace(
        stretch_weight=config.stretch_weight / s**2,
        auxiliary_weight=config.auxiliary_weight / s**2,
        smoothness_weight=config.smoothness_weight / s**2,
        inertia_weight=config.inertia_weight / s**2,
        gravity_weight=config.gravity_weight / s,
        bending_eps=config.bending_eps * s,
        root_alignment_eps=config.root_alignment_eps * s,
        hair_body_xi=config.hair_body_xi * s,
        hair_body_dhat=config.hair_body_dhat * s,
        hair_body_weight=config.hair_body_weight / s**4,
        hair_diameter=config.hair_diameter * s,
        hair_hair_dhat=config.hair_hair_dhat * s,
        hair_hair_weight=config.hair_hair_weight / s**4,
    )


def scaled_inputs(frames, faces: torch.Tensor, scale: float = 100.0) -> EnergyInputs:
    """The frames' energy inputs with every length multiplied by `scale` (body rebuilt, cropped).

    Args:
        frames: `SceneFrames` in metres.
        faces: (F, 3) the full body's triangles (`scene.body.faces`).
        scale: length factor (100: centimetres).
    """
    from hairwarp.ops import BodyMesh

    inputs = frames.inputs
    rigid = inputs.rigid * scale
    full = BodyMesh(frames.posed.vertices.to(rigid.dtype) * scale, faces.to(device=rigid.device, dtype=torch.int32))
    body = full.crop_for_hair(rigid[:, :, 0], inputs.rest_lengths.sum(dim=1) * scale)
    return replace(inputs, rest_lengths=inputs.rest_lengths * scale, rigid=rigid, body=body)


def units_study(iterations: int = STUDY_ITERATIONS, scale: float = 100.0) -> list[dict]:
    """The Table 1 scene in metres and in centimetres: energies and L-BFGS drapes compared."""
    scene, frames = _tiny_frames()
    config = EnergyConfig()
    config_cm = centimetre_config(config, scale)
    inputs_cm = scaled_inputs(frames, scene.scene.body.faces, scale)
    x0 = frames.rigid.positions
    with torch.no_grad():
        e_m = float(total_energy(x0, frames.inputs, config).total.sum())
        e_cm = float(total_energy(x0 * scale, inputs_cm, config_cm).total.sum())
    solver = DirectOptimizationConfig(max_iterations=iterations, patience=50)
    r_m = optimize_drape(x0, frames.inputs, config, solver)
    r_cm = optimize_drape(x0 * scale, inputs_cm, config_cm, solver)
    diff = (r_cm.positions / scale - r_m.positions).norm(dim=-1)
    pen_m = float(M.penetration_percent(r_m.positions, frames.body_mesh).mean())
    pen_cm = float(M.penetration_percent(r_cm.positions, inputs_cm.body).mean())
    return [{
        "study": "units",
        "setting": f"metres vs centimetres (x{scale:g}), {iterations} L-BFGS iterations",
        "initial_energy_rel_diff": abs(e_cm - e_m) / abs(e_m),
        "final_loss_m": r_m.loss, "final_loss_cm": r_cm.loss,
        "drape_max_diff_m": float(diff.max()), "drape_mean_diff_m": float(diff.mean()),
        "penetration_percent_m": pen_m, "penetration_percent_cm": pen_cm,
        "stop_reason_m": r_m.stop_reason, "stop_reason_cm": r_cm.stop_reason,
        "outcome": "same energy; drapes compared after rescaling",
    }]


# ------------------------------------------------------------------------------ degenerate
def degenerate_inputs(frames, strands=(0, 1), vertex: int = 5):
    """Copies of the frames' rigid placement and inputs with coincident vertices.

    Strand strands[0]: vertex `vertex` + 1 moved onto vertex `vertex` (a zero-length rest
    segment, the rest shape changed accordingly). Strand strands[1]: the same in the start
    state only (rest length kept: a collapsed segment the stretch term must reopen).

    Returns:
        (x0 (B, M, N, 3), EnergyInputs).
    """
    x0 = frames.rigid.positions.clone()
    a, b = strands
    x0[:, a, vertex + 1] = x0[:, a, vertex]
    x0[:, b, vertex + 1] = x0[:, b, vertex]
    rest = frames.inputs.rest_lengths.clone()
    rest[a, vertex] = 0.0
    rigid = frames.inputs.rigid.clone()
    rigid[:, a, vertex + 1] = rigid[:, a, vertex]
    return x0, replace(frames.inputs, rest_lengths=rest, rigid=rigid)


def degenerate_study(iterations: int = STUDY_ITERATIONS) -> list[dict]:
    """Degenerate strands (zero-length segments, coincident vertices): does every method stay finite?"""
    _, frames = _tiny_frames()
    x0, inputs = degenerate_inputs(frames)
    x = x0.clone().requires_grad_(True)
    e = total_energy(x, inputs, EnergyConfig()).total.sum()
    (g,) = torch.autograd.grad(e, x)
    row = _drape_row("degenerate_strands", "zero-length rest segment + collapsed segment", x0, inputs, EnergyConfig(),
                     DirectOptimizationConfig(max_iterations=iterations, patience=50), frames.body_mesh,
                     inputs.rest_lengths)
    pos = row.pop("positions")
    row["initial_energy_finite"] = bool(math.isfinite(float(e)))
    row["initial_gradient_finite"] = bool(torch.isfinite(g).all())
    row["collapsed_segment_reopened_m"] = float((pos[0, 1, 6] - pos[0, 1, 5]).norm())
    row["collapsed_segment_rest_m"] = float(inputs.rest_lengths[1, 5])
    row["outcome"] = "finite" if row["finite"] and row["initial_gradient_finite"] else "NaN"
    return [row]


# ------------------------------------------------------------------------------- long hair
def long_hair_inputs(frames, faces: torch.Tensor, factor: float):
    """The rigid placement stretched about each root by `factor` (longer rest lengths too).

    Args:
        frames: `SceneFrames`; faces: (F, 3) the full body's triangles; factor: length factor.

    Returns:
        (x0 (B, M, N, 3), EnergyInputs with the body re-cropped for the longer strands).
    """
    from hairwarp.ops import BodyMesh

    rigid = frames.inputs.rigid
    root = rigid[:, :, :1]
    x0 = root + factor * (rigid - root)
    rest = frames.inputs.rest_lengths * factor
    full = BodyMesh(frames.posed.vertices.to(rigid.dtype), faces.to(device=rigid.device, dtype=torch.int32))
    body = full.crop_for_hair(x0[:, :, 0], rest.sum(dim=1))
    return x0, replace(frames.inputs, rigid=x0, rest_lengths=rest, body=body)


def long_hair_study(factors=(1.0, 2.0, 4.0), iterations: int = STUDY_ITERATIONS) -> list[dict]:
    """Strands `factors` times longer than the scene's: penetration and length change after L-BFGS."""
    scene, frames = _tiny_frames("medium_rest")
    rows = []
    for f in factors:
        x0, inputs = long_hair_inputs(frames, scene.scene.body.faces, f)
        t0 = time.perf_counter()
        row = _drape_row("long_hair", f"medium_rest strands x {f:g} length", x0, inputs, EnergyConfig(),
                         DirectOptimizationConfig(max_iterations=iterations, patience=50), inputs.body,
                         inputs.rest_lengths)
        row.pop("positions")
        row["time_s"] = time.perf_counter() - t0
        row["rigid_penetration_percent"] = float(M.penetration_percent(x0, inputs.body).mean())
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------- time step
def time_step_study(num_frames: int = 8, factors=(1.0, 10.0), stride: int = 32, nv: int = 12) -> list[dict]:
    """The implicit-Euler physics (tight setting) on the whiplash's first frames at dt and 10 dt."""
    from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

    scene = comparison_scene("whiplash", strand_stride=stride, num_vertices=nv)
    per_frame = [scene.frames([i]) for i in range(num_frames)]
    rows, runs = [], {}
    solver = replace(PhysicsConfig().tight(), max_iterations=300)
    for f in factors:
        config = scene.energy_config().replace(time_step=f / scene.fps)
        r = simulate_physics(scene.scene, range(num_frames), energy_config=config, config=solver)
        x = r.positions[:, 0]
        runs[f] = x
        finite = bool(torch.isfinite(x).all())
        pen = torch.stack([M.penetration_percent(x[t], per_frame[t].body_mesh)[0] for t in range(num_frames)])
        rows.append({
            "study": "time_step", "setting": f"whiplash {num_frames} frames, dt = {f:g}/{scene.fps:g} s",
            "finite": finite,
            "penetration_percent": float(pen.mean()) if finite else None,
            "length_change_percent": float(M.length_change_percent(x, per_frame[0].inputs.rest_lengths).mean())
            if finite else None,
            "diverged_frames": sum(1 for s in r.stop_reasons if s.startswith("diverged")),
            "iterations_mean": sum(r.iterations[1:]) / max(1, num_frames - 1),
            "max_step_m": float((x[1:] - x[:-1]).norm(dim=-1).max()) if finite else None,
        })
    if 1.0 in runs and 10.0 in runs:
        rows[-1]["max_diff_to_dt_m"] = float((runs[10.0] - runs[1.0]).norm(dim=-1).max())
    for row in rows:
        row["outcome"] = "finite, no diverged frame" if row["finite"] and not row["diverged_frames"] else "failure"
    return rows


# ------------------------------------------------------------------------------ divergence
def divergence_study(iterations: int = 40) -> list[dict]:
    """Absurd step sizes: the run must be reported as diverged or return a finite drape."""
    _, frames = _tiny_frames()
    x0 = frames.rigid.positions
    with torch.no_grad():
        e0 = float(total_energy(x0, frames.inputs, EnergyConfig()).total.sum())
    rows = []
    for setting, solver in (
        ("adam lr = 10 m", DirectOptimizationConfig(method="adam", adam_lr=10.0, max_iterations=iterations)),
        ("adam lr = 1e6 m", DirectOptimizationConfig(method="adam", adam_lr=1e6, max_iterations=iterations)),
        ("lbfgs lr = 1e8", DirectOptimizationConfig(method="lbfgs", lbfgs_lr=1e8, max_iterations=iterations)),
    ):
        row = _drape_row("divergence", setting, x0, frames.inputs, EnergyConfig(), solver, frames.body_mesh,
                         frames.inputs.rest_lengths)
        row.pop("positions")
        row["initial_loss"] = e0
        row["outcome"] = ("diverged, reported; best finite iterate returned" if row["stop_reason"].startswith("diverged")
                          else "no divergence")
        rows.append(row)
    return rows


# ------------------------------------------------------------------------- sign consistency
def winding_numbers(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor, chunk: int = 64) -> torch.Tensor:
    """Generalized winding numbers of points w.r.t. a closed mesh (1 inside, 0 outside), float64.

    The solid-angle sum (Van Oosterom & Strackee) over every triangle: slow (O(P F)) but
    global and exact on a watertight mesh, a ground truth for inside/outside.

    Args:
        points: (P, 3) [m]; vertices: (V, 3) [m]; faces: (F, 3) counter-clockwise from outside.

    Returns:
        (P,) float64.
    """
    v = vertices.detach().double()
    f = faces.long()
    a_, b_, c_ = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    out = []
    for s in range(0, points.shape[0], chunk):
        p = points[s:s + chunk].detach().double()[:, None]
        a, b, c = a_[None] - p, b_[None] - p, c_[None] - p
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        num = (a * torch.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out.append(2.0 * torch.atan2(num, den).sum(-1) / (4.0 * math.pi))
    return torch.cat(out)


def sign_consistency(points: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor) -> dict:
    """Pseudo-normal sign of `hairwarp.ops` signed distance against the winding number.

    Returns:
        dict: "signed_distance" (P,), "winding" (P,), "wrong_outside" (P,) bool (called outside,
        lies inside), "wrong_inside" (P,) bool (called inside, lies outside).
    """
    from hairwarp.ops.hair_body_contact import point_mesh_signed_distance

    d = point_mesh_signed_distance(points.detach().float(), vertices.float(), faces.int())
    w = winding_numbers(points, vertices, faces)
    return {"signed_distance": d, "winding": w, "wrong_outside": (d > 0) & (w > 0.5),
            "wrong_inside": (d < 0) & (w < 0.5)}


def sign_consistency_study(stride: int = 16, min_depth: float = 0.02) -> list[dict]:
    """Deep vertices of the unfitted long_straight hair on the arms-down body (the old demo).

    The hair of `default_scene("long_straight")` is grown around the T-pose body; with the
    arms lowered (the procedural motions' rest pose) and the head turned, its rigid
    placement passes through the torso by up to 8 cm. Points with |d| >= `min_depth` are
    checked against the winding number.
    """
    from hairwarp.ops import hair_body_signed_distance
    from hairwarp.scene.scene import Scene, default_scene

    base = default_scene("long_straight", "head_turn", seed=0, duration=1.0)
    keep = root_subset(base.hairstyle.num_strands, base.scalp.resolution, stride)
    scene = Scene(body=base.body, scalp=base.scalp, hairstyle=base.hairstyle.subset(keep, 100),
                  motion=base.motion, name="unfitted")
    frames = scene.frames([0], crop=False)
    k = NUM_FIXED_VERTICES
    x = frames.rigid.positions[0, :, k:].reshape(-1, 3)
    d = hair_body_signed_distance(frames.rigid.positions, frames.body_mesh)[0, :, k:].reshape(-1)
    deep = d.abs() >= min_depth
    check = sign_consistency(x[deep], frames.posed.vertices[0], scene.body.faces)
    wrong = check["wrong_outside"] | check["wrong_inside"]
    return [{
        "study": "sign_consistency",
        "setting": f"long_straight (unfitted) head_turn frame 0, stride {stride}, |d| >= {min_depth * 100:g} cm",
        "points_checked": int(deep.sum()),
        "inside_by_winding": int((check["winding"] > 0.5).sum()),
        "wrong_sign": int(wrong.sum()),
        "wrong_sign_abs_distance_m": [float(v) for v in check["signed_distance"][wrong].abs().tolist()],
        "outcome": ("pseudo-normal sign wrong deep inside: zero-energy holes, energy jumps"
                    if bool(wrong.any()) else "signs agree"),
    }]


# ------------------------------------------------------------------------------------- all
def run_stability_study(device="cpu", *, progress: bool = False) -> dict:
    """Every study above at its small size. CPU only (the studies are about behaviour).

    Returns:
        {"machine", "rows": [...], "time_s"}: JSON-ready (tensors dropped).
    """
    from tqdm.auto import tqdm

    from hairwarp.evaluation.harness import machine_description

    device = torch.device(device)
    studies = [barrier_trap_study, barrier_trap_scene, barrier_precision_study, stiffness_study, units_study,
               degenerate_study, long_hair_study, time_step_study, divergence_study, sign_consistency_study]
    rows = []
    start = time.perf_counter()
    for study in tqdm(studies, desc="stability", disable=not progress):
        t0 = time.perf_counter()
        for row in study():
            row["study_time_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
    return {"schema": "hairwarp.stability/1", "machine": machine_description(torch.device("cpu")),
            "rows": rows, "time_s": time.perf_counter() - start}


def stability_markdown(record: dict) -> str:
    """One table per study; columns are the study's measured fields."""
    lines = [f"Machine: {record['machine']['device_name']}; {record['time_s']:.0f} s in all.", ""]
    studies: dict[str, list[dict]] = {}
    for row in record["rows"]:
        studies.setdefault(row["study"], []).append(row)
    for name, rows in studies.items():
        keys = [k for k in rows[0] if k not in ("study", "study_time_s")]
        for r in rows[1:]:
            keys += [k for k in r if k not in keys and k not in ("study", "study_time_s")]
        lines.append(f"#### {name}")
        lines.append("| " + " | ".join(keys) + " |")
        lines.append("|" + "---|" * len(keys))
        for r in rows:
            lines.append("| " + " | ".join(_cell(r.get(k)) for k in keys) + " |")
        lines.append("")
    return "\n".join(lines)


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list):
        return ", ".join(_cell(x) for x in v[:6]) + (" ..." if len(v) > 6 else "")
    return str(v).replace("|", "/")
