"""Torch bridge of the strand energy terms (HairFormer Section 3.4, Eq. 7-11, 15, 16).

Device code in `hairwarp.kernels.strand_energies`: one fused Warp launch evaluates every
enabled term, its per-term energies and the analytic gradient of the weighted total with
respect to the hair positions; the torch backward only scales that saved gradient.

Conventions shared by every public function here:
    * `x` is `(B, M, N, 3)` (output shape `(B,)`) or `(M, N, 3)` (output shape `()`, a 0-dim
      tensor), float32 or float64, on CPU or CUDA; N >= 3, M >= 1. An empty batch (B = 0)
      returns empty results without launching a kernel.
    * Energies are per batch item: each is the paper's loss for one hairstyle state.
    * Gradients flow to `x` only. The gradient at vertices 0 and 1 of every strand is exactly
      zero: the paper fixes the root and its neighbour and excludes them from gradient
      computation (Section 3.4); their positions still enter Eq. 7-10 and 15. Other inputs
      (rest lengths, rigid placement, normals, previous states, masses) are constants: no
      gradient flows to them (for Eq. 16 the paper requires it).
    * Auxiliary inputs are shared by the batch (shape without B) or given per batch item.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterable, Sequence

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from hairwarp import _validate, _warp
from hairwarp._validate import check_positive, check_same_dtype, check_tensor
from hairwarp.config import STRAND_TERMS, EnergyConfig
from hairwarp.kernels import strand_energies as strand_kernels
from hairwarp.ops.reductions import row_sums

LAYOUTS = ("auto", "strand", "vertex")

_TERM_INDEX = {name: i for i, name in enumerate(STRAND_TERMS)}
# The optional inputs each term needs (besides x); a term whose inputs are missing is skipped.
_TERM_INPUTS = {
    "stretch": ("rest_lengths",),
    "bending": (),
    "auxiliary": ("rigid",),
    "smoothness": (),
    "gravity": (),
    "root_alignment": ("scalp_normals",),
    "inertia": ("prev", "prev2"),
}
_VEC3 = {torch.float32: wp.vec3, torch.float64: wp.vec3d}
_DEFAULTS = EnergyConfig()


def compute_rest_lengths(p_init: torch.Tensor) -> torch.Tensor:
    """Rest lengths l0 of Eq. 7, |p_{i+1} - p_i| of the initial (generated) hair.

    Args:
        p_init: initial hair positions [m], `(..., M, N, 3)`, N >= 2.

    Returns:
        `(..., M, N-1)` segment lengths [m], detached (they are constants of Eq. 7).
    """
    check_tensor("p_init", p_init, shape=("...", None, None, 3))
    if p_init.dim() < 3 or p_init.shape[-2] < 2:
        raise ValueError(f"p_init: expected shape (..., M, N >= 2, 3), got {tuple(p_init.shape)}")
    p = p_init.detach()
    return torch.linalg.vector_norm(p[..., 1:, :] - p[..., :-1, :], dim=-1)


# ---------------------------------------------------------------- validation
def _check_positions(x) -> tuple[torch.Tensor, bool]:
    """Validate `x`; return it as `(B, M, N, 3)` and whether it was unbatched."""
    check_tensor("x", x)
    if x.dim() == 3:
        x4, unbatched = x.unsqueeze(0), True
    elif x.dim() == 4:
        x4, unbatched = x, False
    else:
        raise ValueError(f"x: expected shape (B, M, N, 3) or (M, N, 3), got {tuple(x.shape)}")
    if x4.shape[-1] != 3:
        raise ValueError(f"x: expected shape (B, M, N, 3) or (M, N, 3), got {tuple(x.shape)}")
    if x4.shape[1] < 1:
        raise ValueError(f"x: expected at least one strand (M >= 1), got shape {tuple(x.shape)}")
    if x4.shape[2] < 3:
        raise ValueError(f"x: expected at least 3 vertices per strand (N >= 3), got shape {tuple(x.shape)}")
    _warp.warp_device(x.device)  # cpu or cuda only
    return x4, unbatched


def _check_input(
    name: str, t, x4: torch.Tensor, tail: tuple[int, ...], vec3: bool
) -> tuple[torch.Tensor, int]:
    """Validate an auxiliary input of shape `tail` (shared) or `(B,) + tail` (per batch item).

    Returns the contiguous, detached tensor and its batch stride as the kernels index it (in
    vec3 elements when `vec3`, else in scalars; 0 when shared by the batch).
    """
    check_tensor(name, t, device=x4.device)
    check_same_dtype(x=x4, **{name: t})
    batch = x4.shape[0]
    if tuple(t.shape) == tail:
        stride = 0
    elif tuple(t.shape) == (batch,) + tail:
        stride = 1
    else:
        want = "(" + ", ".join(str(d) for d in tail) + ")"
        raise ValueError(f"{name}: expected shape {want} or ({batch}, {want[1:]}, got {tuple(t.shape)}")
    per_item = 1
    for d in tail[:-1] if vec3 else tail:
        per_item *= d
    return t.detach().contiguous(), stride * per_item


def _check_float(name: str, value) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{name}: expected a finite number, got {value}")
    return value


def _check_gravity(gravity) -> tuple[float, float, float]:
    try:
        g = tuple(float(c) for c in gravity)
    except (TypeError, ValueError):
        raise ValueError(f"gravity: expected 3 numbers [m/s^2], got {gravity!r}") from None
    if len(g) != 3:
        raise ValueError(f"gravity: expected 3 numbers [m/s^2], got {gravity!r}")
    for c in g:
        _check_float("gravity", c)
    return g


def _check_segments(name: str, segments) -> int:
    if isinstance(segments, bool) or not isinstance(segments, int) or segments < 0:
        raise ValueError(f"{name}: expected an integer >= 0, got {segments!r}")
    return segments


def _check_layout(layout: str) -> str:
    if layout not in LAYOUTS:
        raise ValueError(f"layout: expected one of {LAYOUTS}, got {layout!r}")
    return layout


# ---------------------------------------------------------------- launch
class _StrandEnergies(torch.autograd.Function):
    """Fused forward; the gradient of the total comes from the same launch."""

    @staticmethod
    def forward(ctx, x4, launch_args):
        inputs, scales, layout, compute_gradient = launch_args
        per_term, gradient = _launch(x4, inputs, scales, layout, compute_gradient=compute_gradient)
        ctx.save_for_backward(gradient)
        ctx.mark_non_differentiable(per_term)
        return per_term.sum(dim=1), per_term

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_total, grad_per_term):
        (gradient,) = ctx.saved_tensors
        if grad_total is None:
            return None, None
        return grad_total.view(-1, 1, 1, 1) * gradient, None


_KERNELS = {
    "strand": strand_kernels.strand_energies_per_strand_kernel,
    "vertex": strand_kernels.strand_energies_per_vertex_kernel,
}
_placeholders: dict = {}
def _placeholder(vec3: bool, dtype: torch.dtype, device: torch.device) -> wp.array:
    """A cached one-element Warp array standing in for the input of a term that is off.

    The kernels never read (or write) it; caching spares a torch allocation and a Warp view
    per call. The torch tensor is kept alive beside its view.
    """
    key = (vec3, dtype, device)
    if key not in _placeholders:
        t = torch.zeros((1, 3) if vec3 else (1,), dtype=dtype, device=device)
        _placeholders[key] = (t, _warp.as_warp(t, vec3=vec3))
    return _placeholders[key][1]


# The fused launch's plan per (thread, layout, device, dtype, shape, gradient or not, which inputs
# with which batch strides, scales): an eager call repeats the same launch with other tensors,
# and packing its 31 parameters cost ~35 us of host time per call on a 2-core CPU
# (docs/contact.md 12); a plan only points its arrays at this call's tensors. Bounded: cleared
# when full.
_plans: dict = {}
_MAX_PLANS = 64
# The kernel's array arguments by position: x, the optional inputs, the two outputs.
_X = 0
_INPUT_POSITIONS = {"rest_lengths": 1, "rigid": 3, "scalp_normals": 5, "prev": 7, "prev2": 9, "vertex_mass": 11}
_ENERGY, _GRADIENT = 29, 30


def _scales_key(scales: dict) -> bytes:
    """The scales as a key, packed as doubles (bit for bit: -0.0 is not 0.0)."""
    values = [value for name, value in scales.items() if name != "weight_g"]
    return struct.pack(f"<{len(values) + 3}d", *values, *scales["weight_g"])


def _plan(x4, inputs, scales, layout, compute_gradient, energy, gradient) -> _warp.LaunchPlan:
    """The fused launch's plan for these inputs, built on first use (see `_plans`); its varying
    arrays are x, the given inputs (in `inputs`' order), the energies and the gradient (if any).
    """
    batch, num_strands, num_vertices, _ = x4.shape
    dtype, device = x4.dtype, x4.device
    key = (threading.get_ident(), layout, device, dtype, x4.shape, compute_gradient,
           tuple((name, stride) for name, (_, stride) in inputs.items()), _scales_key(scales))
    plan = _plans.get(key)
    if plan is not None:
        return plan

    def view(name, vec3=True):
        if name not in inputs:
            return _placeholder(vec3, dtype, device), 0
        t, stride = inputs[name]
        return _warp.as_warp(t, vec3=vec3), stride

    rest, rest_stride = view("rest_lengths", vec3=False)
    rigid, rigid_stride = view("rigid")
    normals, normals_stride = view("scalp_normals")
    prev, prev_stride = view("prev")
    prev2, prev2_stride = view("prev2")
    mass, _ = view("vertex_mass", vec3=False)
    s = scales

    def scalar(value):
        return _warp.scalar(value, dtype)

    arguments = [
        _warp.as_warp(x4, vec3=True),
        rest,
        rest_stride,
        rigid,
        rigid_stride,
        normals,
        normals_stride,
        prev,
        prev_stride,
        prev2,
        prev2_stride,
        mass,
        int("vertex_mass" in inputs),
        scalar(s["mass_value"]),
        _VEC3[dtype](*s["weight_g"]),
        scalar(s["stretch"]),
        scalar(s["bending"]),
        scalar(s["bending_eps"]),
        scalar(s["auxiliary"]),
        scalar(s["smoothness"]),
        int(s["gravity_on"]),
        scalar(s["root_alignment"]),
        scalar(s["root_constant"]),
        scalar(s["root_eps"]),
        int(s["root_segments"]),
        scalar(s["inertia"]),
        num_strands,
        num_vertices,
        int(compute_gradient),
    ]
    outputs = [
        _warp.as_warp(energy),
        _placeholder(True, dtype, device) if gradient is None else _warp.as_warp(gradient, vec3=True),
    ]
    varying = (_X, *(_INPUT_POSITIONS[name] for name in inputs), _ENERGY) + ((_GRADIENT,) if compute_gradient else ())
    if len(_plans) >= _MAX_PLANS:
        _plans.clear()
    plan = _plans[key] = _warp.LaunchPlan(
        _KERNELS[layout], energy.numel() // len(STRAND_TERMS), arguments, outputs, _warp.warp_device(device), varying
    )
    return plan


def _launch(x4, inputs, scales, layout, *, compute_gradient):
    """One fused launch; returns per-term energies `(B, 7)` and dE_total/dx (or None)."""
    batch, num_strands, num_vertices, _ = x4.shape
    dtype, device = x4.dtype, x4.device
    x4 = x4.detach().contiguous()
    if layout == "auto":
        layout = "vertex" if device.type == "cuda" else "strand"
    rows = num_strands if layout == "strand" else num_strands * num_vertices
    # Term-major (see `write_energies`): (terms, B, rows), summed over rows below.
    energy = torch.empty((len(STRAND_TERMS), batch, rows), dtype=dtype, device=device)
    gradient = torch.empty_like(x4) if compute_gradient else None
    plan = _plan(x4, inputs, scales, layout, compute_gradient, energy, gradient)
    tensors = [x4, *(t for t, _ in inputs.values()), energy]
    if gradient is not None:
        tensors.append(gradient)
    # Every tensor here is torch's: the launch goes on torch's stream without `launch_scope`.
    plan.launch(tensors, _warp.torch_stream(device))
    return row_sums(energy.view(-1, rows)).view(len(STRAND_TERMS), batch).t(), gradient


def _evaluate(
    x,
    *,
    weights: dict[str, float],
    required: Iterable[str] = (),
    rest_lengths=None,
    rigid=None,
    scalp_normals=None,
    prev=None,
    prev2=None,
    vertex_mass=_DEFAULTS.vertex_mass,
    gravity: Sequence[float] = _DEFAULTS.gravity,
    bending_eps: float = _DEFAULTS.bending_eps,
    root_segments: int = _DEFAULTS.root_alignment_segments,
    root_eps: float = _DEFAULTS.root_alignment_eps,
    time_step: float = _DEFAULTS.time_step,
    layout: str = "auto",
    names: dict[str, str] | None = None,
    reference_strand_count: int = 0,
):
    """Validate, pick the active terms, launch; returns (total, per-term dict) in x's batch shape.

    The means over strands divide by `reference_strand_count` where it is not 0
    (`EnergyConfig.reference_strand_count`).

    Scalar parameters are reported in errors by their `EnergyConfig` field names unless `names`
    maps a field name to the caller's argument name (the per-term functions say "weight").
    """
    names = names or {}

    def arg(field):
        return names.get(field, field)

    x4, unbatched = _check_positions(x)
    layout = _check_layout(layout)
    batch, num_strands, num_vertices, _ = x4.shape
    required = set(required)

    given = {}
    tails = {
        "rest_lengths": (num_strands, num_vertices - 1),
        "rigid": (num_strands, num_vertices, 3),
        "scalp_normals": (num_strands, 3),
        "prev": (num_strands, num_vertices, 3),
        "prev2": (num_strands, num_vertices, 3),
    }
    for name, t in (
        ("rest_lengths", rest_lengths),
        ("rigid", rigid),
        ("scalp_normals", scalp_normals),
        ("prev", prev),
        ("prev2", prev2),
    ):
        if t is not None:
            given[name] = _check_input(name, t, x4, tails[name], vec3=name != "rest_lengths")

    weights = {name: _check_float(arg(f"{name}_weight"), w) for name, w in weights.items()}
    bending_eps = check_positive(arg("bending_eps"), bending_eps, allow_zero=True)
    root_eps = check_positive(arg("root_alignment_eps"), root_eps, allow_zero=True)
    root_segments = _check_segments(arg("root_alignment_segments"), root_segments)
    time_step = check_positive("time_step", time_step)
    gravity = _check_gravity(gravity)
    if isinstance(vertex_mass, torch.Tensor):
        check_tensor("vertex_mass", vertex_mass, shape=(num_strands, num_vertices), device=x4.device)
        if vertex_mass.numel() == 0:
            raise ValueError("vertex_mass: expected a non-empty (M, N) tensor")
        check_same_dtype(x=x4, vertex_mass=vertex_mass)
        # Like the NaN scan, a host read: skipped when finite checks are off (hot loops).
        if _validate.finite_checks_enabled() and bool((vertex_mass < 0).any()):
            raise ValueError("vertex_mass: expected non-negative masses [kg]")
        given["vertex_mass"] = (vertex_mass.detach().contiguous(), 0)
        mass_value = 0.0
    else:
        mass_value = check_positive("vertex_mass", vertex_mass, allow_zero=True)

    # Active terms: a non-zero weight and every input present. The per-term functions name
    # their term in `required`: there a missing input is an error, not a silent zero.
    active = []
    for name in STRAND_TERMS:
        if name not in weights:
            continue
        missing = [i for i in _TERM_INPUTS[name] if i not in given]
        if missing:
            if name in required:
                raise ValueError(f"{missing[0]}: required by the {name} term, got None")
            continue
        if weights[name] != 0.0:
            active.append(name)

    m, n = reference_strand_count or num_strands, num_vertices
    # Eq. 15 sums the first k' moving segments i = 1..k'; a strand of N vertices has N - 2.
    k_align = min(root_segments, n - 2)
    w = {name: (weights[name] if name in active else 0.0) for name in STRAND_TERMS}
    if "root_alignment" in active and k_align == 0:
        active.remove("root_alignment")
        w["root_alignment"] = 0.0
    weight_g = tuple(w["gravity"] * c for c in gravity)
    scales = {
        "stretch": w["stretch"] / (m * (n - 1)),  # Eq. 7
        "bending": w["bending"],  # Eq. 8 (no normalisation in the paper)
        "bending_eps": bending_eps,
        "auxiliary": w["auxiliary"] / (3 * m * n),  # Eq. 9
        "smoothness": w["smoothness"] / (m * (n - 2)),  # Eq. 10
        "weight_g": weight_g,  # Eq. 11
        "gravity_on": any(c != 0.0 for c in weight_g),
        "mass_value": mass_value,
        "root_alignment": w["root_alignment"] / (m * k_align) if k_align else 0.0,  # Eq. 15
        "root_constant": w["root_alignment"] / m,
        "root_eps": root_eps,
        "root_segments": k_align,
        "inertia": w["inertia"] / (m * (n - 2) * 2.0 * time_step * time_step),  # Eq. 16
    }

    if batch == 0 or not active:
        # Nothing to launch; keep the result attached to x so callers can still backpropagate.
        total = x4.sum(dim=(1, 2, 3)) * 0.0
        per_term = torch.zeros((batch, len(STRAND_TERMS)), dtype=x4.dtype, device=x4.device)
    else:
        compute_gradient = torch.is_grad_enabled() and x4.requires_grad
        total, per_term = _StrandEnergies.apply(x4, (given, scales, layout, compute_gradient))
    if unbatched:
        total, per_term = total[0], per_term[0]
    return total, {name: per_term[..., _TERM_INDEX[name]] for name in active}


# ---------------------------------------------------------------- public API
def strand_energies(
    x: torch.Tensor,
    rest_lengths: torch.Tensor | None,
    config: EnergyConfig | None = None,
    *,
    rigid: torch.Tensor | None = None,
    scalp_normals: torch.Tensor | None = None,
    prev: torch.Tensor | None = None,
    prev2: torch.Tensor | None = None,
    vertex_mass: torch.Tensor | None = None,
    terms: Iterable[str] | None = None,
    layout: str = "auto",
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """All strand terms of Section 3.4 (Eq. 7-11, 15, 16) in one fused launch.

    A term is evaluated when it is selected (`terms`), its weight in `config` is non-zero and
    its inputs are given (stretch needs `rest_lengths`, auxiliary `rigid`, root alignment
    `scalp_normals` and `config.root_alignment_segments` > 0, inertia `prev` and `prev2`); the
    others are skipped and absent from `per_term`. The gradient of the weighted total with
    respect to `x` is computed in the same pass as the energies.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64, N >= 3.
        rest_lengths: rest segment lengths l0 of Eq. 7 [m], `(M, N-1)` or `(B, M, N-1)`
            (see `compute_rest_lengths`), or None to skip stretch.
        config: weights and constants (`EnergyConfig()` when None); the means of Eq. 7, 9, 10,
            15 and 16 divide by its `reference_strand_count` (the per-term functions below, which
            take bare weights, divide by the M strands given, as the paper writes them).
        rigid: rigidly posed hair P_rigid of Eq. 9 [m], `(M, N, 3)` or `(B, M, N, 3)`.
        scalp_normals: unit scalp normals n_s at the roots (Eq. 15), `(M, 3)` or `(B, M, 3)`.
        prev: positions at t-1 [m] (Eq. 16), like `rigid`; constant (no gradient).
        prev2: positions at t-2 [m] (Eq. 16), like `rigid`; constant (no gradient).
        vertex_mass: optional per-vertex masses [kg], `(M, N)` (entries of vertices 0 and 1
            unused), replacing the scalar `config.vertex_mass` in Eq. 11 and 16.
        terms: restrict to these names of `hairwarp.config.STRAND_TERMS` (ablations); a named
            term whose input is missing is skipped like any other.
        layout: "strand" (one thread per strand; the CPU default), "vertex" (one thread per
            vertex; the CUDA default) or "auto".

    Returns:
        (total, per_term): `total` `(B,)` (or `()` for unbatched `x`), the weighted sum of the
        evaluated terms, differentiable w.r.t. `x` (zero gradient at vertices 0 and 1);
        `per_term` maps each evaluated term's name to its weighted value, same shape, not
        differentiable (from the same launch; they sum to `total`).

    Raises:
        ValueError: a bad shape, dtype, device, NaN/Inf, term name or parameter, naming it.
    """
    if config is None:
        config = EnergyConfig()
    if not isinstance(config, EnergyConfig):
        raise ValueError(f"config: expected an EnergyConfig, got {type(config).__name__}")
    all_weights = config.weights()
    if terms is None:
        names = STRAND_TERMS
    else:
        if isinstance(terms, str):
            raise ValueError(f"terms: expected an iterable of term names, got the string {terms!r}")
        names = tuple(terms)
        for name in names:
            if name not in _TERM_INDEX:
                raise ValueError(f"terms: unknown strand term {name!r}; expected names from {STRAND_TERMS}")
    return _evaluate(
        x,
        weights={name: all_weights[name] for name in names},
        rest_lengths=rest_lengths,
        rigid=rigid,
        scalp_normals=scalp_normals,
        prev=prev,
        prev2=prev2,
        vertex_mass=vertex_mass if vertex_mass is not None else config.vertex_mass,
        gravity=config.gravity,
        bending_eps=config.bending_eps,
        root_segments=config.root_alignment_segments,
        root_eps=config.root_alignment_eps,
        time_step=config.time_step,
        layout=layout,
        reference_strand_count=config.reference_strand_count,
    )


def stretch_energy(
    x: torch.Tensor,
    rest_lengths: torch.Tensor,
    weight: float = _DEFAULTS.stretch_weight,
    *,
    layout: str = "auto",
) -> torch.Tensor:
    """Inextensibility loss of Eq. 7: k_s / (M (N-1)) sum_s sum_i (|p_{i+1} - p_i| - l0_i)^2.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        rest_lengths: rest lengths l0 [m], `(M, N-1)` or `(B, M, N-1)`.
        weight: k_s [J/m^2].
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy, differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
        Where a segment has zero length its gradient is taken as 0 (|e| has no derivative there).
    """
    total, _ = _evaluate(
        x,
        weights={"stretch": weight},
        required=("stretch",),
        rest_lengths=rest_lengths,
        layout=layout,
        names={"stretch_weight": "weight"},
    )
    return total


def bending_energy(
    x: torch.Tensor,
    weight: float = _DEFAULTS.bending_weight,
    eps: float = _DEFAULTS.bending_eps,
    *,
    layout: str = "auto",
) -> torch.Tensor:
    """Bending loss of Eq. 8: k_b sum_s sum_{i=0}^{N-3} alpha_{s,i}.

    alpha = arccos(clamp(theta, -1 + eps, 1 - eps)) with theta = e_i / (|e_i| + eps) .
    e_{i+1} / (|e_{i+1}| + eps), and alpha = 0 unless both edges are longer than eps. The eps in
    the normalisation makes theta slightly below 1 for a straight strand, so a straight joint
    has alpha ~ sqrt(2 eps (1/|e_i| + 1/|e_{i+1}|)) rather than 0, as in the paper's formula.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        weight: k_b [J/rad].
        eps: epsilon of Eq. 8 [m], >= 0.
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy, differentiable w.r.t. `x` (zero gradient at vertices 0, 1, and
        where the clamp is active or the joint is invalid).
    """
    total, _ = _evaluate(
        x,
        weights={"bending": weight},
        bending_eps=eps,
        layout=layout,
        names={"bending_weight": "weight", "bending_eps": "eps"},
    )
    return total


def auxiliary_energy(
    x: torch.Tensor, rigid: torch.Tensor, weight: float = _DEFAULTS.auxiliary_weight, *, layout: str = "auto"
) -> torch.Tensor:
    """Auxiliary loss of Eq. 9: lambda_aux / (3 M N) sum_s sum_v |p_v - p_v^rigid|^2.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        rigid: rigidly posed hair [m], `(M, N, 3)` or `(B, M, N, 3)` (constant).
        weight: lambda_aux [J/m^2].
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy, differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
    """
    total, _ = _evaluate(
        x,
        weights={"auxiliary": weight},
        required=("auxiliary",),
        rigid=rigid,
        layout=layout,
        names={"auxiliary_weight": "weight"},
    )
    return total


def smoothness_energy(
    x: torch.Tensor, weight: float = _DEFAULTS.smoothness_weight, *, layout: str = "auto"
) -> torch.Tensor:
    """Smoothness loss of Eq. 10: lambda_smooth / (M (N-2)) sum_{s, v=1..N-2} |p_{v+1} - 2 p_v + p_{v-1}|^2.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        weight: lambda_smooth [J/m^2].
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy, differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
    """
    total, _ = _evaluate(
        x, weights={"smoothness": weight}, layout=layout, names={"smoothness_weight": "weight"}
    )
    return total


def gravity_energy(
    x: torch.Tensor,
    vertex_mass: float | torch.Tensor = _DEFAULTS.vertex_mass,
    gravity: Sequence[float] = _DEFAULTS.gravity,
    weight: float = _DEFAULTS.gravity_weight,
    *,
    layout: str = "auto",
) -> torch.Tensor:
    """Gravity loss of Eq. 11: -weight sum_s sum_{v>=2} m_v g . p_v [J], moving vertices only.

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        vertex_mass: mass per moving vertex [kg], a number or an `(M, N)` tensor (entries of
            vertices 0 and 1 unused).
        gravity: acceleration g [m/s^2], 3 numbers (y up: (0, -9.81, 0)).
        weight: dimensionless multiplier (1 = physical potential energy).
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy [J], differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
    """
    total, _ = _evaluate(
        x,
        weights={"gravity": weight},
        vertex_mass=vertex_mass,
        gravity=gravity,
        layout=layout,
        names={"gravity_weight": "weight"},
    )
    return total


def root_alignment_energy(
    x: torch.Tensor,
    scalp_normals: torch.Tensor,
    weight: float = _DEFAULTS.root_alignment_weight,
    segments: int = _DEFAULTS.root_alignment_segments,
    eps: float = _DEFAULTS.root_alignment_eps,
    *,
    layout: str = "auto",
) -> torch.Tensor:
    """Root alignment loss of Eq. 15: lambda_root (1 - 1/(M k') sum_s sum_{i=1}^{k'} d_hat_{s,i} . n_s).

    d_hat_{s,i} = (p_{i+1} - p_i) / (|p_{i+1} - p_i| + eps): segment 1 joins the fixed vertex 1
    to the first moving vertex. k' = min(segments, N - 2) (a strand has N - 2 such segments);
    k' = 0 turns the term off (energy 0).

    Args:
        x: hair positions [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        scalp_normals: unit scalp normals at the roots, `(M, 3)` or `(B, M, 3)` (posed).
        weight: lambda_root [J].
        segments: k'_align, number of moving segments aligned with the normal (>= 0).
        eps: epsilon_norm [m], >= 0.
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy, differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
    """
    total, _ = _evaluate(
        x,
        weights={"root_alignment": weight},
        required=("root_alignment",),
        scalp_normals=scalp_normals,
        root_segments=segments,
        root_eps=eps,
        layout=layout,
        names={
            "root_alignment_weight": "weight",
            "root_alignment_segments": "segments",
            "root_alignment_eps": "eps",
        },
    )
    return total


def inertia_energy(
    x: torch.Tensor,
    prev: torch.Tensor,
    prev2: torch.Tensor,
    vertex_mass: float | torch.Tensor = _DEFAULTS.vertex_mass,
    time_step: float = _DEFAULTS.time_step,
    weight: float = _DEFAULTS.inertia_weight,
    *,
    layout: str = "auto",
) -> torch.Tensor:
    """Inertia loss of Eq. 16: lambda / (M N_mov) sum_{s, v>=2} m_v / (2 dt^2) |p_v - p_proj_v|^2.

    p_proj = 2 p^{t-1} - p^{t-2}, the constant-velocity prediction; N_mov = N - 2.

    Args:
        x: hair positions at t [m], `(B, M, N, 3)` or `(M, N, 3)`, float32 or float64.
        prev: positions at t-1 [m], `(M, N, 3)` or `(B, M, N, 3)`; no gradient flows to it.
        prev2: positions at t-2 [m], like `prev`; no gradient flows to it.
        vertex_mass: mass per moving vertex [kg], a number or an `(M, N)` tensor.
        time_step: Delta t [s], > 0.
        weight: lambda_inertia (dimensionless).
        layout: "auto", "strand" or "vertex" (see `strand_energies`).

    Returns:
        `(B,)` or `()` energy [J], differentiable w.r.t. `x` (zero gradient at vertices 0, 1).
    """
    total, _ = _evaluate(
        x,
        weights={"inertia": weight},
        required=("inertia",),
        prev=prev,
        prev2=prev2,
        vertex_mass=vertex_mass,
        time_step=time_step,
        layout=layout,
        names={"inertia_weight": "weight"},
    )
    return total
