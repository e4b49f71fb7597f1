"""Accuracy metrics of Table 1 and beyond.

Penetration and length change are the paper's Table 1 columns; the energy gap, the distance
to the physics reference and the jitter measure are ours (Section "Metrics" of the harness).
All take torch tensors and return Python floats or tensors on the input's device.
"""

from __future__ import annotations

import torch

from hairwarp._validate import check_tensor
from hairwarp.config import NUM_FIXED_VERTICES


def _batched(x: torch.Tensor, name: str = "x") -> torch.Tensor:
    check_tensor(name, x, shape=("...", None, None, 3))
    return x if x.dim() == 4 else x.reshape(-1, *x.shape[-3:])


def penetration_percent(x: torch.Tensor, body, *, moving_only: bool = True) -> torch.Tensor:
    """Share of hair vertices inside the body (signed distance < 0), in percent, per batch item.

    Args:
        x: (B, M, N, 3) or (M, N, 3) hair positions [m].
        body: a `hairwarp.ops.BodyMesh` with one mesh or B meshes.
        moving_only: count vertices 2..N-1 only. Roots sit on the scalp (|d| ~ float32 noise)
            and vertex 1 is fixed with them, so neither is the method's doing.

    Returns:
        (B,) float tensor in [0, 100].
    """
    from hairwarp.ops import hair_body_signed_distance

    xb = _batched(x)
    return penetration_from_signed_distance(hair_body_signed_distance(xb, body), moving_only=moving_only)


def penetration_from_signed_distance(signed_distance: torch.Tensor, *, moving_only: bool = True) -> torch.Tensor:
    """`penetration_percent` from signed distances (B, M, N) [m] already computed: (B,) in [0, 100]."""
    d = signed_distance[:, :, NUM_FIXED_VERTICES:] if moving_only else signed_distance
    return (d < 0).to(signed_distance.dtype).mean(dim=(1, 2)) * 100.0


def frame_metrics(x: torch.Tensor, frames, energy_config=None) -> tuple[dict, torch.Tensor]:
    """Table 1's metrics of positions on a scene's frames, per frame, and the signed distances.

    Args:
        x: (B, M, N, 3) hair positions [m] of the B frames of `frames` (`Scene.frames(...)`).
        frames: the frames (their body meshes and rest lengths).
        energy_config: when given, the static total energy (Eq. 5) per frame is added.

    Returns:
        ({"penetration_percent": [B floats], "length_change_percent": [B floats],
        "energy": [B floats] when asked}, signed distances (B, M, N) [m]).
    """
    return frame_metrics_of({"x": x}, frames, energy_config)["x"]


def frame_metrics_of(positions: dict, frames, energy_config=None) -> dict:
    """`frame_metrics` of several hair positions on the same frames, in one pass over
    `frames.chunks()`: each chunk's body is built once for all of them and dropped before the
    next (memory flat in the number of frames).

    Args:
        positions: label -> (B, M, N, 3) hair positions [m] of the B frames of `frames`.
        frames: the frames (`Scene.frames(...)`).
        energy_config: when given, the static total energy (Eq. 5) per frame is added.

    Returns:
        label -> (metrics per frame, signed distances (B, M, N) [m]), as `frame_metrics`.
    """
    from hairwarp.ops import hair_body_signed_distance

    xs = {label: _batched(x.detach()) for label, x in positions.items()}
    parts = {label: [] for label in xs}
    start = 0
    for chunk in frames.chunks():
        rows = slice(start, start + chunk.num_frames)
        start = rows.stop
        for label, x in xs.items():
            sd = hair_body_signed_distance(x[rows], chunk.body_mesh)
            found = {"penetration_percent": penetration_from_signed_distance(sd),
                     "length_change_percent": length_change_percent(x[rows], chunk.inputs.rest_lengths)}
            if energy_config is not None:
                from hairwarp.energy import total_energy

                with torch.no_grad():
                    found["energy"] = total_energy(x[rows], chunk.inputs, energy_config).total
            parts[label].append((found, sd))
    out = {}
    for label, found in parts.items():
        per_frame = {key: torch.cat([f[key] for f, _ in found]).tolist() for key in found[0][0]}
        out[label] = (per_frame, torch.cat([sd for _, sd in found]))
    return out


def groom_metrics(frames, guide_positions: torch.Tensor, guide_signed_distance: torch.Tensor, *,
                  body_pass: bool = True) -> dict:
    """The whole groom of a scene simulated through guides, and Table 1's metrics over all its strands.

    Runs over `frames.chunks()` (a few frames' bodies held at a time).

    Args:
        frames: the scene's frames (`Scene.frames`), the scene holding a `GuideSet`.
        guide_positions: (B, K, N, 3) the guides [m] (a method's result or the rigid placement).
        guide_signed_distance: (B, K, N) their signed distances [m] (`frame_metrics`).
        body_pass: keep the followers out of the body (False for the rigid placement: doing
            nothing does nothing).

    Returns:
        {"positions": (B, M, N, 3) [m], "signed_distance": (B, M, N) [m] (exact where it is
        negative; see `GuideSet.signed_distance`), "per_frame": {"penetration_percent",
        "length_change_percent"} lists over the B frames, "body_pass": {"pushed_vertices",
        "pushed_strands"} summed over the frames}.
    """
    scene = frames.scene
    if scene is None or scene.guides is None:
        raise ValueError("frames: expected frames of a scene simulated through guides (Scene.guides)")
    xs, sds, pushes = [], [], []
    start = 0
    with torch.no_grad():
        for chunk in frames.chunks():
            rows = slice(start, start + chunk.num_frames)
            start = rows.stop
            guides, guide_sd = guide_positions[rows].detach(), guide_signed_distance[rows]
            x, facts = scene.full_groom(guides, chunk, body_pass=body_pass, guide_signed_distance=guide_sd)
            xs.append(x)
            sds.append(scene.guides.signed_distance(x, guides, guide_sd, chunk.body_mesh))
            pushes.append(facts.get("pushed"))
        x, sd = torch.cat(xs), torch.cat(sds)
        rest = scene.guides.groom.strands.to(x.device, x.dtype)
        per_frame = {"penetration_percent": penetration_from_signed_distance(sd).tolist(),
                     "length_change_percent": length_change_percent(x, (rest[:, 1:] - rest[:, :-1]).norm(dim=-1)).tolist()}
    body = {}
    if pushes[0] is not None:
        pushed = torch.cat(pushes)
        body = {"pushed_vertices": int(pushed.sum()), "pushed_strands": int((pushed > 0).sum())}
    return {"positions": x, "signed_distance": sd, "per_frame": per_frame, "body_pass": body}


def length_change_percent(x: torch.Tensor, rest_lengths: torch.Tensor) -> torch.Tensor:
    """Mean |segment length / rest length - 1| in percent, per batch item (Table 1).

    Args:
        x: (B, M, N, 3) or (M, N, 3) hair positions [m].
        rest_lengths: (M, N-1) rest segment lengths [m]; zero-length rest segments are skipped.

    Returns:
        (B,) float tensor.
    """
    xb = _batched(x)
    check_tensor("rest_lengths", rest_lengths, shape=(xb.shape[1], xb.shape[2] - 1))
    lengths = (xb[:, :, 1:] - xb[:, :, :-1]).norm(dim=-1)
    valid = rest_lengths > 0
    ratio = torch.where(valid, lengths / rest_lengths.clamp_min(1e-12), torch.ones_like(lengths))
    err = (ratio - 1.0).abs() * valid
    return err.sum(dim=(1, 2)) / valid.sum().clamp_min(1) * 100.0


def energy_gap(energy: torch.Tensor, optimum: torch.Tensor | float,
               initial: torch.Tensor | float | None = None) -> torch.Tensor:
    """Relative gap of an energy to the converged optimum E* of the same scene.

    Without `initial`: (E - E*) / |E*|. With the energy E0 of the starting state (the rigid
    placement): (E - E*) / (E0 - E*), 1 at the start and 0 at the optimum. The second form is
    the one the harness reports: the gravity term (Eq. 11) measures height from an arbitrary
    origin, so |E*| is no meaningful scale, while E0 - E* is the energy the method had to
    remove. Negative values mean the method found a lower energy than the "optimum".

    Args:
        energy: (B,) or scalar total energies (Eq. 5) of a method's drapes.
        optimum: E*, broadcastable to `energy`.
        initial: optional E0, broadcastable to `energy`.

    Returns:
        Tensor shaped like `energy` (dimensionless).
    """
    check_tensor("energy", energy)
    optimum = torch.as_tensor(optimum, dtype=energy.dtype, device=energy.device)
    check_tensor("optimum", optimum)
    if initial is None:
        return (energy - optimum) / optimum.abs().clamp_min(1e-30)
    initial = torch.as_tensor(initial, dtype=energy.dtype, device=energy.device)
    check_tensor("initial", initial)
    return (energy - optimum) / (initial - optimum).abs().clamp_min(1e-30)


def distance_to_reference(x: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame mean and max vertex distance [m] between a sequence and the physics reference.

    Args:
        x: (T, M, N, 3) positions of a method over a motion.
        reference: (T, M, N, 3) positions of the physics reference.

    Returns:
        (mean (T,), max (T,)) in metres.
    """
    check_tensor("x", x, shape=(None, None, None, 3))
    check_tensor("reference", reference, shape=tuple(x.shape))
    dist = (x - reference).norm(dim=-1)
    return dist.mean(dim=(1, 2)), dist.amax(dim=(1, 2))


def jitter(x: torch.Tensor, reference: torch.Tensor | None = None) -> torch.Tensor:
    """Mean norm of the second time difference of positions [m], beyond the reference's.

    The second difference x_{t+1} - 2 x_t + x_{t-1} is the discrete acceleration times dt^2:
    a smooth motion has it small, frame-to-frame flicker makes it large. With a reference, the
    reference's own value is subtracted (a fast motion legitimately accelerates).

    Args:
        x: (T, M, N, 3) positions over T >= 3 frames.
        reference: optional (T, M, N, 3) physics reference.

    Returns:
        scalar tensor [m].
    """
    check_tensor("x", x, shape=(None, None, None, 3))
    if x.shape[0] < 3:
        raise ValueError(f"x: jitter needs at least 3 frames, got {x.shape[0]}")
    acc = (x[2:] - 2 * x[1:-1] + x[:-2]).norm(dim=-1).mean()
    if reference is not None:
        check_tensor("reference", reference, shape=tuple(x.shape))
        acc = acc - (reference[2:] - 2 * reference[1:-1] + reference[:-2]).norm(dim=-1).mean()
    return acc


# RMS swings and standard deviations below this are float32 rounding of ~1 m coordinates
# (ulp 1.2e-7 m), not motion: the amplitude ratio and correlation are undefined against them.
_SWING_FLOOR = 1e-6  # m

_MM = 1e3  # metres to millimetres


def _moving_distance(x: torch.Tensor, reference: torch.Tensor, name: str, ref_name: str) -> torch.Tensor:
    """(B, M, N - 2) float64 distances [m] of the moving vertices 2..N-1 of two matching batches."""
    check_tensor(ref_name, reference, shape=tuple(x.shape), device=x.device)
    if x.shape[-2] <= NUM_FIXED_VERTICES:
        raise ValueError(f"{name}: expected more than {NUM_FIXED_VERTICES} vertices per strand, got {x.shape[-2]}")
    d = (x[..., NUM_FIXED_VERTICES:, :] - reference[..., NUM_FIXED_VERTICES:, :]).norm(dim=-1)
    return d.double()


def _quantile(values: torch.Tensor, q: float) -> float:
    """Linear-interpolation quantile (numpy's default) of a 1-D tensor; `torch.quantile` caps the size."""
    n = values.numel()
    pos = q * (n - 1)
    lo = int(pos)
    hi = min(lo + 1, n - 1)
    v_lo = float(torch.kthvalue(values, lo + 1).values)
    v_hi = float(torch.kthvalue(values, hi + 1).values) if hi != lo else v_lo
    return v_lo + (pos - lo) * (v_hi - v_lo)


def static_fidelity(x: torch.Tensor, optimum: torch.Tensor, energy=None, optimum_energy=None) -> dict:
    """How far a static drape is from the converged optimum of the same frames, over the batch.

    Args:
        x: (B, M, N, 3) or (M, N, 3) hair positions of a method [m].
        optimum: positions of the converged optimum, shaped like `x` [m].
        energy: total static energy E (Eq. 5) of `x`: a float or a (B,) tensor, summed [J].
        optimum_energy: E* of `optimum`, like `energy` [J].

    Returns:
        {"mean_distance_mm", "p95_distance_mm": mean and 95th percentile of the per-vertex
        distance over the moving vertices 2..N-1 of every batch item [mm];
        "tip_height_difference_mm": mean over strands of tip y of `x` minus tip y of `optimum`
        [mm], positive when the method's tips hang higher; "energy_ratio": E / E*, only when
        both energies are given (None when E* is 0)}, all Python floats. The ratio reads as
        "times the optimum's energy" only when E* > 0: the gravity term's height origin is
        arbitrary (see `energy_gap`).

    Raises:
        ValueError: shapes that differ, or strands of no moving vertex.
    """
    xb = _batched(check_tensor("x", x, allow_empty=False))
    ob = _batched(check_tensor("optimum", optimum, shape=tuple(x.shape)), "optimum")
    d = _moving_distance(xb, ob, "x", "optimum").flatten()
    out = {"mean_distance_mm": float(d.mean()) * _MM,
           "p95_distance_mm": _quantile(d, 0.95) * _MM,
           "tip_height_difference_mm": float((xb[:, :, -1, 1].double() - ob[:, :, -1, 1].double()).mean()) * _MM}
    if energy is not None and optimum_energy is not None:
        e = float(torch.as_tensor(energy, dtype=torch.float64).sum())
        e_star = float(torch.as_tensor(optimum_energy, dtype=torch.float64).sum())
        out["energy_ratio"] = e / e_star if e_star != 0 else None
    return out


def _tip_offset(x: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
    check_tensor("x", x, shape=(None, None, None, 3), allow_empty=False)
    check_tensor("rigid", rigid, shape=tuple(x.shape), device=x.device)
    return x[:, :, -1] - rigid[:, :, -1]


def tip_swing(x: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
    """The tips' offset from the rigid placement minus its mean over the motion.

    What the hair does beyond following the head: zero for the rigid placement itself, and for
    any drape that keeps a constant offset (a static sag) from it.

    Args:
        x: (T, M, N, 3) hair positions over T frames [m].
        rigid: (T, M, N, 3) the rigid placement of the same frames [m].

    Returns:
        (T, M, 3) tensor [m], differentiable in `x`.

    Raises:
        ValueError: shapes that differ or an empty `x`.
    """
    offset = _tip_offset(x, rigid)
    return offset - offset.mean(dim=0, keepdim=True)


def mean_tip_offset(x: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
    """Mean over strands of the tips' offset from the rigid placement (not mean-subtracted), for plotting.

    Args:
        x: (T, M, N, 3) hair positions over T frames [m].
        rigid: (T, M, N, 3) the rigid placement of the same frames [m].

    Returns:
        (T, 3) tensor [m] (the curves of `hairwarp.evaluation.charts.swing_plot`).

    Raises:
        ValueError: shapes that differ or an empty `x`.
    """
    return _tip_offset(x, rigid).mean(dim=1)


def _rms(v: torch.Tensor) -> float:
    return float(v.double().square().sum(dim=-1).mean().sqrt())


def swing_rms(v: torch.Tensor) -> float:
    """RMS over the leading dimensions of the length of the last one's vectors (a swing's, (T, M, 3)) [its unit]."""
    return _rms(v)


def swing_correlation(a: torch.Tensor, b: torch.Tensor) -> float | None:
    """Pearson correlation of two swings over all their components; None when either is ~constant
    (standard deviation at most `_SWING_FLOOR`, 1e-6 m).
    """
    a, b = a.double().flatten(), b.double().flatten()
    a, b = a - a.mean(), b - b.mean()
    sa, sb = float(a.square().mean().sqrt()), float(b.square().mean().sqrt())
    if sa > _SWING_FLOOR and sb > _SWING_FLOOR:
        return max(-1.0, min(1.0, float((a * b).mean()) / (sa * sb)))
    return None


def swing_by_axis(a: torch.Tensor, b: torch.Tensor) -> dict:
    """Two swings (..., 3) compared component by component (x, y, z).

    Returns:
        {"rms_mm": [x, y, z] RMS of each component of `a` [mm], "reference_rms_mm": the same of
        `b`, "correlation": [x, y, z] `swing_correlation` of each component (None where either
        is ~constant)}.
    """
    return {"rms_mm": [_rms(a[..., k:k + 1]) * _MM for k in range(3)],
            "reference_rms_mm": [_rms(b[..., k:k + 1]) * _MM for k in range(3)],
            "correlation": [swing_correlation(a[..., k], b[..., k]) for k in range(3)]}


def largest_step_from_rigid(x: torch.Tensor, rigid: torch.Tensor) -> float:
    """The farthest any moving vertex travels in one frame beyond the rigid placement's own move [m].

    max over t >= 1, strands and vertices 2..N-1 of |(x(t) - P(t)) - (x(t-1) - P(t-1))|: hair
    carried by the head moves 0; a swing a few millimetres a frame; a strand flung out of a
    pinch between two body parts tens of centimetres a frame (docs/physics.md, "Twenty-third
    session"), which the mean distances hide.

    Args:
        x: (T, M, N, 3) hair positions over T frames [m].
        rigid: (T, M, N, 3) the rigid placement of the same frames [m].

    Returns:
        the distance [m]; 0.0 for a single frame.
    """
    check_tensor("x", x, shape=[None, None, None, 3], allow_empty=False)
    check_tensor("rigid", rigid, shape=tuple(x.shape), device=x.device)
    if x.shape[-2] <= NUM_FIXED_VERTICES:
        raise ValueError(f"x: expected more than {NUM_FIXED_VERTICES} vertices per strand, got {x.shape[-2]}")
    if x.shape[0] < 2:
        return 0.0
    relative = (x - rigid)[:, :, NUM_FIXED_VERTICES:].double()
    return float((relative[1:] - relative[:-1]).norm(dim=-1).max())


def motion_fidelity(x: torch.Tensor, physics: torch.Tensor, rigid: torch.Tensor) -> dict:
    """How a method's motion compares with the physics simulation of the same motion.

    Args:
        x: (T, M, N, 3) hair positions of a method over T frames [m].
        physics: (T, M, N, 3) the implicit-Euler simulation of the same frames [m].
        rigid: (T, M, N, 3) the rigid placement of the same frames [m].

    Returns:
        Python floats (or None) under
        "per_frame_distance_mm": T per-frame mean distances to `physics` over the moving
        vertices 2..N-1 [mm]; "mean_distance_mm", "max_distance_mm": their mean and maximum;
        "strand_distance_p99_mm": per frame the 99th percentile over the strands of a strand's
        mean distance, at the worst frame [mm] (the few strands that fly out, which the mean
        hides: the demo's outer strands);
        "swing_mm", "physics_swing_mm": RMS over frames and strands of |`tip_swing`| of `x` and
        of `physics` [mm]; "swing_amplitude_ratio": swing_mm / physics_swing_mm (None when the
        physics barely swings); "swing_correlation": Pearson correlation of the two swings over
        all (T, M, 3) components (None when either is ~constant, e.g. for the rigid placement);
        "largest_step_mm", "physics_largest_step_mm": `largest_step_from_rigid` of `x` and of
        `physics` [mm] (a strand flung out in one frame);
        "swing_by_axis_mm", "physics_swing_by_axis_mm": [x, y, z] RMS over frames and strands of
        each component of the two swings [mm]; "swing_correlation_by_axis": [x, y, z] their
        correlation per component (None where either is ~constant): which way the motion is
        missed (the curly walk's vertical bounce, a bob's climb);
        "bulk_swing_correlation": the correlation of the strands' mean swings ((T, 3), the swing
        plot's curves less their means): whether the hair as a whole moves like the physics where
        "swing_correlation" asks it of every strand.

    Raises:
        ValueError: shapes that differ, an empty `x` or strands of no moving vertex.
    """
    s_x = tip_swing(x, rigid).double()
    check_tensor("physics", physics, shape=tuple(x.shape), device=x.device)
    s_p = tip_swing(physics, rigid).double()
    per_strand = _moving_distance(x, physics, "x", "physics").mean(dim=2) * _MM  # (T, M)
    per_frame = per_strand.mean(dim=1)
    strand_p99 = max(_quantile(row, 0.99) for row in per_strand)
    swing, physics_swing = _rms(s_x), _rms(s_p)
    corr = swing_correlation(s_x, s_p)
    axes = swing_by_axis(s_x, s_p)
    return {"mean_distance_mm": float(per_frame.mean()),
            "max_distance_mm": float(per_frame.max()),
            "per_frame_distance_mm": per_frame.tolist(),
            "strand_distance_p99_mm": strand_p99,
            "swing_mm": swing * _MM,
            "physics_swing_mm": physics_swing * _MM,
            "swing_amplitude_ratio": swing / physics_swing if physics_swing > _SWING_FLOOR else None,
            "swing_correlation": corr,
            "largest_step_mm": largest_step_from_rigid(x, rigid) * _MM,
            "physics_largest_step_mm": largest_step_from_rigid(physics, rigid) * _MM,
            "swing_by_axis_mm": axes["rms_mm"],
            "physics_swing_by_axis_mm": axes["reference_rms_mm"],
            "swing_correlation_by_axis": axes["correlation"],
            "bulk_swing_correlation": swing_correlation(s_x.mean(dim=1), s_p.mean(dim=1))}


def drape_fidelity(x: torch.Tensor, optimum: torch.Tensor, inputs, config=None) -> dict:
    """`static_fidelity` of drapes `x` against `optimum` (both (B, M, N, 3) [m]) with their static
    energies (Eq. 5) computed from the frames' `EnergyInputs` and `config`: E / E* included.
    """
    from hairwarp.energy import total_energy

    with torch.no_grad():
        energy = float(total_energy(x, inputs, config).total.sum())
        optimum_energy = float(total_energy(optimum, inputs, config).total.sum())
    return static_fidelity(x, optimum, energy, optimum_energy)
