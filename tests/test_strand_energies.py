"""Strand energies (HairFormer Eq. 7-11, 15, 16): the fused Warp kernels against numpy float64
references written from the equations, the plain-torch reference, finite differences, the two
launch layouts, fixed vertices, degenerate strands and bad input."""

import importlib
import itertools
import math
from typing import Any

import numpy as np
import pytest
import torch
import warp as wp

from hairwarp import _warp
from hairwarp.config import STRAND_TERMS, EnergyConfig
from hairwarp.kernels import strand_energies as strand_kernels
from references import strand_energies as ref

# `hairwarp.ops.strand_energies` is also the name of the fused function that `hairwarp.ops`
# exports, which shadows the submodule as an attribute: take the modules from the import system.
ops = importlib.import_module("hairwarp.ops.strand_energies")
torch_ref = importlib.import_module("hairwarp.torch_reference.strand_energies")

LAYOUTS = ("strand", "vertex")
DTYPES = (torch.float64, torch.float32)

# float64: the kernels and numpy sum the same terms in different orders (round-off only).
RTOL_FLOAT64 = 1e-10
# float32: ~1e-7 per operation, accumulated over a few dozen terms and arccos near small angles.
RTOL_FLOAT32 = 2e-4
# Central differences in float64 with h = 1e-6 of the segment length: truncation ~h^2 and
# round-off ~1e-16 / 1e-6 relative to the largest gradient entry.
FD_RTOL = 1e-6
FD_STEP = 1e-6

# Weights chosen so that every term matters at the test sizes (not the paper's defaults).
CONFIG = EnergyConfig(
    stretch_weight=50.0,
    bending_weight=0.2,
    bending_eps=1e-6,
    auxiliary_weight=30.0,
    smoothness_weight=80.0,
    vertex_mass=2e-3,
    gravity_weight=1.5,
    root_alignment_weight=0.7,
    root_alignment_segments=2,
    root_alignment_eps=1e-8,
    inertia_weight=1e-3,
    time_step=1.0 / 60.0,
    reference_strand_count=0,  # the paper's means over the M strands given, as the references write them
)


def rtol_for(dtype):
    return RTOL_FLOAT64 if dtype == torch.float64 else RTOL_FLOAT32


def make_strands(rng, batch, strands, vertices, segment=0.01):
    """Curved strands: segments of 0.5-1.5 `segment` [m], turning 0.15-0.6 rad at every joint
    (away from the arccos clamp of Eq. 8), roots scattered over a 10 cm patch."""
    x = np.zeros((batch, strands, vertices, 3))
    for b, s in itertools.product(range(batch), range(strands)):
        p = rng.normal(size=3) * 0.05
        d = rng.normal(size=3) + np.array([0.0, -1.0, 0.0])
        d /= np.linalg.norm(d)
        for v in range(vertices):
            x[b, s, v] = p
            p = p + segment * rng.uniform(0.5, 1.5) * d
            axis = np.cross(d, rng.normal(size=3))
            axis /= np.linalg.norm(axis)
            angle = rng.uniform(0.15, 0.6)
            d = d * math.cos(angle) + np.cross(axis, d) * math.sin(angle)
    return x


def make_inputs(rng, x, shared=True, segment=0.01):
    """Auxiliary inputs for `x` (B, M, N, 3) as numpy, shared by the batch or per item."""
    batch, strands, vertices, _ = x.shape
    lead = () if shared else (batch,)
    source = x[0] if shared else x
    lengths = np.linalg.norm(source[..., 1:, :] - source[..., :-1, :], axis=-1)
    normals = rng.normal(size=lead + (strands, 3))
    return {
        "rest_lengths": lengths * (1.0 + 0.2 * rng.normal(size=lengths.shape)),
        "rigid": source + 0.3 * segment * rng.normal(size=source.shape),
        "scalp_normals": normals / np.linalg.norm(normals, axis=-1, keepdims=True),
        "prev": x + 0.2 * segment * rng.normal(size=x.shape),
        "prev2": x + 0.2 * segment * rng.normal(size=x.shape),
    }


def to_torch(arrays, dtype, device="cpu"):
    return {k: torch.tensor(v, dtype=dtype, device=device) for k, v in arrays.items()}


def batched(a, batch, tail_dims):
    """Broadcast a shared numpy input to (B,) + its shape (what the numpy references take)."""
    return a if a.ndim == tail_dims + 1 else np.broadcast_to(a, (batch,) + a.shape)


def reference_term(term, x, inputs, config, mass=None):
    """numpy value of one weighted term, (B,)."""
    batch, strands, vertices, _ = x.shape
    if mass is None:
        mass = np.full((strands, vertices), config.vertex_mass)
    w = config.weights()
    if term == "stretch":
        return ref.stretch(x, batched(inputs["rest_lengths"], batch, 2), w[term])
    if term == "bending":
        return ref.bending(x, w[term], config.bending_eps)
    if term == "auxiliary":
        return ref.auxiliary(x, batched(inputs["rigid"], batch, 3), w[term])
    if term == "smoothness":
        return ref.smoothness(x, w[term])
    if term == "gravity":
        return ref.gravity(x, mass, config.gravity, w[term])
    if term == "root_alignment":
        return ref.root_alignment(
            x,
            batched(inputs["scalp_normals"], batch, 2),
            w[term],
            config.root_alignment_segments,
            config.root_alignment_eps,
        )
    if term == "inertia":
        return ref.inertia(x, inputs["prev"], inputs["prev2"], mass, config.time_step, w[term])
    raise KeyError(term)


def call_term(module, term, x, t, config, **kw):
    """One weighted term through the per-term public function of `module` (ops or torch_ref)."""
    w = config.weights()
    if term == "stretch":
        return module.stretch_energy(x, t["rest_lengths"], w[term], **kw)
    if term == "bending":
        return module.bending_energy(x, w[term], config.bending_eps, **kw)
    if term == "auxiliary":
        return module.auxiliary_energy(x, t["rigid"], w[term], **kw)
    if term == "smoothness":
        return module.smoothness_energy(x, w[term], **kw)
    if term == "gravity":
        mass = t.get("vertex_mass", config.vertex_mass)
        return module.gravity_energy(x, mass, config.gravity, w[term], **kw)
    if term == "root_alignment":
        return module.root_alignment_energy(
            x, t["scalp_normals"], w[term], config.root_alignment_segments, config.root_alignment_eps, **kw
        )
    if term == "inertia":
        mass = t.get("vertex_mass", config.vertex_mass)
        return module.inertia_energy(x, t["prev"], t["prev2"], mass, config.time_step, w[term], **kw)
    raise KeyError(term)


def fused(x, t, config=CONFIG, **kw):
    return ops.strand_energies(
        x,
        t.get("rest_lengths"),
        config,
        rigid=t.get("rigid"),
        scalp_normals=t.get("scalp_normals"),
        prev=t.get("prev"),
        prev2=t.get("prev2"),
        **kw,
    )


def as_numpy(a):
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().double().numpy()
    return np.asarray(a, dtype=np.float64)


def assert_close(actual, expected, rtol, what):
    actual = as_numpy(actual)
    expected = as_numpy(expected)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    scale = np.abs(expected).max()
    assert scale > 0.0, f"{what}: the reference is zero, the comparison would test nothing"
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * scale, err_msg=what)


def fd_gradient(energy, x):
    """Central differences of `energy(x)` (B,) over the moving vertices (v >= 2) of x (B, M, N, 3).

    Batch items are independent, so one pair of evaluations gives the derivative for all of them.
    """
    grad = torch.zeros_like(x)
    h = FD_STEP * float(torch.linalg.vector_norm(x[..., 1:, :] - x[..., :-1, :], dim=-1).mean())
    for s, v, c in itertools.product(range(x.shape[1]), range(2, x.shape[2]), range(3)):
        xp, xm = x.clone(), x.clone()
        xp[:, s, v, c] += h
        xm[:, s, v, c] -= h
        grad[:, s, v, c] = (energy(xp) - energy(xm)) / (2.0 * h)
    return grad


# ---------------------------------------------------------------- values
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("term", STRAND_TERMS)
def test_term_matches_numpy_reference(term, dtype, layout, device, rng):
    x_np = make_strands(rng, 2, 3, 7)
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, dtype, device)
    value = call_term(ops, term, torch.tensor(x_np, dtype=dtype, device=device), t, CONFIG, layout=layout)
    assert value.shape == (2,) and value.dtype == dtype and value.device.type == device.type
    assert_close(value, reference_term(term, x_np, inputs, CONFIG), rtol_for(dtype), term)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_fused_total_is_the_sum_of_the_terms(layout, device, rng):
    x_np = make_strands(rng, 3, 4, 8)
    inputs = make_inputs(rng, x_np, shared=False)
    t = to_torch(inputs, torch.float64, device)
    x = torch.tensor(x_np, device=device)
    total, per_term = fused(x, t, layout=layout)
    assert tuple(per_term) == STRAND_TERMS
    assert total.shape == (3,)
    assert_close(total, sum(per_term.values()), RTOL_FLOAT64, "total vs sum of per-term")
    for term, value in per_term.items():
        assert not value.requires_grad
        assert_close(value, reference_term(term, x_np, inputs, CONFIG), RTOL_FLOAT64, term)
        assert_close(value, call_term(ops, term, x, t, CONFIG, layout=layout), RTOL_FLOAT64, term)


def test_torch_reference_agrees_in_values_and_gradients(device, rng):
    x_np = make_strands(rng, 2, 3, 9)
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, torch.float64, device)
    x_warp = torch.tensor(x_np, device=device, requires_grad=True)
    x_torch = torch.tensor(x_np, device=device, requires_grad=True)
    total, per_term = fused(x_warp, t)
    total_ref, per_term_ref = torch_ref.strand_energies(
        x_torch,
        t["rest_lengths"],
        CONFIG,
        rigid=t["rigid"],
        scalp_normals=t["scalp_normals"],
        prev=t["prev"],
        prev2=t["prev2"],
    )
    assert tuple(per_term_ref) == tuple(per_term) == STRAND_TERMS
    for term in STRAND_TERMS:
        assert_close(per_term[term], per_term_ref[term], RTOL_FLOAT64, term)
    weights = torch.tensor([0.5, -2.0], dtype=torch.float64, device=device)  # non-uniform upstream
    (total * weights).sum().backward()
    (total_ref * weights).sum().backward()
    assert float(x_torch.grad.abs().max()) > 0.0
    assert_close(x_warp.grad, x_torch.grad, 1e-9, "gradient vs torch autograd")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_reference_strand_count_divides_the_means_by_it(layout, device, rng):
    """`reference_strand_count` R: Eq. 7, 9, 10, 15, 16 divide by R instead of M (the numpy
    means times M / R), the sums (bending, gravity) unchanged; the torch reference agrees in
    values and gradients; and a groom of the same strands twice over has twice the energy, each
    strand the share it has in a groom of R (the paper's means give the doubled groom the same
    energy: each strand half its share)."""
    x_np = make_strands(rng, 2, 3, 8)
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, torch.float64, device)
    config = CONFIG.replace(reference_strand_count=12)
    x = torch.tensor(x_np, device=device, requires_grad=True)
    total, per_term = fused(x, t, config, layout=layout)
    means = ("stretch", "auxiliary", "smoothness", "root_alignment", "inertia")
    for term, value in per_term.items():
        expected = reference_term(term, x_np, inputs, CONFIG) * (3 / 12 if term in means else 1.0)
        assert_close(value, expected, RTOL_FLOAT64, term)
    x_ref = torch.tensor(x_np, device=device, requires_grad=True)
    total_ref, _ = torch_ref.strand_energies(x_ref, t["rest_lengths"], config, rigid=t["rigid"],
                                             scalp_normals=t["scalp_normals"], prev=t["prev"], prev2=t["prev2"])
    assert_close(total, total_ref, RTOL_FLOAT64, "total vs torch reference")
    total.sum().backward()
    total_ref.sum().backward()
    assert_close(x.grad, x_ref.grad, 1e-9, "gradient vs torch reference")

    doubled = {k: torch.cat([v, v], dim=-2 if k == "scalp_normals" else (-2 if k == "rest_lengths" else -3))
               for k, v in t.items()}
    x2 = torch.cat([x.detach(), x.detach()], dim=-3)
    for cfg, factor in ((config, 2.0), (CONFIG, None)):
        one, parts_one = fused(x.detach(), t, cfg, layout=layout)
        two, parts_two = fused(x2, doubled, cfg, layout=layout)
        for term in parts_one:
            ratio = factor if factor is not None else (1.0 if term in means else 2.0)
            assert_close(parts_two[term], ratio * parts_one[term], RTOL_FLOAT64, f"{term} of the doubled groom")
    with pytest.raises(ValueError, match="reference_strand_count"):
        EnergyConfig(reference_strand_count=-1)


@pytest.mark.parametrize("term", STRAND_TERMS)
def test_layouts_agree_in_values_and_gradients(term, device, rng):
    for vertices in (3, 4, 6):
        x_np = make_strands(rng, 2, 2, vertices)
        t = to_torch(make_inputs(rng, x_np, shared=False), torch.float64, device)
        results = []
        for layout in LAYOUTS:
            x = torch.tensor(x_np, device=device, requires_grad=True)
            value = call_term(ops, term, x, t, CONFIG, layout=layout)
            value.sum().backward()
            results.append((value.detach(), x.grad))
        assert_close(results[1][0], results[0][0], RTOL_FLOAT64, f"{term} N={vertices} value")
        assert_close(results[1][1], results[0][1], RTOL_FLOAT64, f"{term} N={vertices} gradient")


def test_unbatched_input_gives_a_0_dim_result(rng):
    x_np = make_strands(rng, 2, 3, 6)
    t = to_torch(make_inputs(rng, x_np, shared=True), torch.float64)
    total, per_term = fused(torch.tensor(x_np), t)
    x1 = torch.tensor(x_np[1], requires_grad=True)
    t1 = dict(t, prev=t["prev"][1], prev2=t["prev2"][1])  # previous states are always per item
    total1, per_term1 = fused(x1, t1)
    assert total1.shape == () and all(v.shape == () for v in per_term1.values())
    assert_close(total1.detach(), total[1], RTOL_FLOAT64, "unbatched total")
    total1.backward()
    assert x1.grad.shape == x1.shape and float(x1.grad.abs().max()) > 0.0


def test_shared_and_per_item_inputs_agree(rng):
    x_np = make_strands(rng, 3, 2, 6)
    shared = make_inputs(rng, x_np, shared=True)
    per_item = dict(shared)
    for name, tail in (("rest_lengths", 2), ("rigid", 3), ("scalp_normals", 2)):
        per_item[name] = np.ascontiguousarray(batched(shared[name], 3, tail))
    x = torch.tensor(x_np)
    total_shared, _ = fused(x, to_torch(shared, torch.float64))
    total_per_item, _ = fused(x, to_torch(per_item, torch.float64))
    assert_close(total_per_item, total_shared, RTOL_FLOAT64, "per-item inputs")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_per_vertex_masses(layout, rng):
    x_np = make_strands(rng, 2, 3, 6)
    inputs = make_inputs(rng, x_np, shared=True)
    mass = rng.uniform(1e-4, 3e-3, size=(3, 6))
    t = to_torch(inputs, torch.float64)
    t["vertex_mass"] = torch.tensor(mass)
    x = torch.tensor(x_np)
    for term in ("gravity", "inertia"):
        value = call_term(ops, term, x, t, CONFIG, layout=layout)
        assert_close(value, reference_term(term, x_np, inputs, CONFIG, mass=mass), RTOL_FLOAT64, term)
        assert_close(call_term(torch_ref, term, x, t, CONFIG), value, RTOL_FLOAT64, f"{term} torch reference")
    total, per_term = fused(x, t, vertex_mass=t["vertex_mass"], layout=layout)
    expected = reference_term("inertia", x_np, inputs, CONFIG, mass=mass)
    assert_close(per_term["inertia"], expected, RTOL_FLOAT64, "fused with per-vertex masses")


# ---------------------------------------------------------------- kernel helpers
@wp.kernel
def _bending_acos_kernel(x: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    i = wp.tid()
    out[i] = strand_kernels.bending_acos(x[i])


# The float32 arccos is an inline polynomial (Cephes asinf): a few float32 ulps of pi.
ACOS_FLOAT32_ATOL = 5e-7


@pytest.mark.parametrize("dtype", DTYPES)
def test_bending_acos_matches_numpy(dtype, device):
    x = torch.linspace(-1.0, 1.0, 20001, dtype=dtype)
    x = torch.cat([x, torch.tensor([-1 + 1e-6, 1 - 1e-6, 0.5, -0.5, 0.49999997, 0.50000003], dtype=dtype)])
    x = x.to(device)
    out = torch.empty_like(x)
    wp.launch(
        _bending_acos_kernel,
        dim=x.numel(),
        inputs=[wp.from_torch(x)],
        outputs=[wp.from_torch(out)],
        device=_warp.warp_device(device),
    )
    expected = np.arccos(x.double().cpu().numpy())
    atol = 1e-15 if dtype == torch.float64 else ACOS_FLOAT32_ATOL
    np.testing.assert_allclose(out.double().cpu().numpy(), expected, rtol=0.0, atol=atol)


# ---------------------------------------------------------------- hand-built strands
def straight_strand(vertices, segment=0.01, direction=(0.0, -1.0, 0.0)):
    d = np.asarray(direction, dtype=np.float64)
    return np.arange(vertices)[:, None] * segment * d[None, :]


def test_rest_strand_has_zero_stretch():
    x_np = make_strands(np.random.default_rng(3), 2, 3, 6)
    x = torch.tensor(x_np, requires_grad=True)
    rest = ops.compute_rest_lengths(x)
    value = ops.stretch_energy(x, rest, 1e4)
    assert value.shape == (2,) and float(value.detach().abs().max()) < 1e-25
    value.sum().backward()
    assert float(x.grad.abs().max()) < 1e-9
    # Stretched by 10 %: (0.1 l)^2 per segment, a known non-zero value.
    stretched = ops.stretch_energy(x.detach() * 1.1, rest, 1e4)
    expected = 1e4 / (3 * 5) * ((0.1 * rest) ** 2).sum(dim=(-2, -1))
    assert_close(stretched, expected, RTOL_FLOAT64, "10 % stretch")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_straight_strand_bending(layout):
    segment, vertices = 0.01, 8
    x = torch.tensor(straight_strand(vertices, segment)[None, None]).requires_grad_(True)
    # eps = 0 on an axis-aligned strand: theta = 1 exactly (|e| = |e_y|), the clamp is active,
    # arccos(1) = 0, and the gradient is zero instead of 1 / sqrt(1 - theta^2) = inf.
    value = ops.bending_energy(x, 1.0, 0.0, layout=layout)
    assert float(value.detach()) == 0.0
    value.sum().backward()
    assert torch.count_nonzero(x.grad) == 0
    # Folded back on itself at vertex 3 (the last vertex returns onto vertex 2): theta = -1,
    # alpha = pi, again a clamped zero gradient.
    folded = torch.tensor(straight_strand(5, segment)[None, None])
    folded[0, 0, 4] = folded[0, 0, 2]
    folded.requires_grad_(True)
    value = ops.bending_energy(folded, 1.0, 0.0, layout=layout)
    assert_close(value, [math.pi], 1e-7, "folded strand")
    value.sum().backward()
    assert torch.isfinite(folded.grad).all() and torch.count_nonzero(folded.grad) == 0
    # eps > 0: the normalisation biases theta below 1, alpha = arccos(1 / (1 + eps / l)^2) per joint.
    eps = 1e-6
    biased = ops.bending_energy(x.detach(), 1.0, eps, layout=layout)
    expected = (vertices - 2) * math.acos(1.0 / (1.0 + eps / segment) ** 2)
    assert 0.0 < expected < 0.2
    assert_close(biased, [expected], 1e-7, "eps bias of a straight strand")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_circular_arc_has_known_angle_sum(layout):
    """A planar polyline turning by phi at each of its N-2 joints: bending = k_b (N-2) phi."""
    vertices, phi, weight = 10, 0.3, 2.5
    heading = np.arange(vertices - 1) * phi
    steps = 0.01 * np.stack([np.cos(heading), np.sin(heading), np.zeros_like(heading)], axis=-1)
    x_np = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])[None, None]
    for dtype, rtol in ((torch.float64, 1e-9), (torch.float32, RTOL_FLOAT32)):
        # eps = 0: no normalisation bias (eps / l would shift each angle by ~2 eps / (l tan phi)).
        value = ops.bending_energy(torch.tensor(x_np, dtype=dtype), weight, 0.0, layout=layout)
        assert_close(value, [weight * (vertices - 2) * phi], rtol, f"arc {dtype}")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_hand_built_smoothness_gravity_root_inertia(layout):
    vertices, segment = 6, 0.02
    normal = np.array([0.0, -1.0, 0.0])
    x_np = straight_strand(vertices, segment, normal)[None, None]
    x = torch.tensor(x_np)
    # A uniform straight strand has zero discrete second difference.
    assert float(ops.smoothness_energy(x, 1e3, layout=layout)) < 1e-25
    # Gravity: -w sum_{v>=2} m g . p = -w m (-9.81) (-v segment) summed over v = 2..N-1.
    expected = -2.0 * 1e-3 * 9.81 * segment * sum(range(2, vertices))
    gravity = ops.gravity_energy(x, 1e-3, (0.0, -9.81, 0.0), 2.0, layout=layout)
    assert_close(gravity, [expected], 1e-12, "gravity")
    # Root alignment: along the normal 1 - l / (l + eps) ~ 0; perpendicular to it exactly lambda.
    n = torch.tensor(normal[None])
    along = ops.root_alignment_energy(x, n, 0.5, 3, 1e-8, layout=layout)
    assert abs(float(along)) < 1e-6
    sideways = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    across = ops.root_alignment_energy(x, sideways, 0.5, 3, 1e-8, layout=layout)
    assert_close(across, [0.5], 1e-12, "root alignment across the normal")
    # Inertia: zero on the constant-velocity prediction, positive elsewhere.
    prev = x + 0.001
    prev2 = x + 0.002  # 2 prev - prev2 == x
    assert float(ops.inertia_energy(x, prev, prev2, 1e-3, 1 / 60, 1.0, layout=layout)) < 1e-20
    assert float(ops.inertia_energy(x, prev, prev, 1e-3, 1 / 60, 1.0, layout=layout)) > 0.0


# ---------------------------------------------------------------- gradients
@pytest.mark.parametrize("scale", [1e-3, 1.0])
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("term", STRAND_TERMS + ("total",))
def test_gradient_matches_finite_differences(term, layout, scale, device, rng):
    x_np = make_strands(rng, 2, 2, 6, segment=scale)
    t = to_torch(make_inputs(rng, x_np, shared=False, segment=scale), torch.float64, device)

    def energy(x):
        if term == "total":
            return fused(x, t, layout=layout)[0]
        return call_term(ops, term, x, t, CONFIG, layout=layout)

    x = torch.tensor(x_np, device=device, requires_grad=True)
    energy(x).sum().backward()
    expected = fd_gradient(lambda y: energy(y).detach(), x.detach())
    assert float(expected.abs().max()) > 0.0, "finite differences are zero: nothing would be checked"
    assert_close(x.grad, expected, FD_RTOL, f"{term} gradient vs finite differences")


@pytest.mark.parametrize("layout", LAYOUTS)
def test_fixed_vertices_get_exactly_zero_gradient(layout, device, rng):
    x_np = make_strands(rng, 2, 3, 6)
    t = to_torch(make_inputs(rng, x_np, shared=True), torch.float32, device)
    x = torch.tensor(x_np, dtype=torch.float32, device=device, requires_grad=True)
    total, _ = fused(x, t, layout=layout)
    total.sum().backward()
    assert torch.count_nonzero(x.grad[..., :2, :]) == 0
    assert torch.count_nonzero(x.grad[..., 2:, :]) == x.grad[..., 2:, :].numel()
    x_ref = torch.tensor(x_np, dtype=torch.float32, device=device, requires_grad=True)
    for term in STRAND_TERMS:
        call_term(torch_ref, term, x_ref, t, CONFIG).sum().backward()
    assert torch.count_nonzero(x_ref.grad[..., :2, :]) == 0


def test_inertia_gives_no_gradient_to_previous_states(rng):
    x_np = make_strands(rng, 2, 2, 6)
    t = to_torch(make_inputs(rng, x_np, shared=False), torch.float64)
    for module, kw in ((ops, {"layout": "strand"}), (ops, {"layout": "vertex"}), (torch_ref, {})):
        prev = t["prev"].clone().requires_grad_(True)
        prev2 = t["prev2"].clone().requires_grad_(True)
        x = torch.tensor(x_np, requires_grad=True)
        value = module.inertia_energy(x, prev, prev2, 1e-3, 1 / 60, 1.0, **kw)
        assert value.grad_fn is not None
        value.sum().backward()
        assert prev.grad is None and prev2.grad is None
        assert float(x.grad.abs().max()) > 0.0
        # ... although the energy does depend on them.
        moved = module.inertia_energy(
            x.detach(), prev.detach() + 1e-3, prev2.detach(), 1e-3, 1 / 60, 1.0, **kw
        )
        assert float((moved - value.detach()).abs().min()) > 0.0


def test_no_grad_evaluation_matches(rng):
    x_np = make_strands(rng, 2, 2, 6)
    t = to_torch(make_inputs(rng, x_np, shared=True), torch.float64)
    x = torch.tensor(x_np, requires_grad=True)
    with torch.no_grad():
        total_no_grad, _ = fused(x, t)
    total, _ = fused(x, t)
    assert total.requires_grad and not total_no_grad.requires_grad
    assert_close(total_no_grad, total.detach(), RTOL_FLOAT64, "no_grad value")


def test_repeated_calls_replay_one_plan_and_follow_every_change(rng):
    """Eager calls with the same shapes and weights replay one packed launch (`_plans`); new
    tensors, new values at the same address, a new weight or gravity and gradients on or off
    each take effect, checked against the numpy references."""
    x_np = make_strands(rng, 2, 3, 6)
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, torch.float64)
    ops._plans.clear()
    for _ in range(3):
        x = torch.tensor(x_np, requires_grad=True)
        total, per_term = fused(x, t)
        total.sum().backward()
    assert len(ops._plans) == 1
    assert_close(per_term["auxiliary"], reference_term("auxiliary", x_np, inputs, CONFIG), RTOL_FLOAT64, "replayed")

    moved = x_np + 1e-3 * rng.normal(size=x_np.shape)
    x.detach().copy_(torch.tensor(moved))  # same address, new values
    _, per_term = fused(x, t)
    assert_close(per_term["stretch"], reference_term("stretch", moved, inputs, CONFIG), RTOL_FLOAT64, "new x values")
    other = dict(inputs, rigid=inputs["rigid"] + 2e-3)
    _, per_term = fused(x, to_torch(other, torch.float64))  # a new rigid tensor
    assert_close(per_term["auxiliary"], reference_term("auxiliary", moved, other, CONFIG), RTOL_FLOAT64, "new rigid")
    config = CONFIG.replace(smoothness_weight=3.0)
    _, per_term = fused(x, t, config=config)
    assert_close(per_term["smoothness"], reference_term("smoothness", moved, inputs, config), RTOL_FLOAT64, "weight")
    with torch.no_grad():
        no_grad_total, _ = fused(x, t)
    assert_close(no_grad_total, fused(x, t)[0].detach(), RTOL_FLOAT64, "without the gradient")
    for g in ((0.0, -9.81, 0.0), (3.0, 0.0, 0.0)):  # CONFIG's own (the first plan again), a new one
        config = CONFIG.replace(gravity=g)
        _, per_term = fused(x, t, config=config)
        assert_close(per_term["gravity"], reference_term("gravity", moved, inputs, config), RTOL_FLOAT64, f"g={g}")
    assert len(ops._plans) == 4  # first (new tensors replay it), new weight, no gradient, new gravity


# ---------------------------------------------------------------- selection of terms
def test_terms_subset_and_skipping(rng):
    x_np = make_strands(rng, 2, 2, 6)
    t = to_torch(make_inputs(rng, x_np, shared=True), torch.float64)
    x = torch.tensor(x_np)
    total, per_term = fused(x, t, terms=("stretch", "gravity"))
    assert tuple(per_term) == ("stretch", "gravity")
    assert_close(total, per_term["stretch"] + per_term["gravity"], RTOL_FLOAT64, "subset total")
    # Missing inputs skip their terms when not requested by name; a zero weight skips too.
    total, per_term = ops.strand_energies(x, None, CONFIG.replace(bending_weight=0.0))
    assert tuple(per_term) == ("smoothness", "gravity")
    assert_close(total, sum(per_term.values()), RTOL_FLOAT64, "skipped terms")
    # Named but without its inputs: skipped as well (the energy composition relies on it).
    total, per_term = ops.strand_energies(x, None, CONFIG, terms=["inertia", "smoothness"])
    assert tuple(per_term) == ("smoothness",)
    assert_close(total, per_term["smoothness"], RTOL_FLOAT64, "inertia skipped")
    with pytest.raises(ValueError, match="terms"):
        ops.strand_energies(x, None, CONFIG, terms=["twist"])
    with pytest.raises(ValueError, match="terms"):
        ops.strand_energies(x, None, CONFIG, terms="stretch")


def test_root_alignment_segments_are_capped_and_zero_turns_it_off(rng):
    x_np = make_strands(rng, 1, 2, 3)  # N = 3: a single moving segment
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, torch.float64)
    x = torch.tensor(x_np)
    value = ops.root_alignment_energy(x, t["scalp_normals"], 1.0, 5, 1e-8)
    normals = batched(inputs["scalp_normals"], 1, 2)
    assert_close(value, ref.root_alignment(x_np, normals, 1.0, 1, 1e-8), RTOL_FLOAT64, "k' capped at N - 2")
    off = ops.root_alignment_energy(x, t["scalp_normals"], 1.0, 0, 1e-8)
    assert float(off.abs().max()) == 0.0


# ---------------------------------------------------------------- degenerate input
@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_coincident_vertices_give_finite_energy_and_gradient(dtype, layout, device, rng):
    x_np = make_strands(rng, 2, 3, 7)
    x_np[0, 0, 3] = x_np[0, 0, 2]  # one zero-length segment
    x_np[0, 1, 4:6] = x_np[0, 1, 3]  # two in a row
    x_np[1, 2, :] = x_np[1, 2, 0]  # a collapsed strand
    inputs = make_inputs(rng, x_np, shared=True)
    t = to_torch(inputs, dtype, device)
    for eps in (1e-6, 0.0):
        config = CONFIG.replace(bending_eps=eps, root_alignment_eps=eps)
        x = torch.tensor(x_np, dtype=dtype, device=device, requires_grad=True)
        total, per_term = fused(x, t, config=config, layout=layout)
        total.sum().backward()
        assert len(per_term) == len(STRAND_TERMS)
        assert torch.isfinite(total).all() and torch.isfinite(x.grad).all(), f"eps={eps}"
        for term in ("stretch", "bending", "smoothness", "auxiliary"):
            assert_close(per_term[term], reference_term(term, x_np, inputs, config), rtol_for(dtype), term)


def test_empty_batch_returns_empty_results_without_launching(monkeypatch):
    def no_launch(*args, **kwargs):
        raise AssertionError("an empty batch must not launch a kernel")

    monkeypatch.setattr(ops, "_launch", no_launch)
    x = torch.zeros((0, 2, 5, 3), dtype=torch.float32, requires_grad=True)
    rest = torch.ones((2, 4))
    total, per_term = ops.strand_energies(x, rest, CONFIG)
    assert total.shape == (0,) and len(per_term) >= 1 and all(v.shape == (0,) for v in per_term.values())
    total.sum().backward()
    assert x.grad.shape == x.shape
    assert ops.bending_energy(x).shape == (0,)


def test_minimal_strand_of_three_vertices(device, rng):
    x_np = make_strands(rng, 2, 2, 3)
    inputs = make_inputs(rng, x_np, shared=False)
    t = to_torch(inputs, torch.float64, device)
    for layout in LAYOUTS:
        x = torch.tensor(x_np, device=device, requires_grad=True)
        total, per_term = fused(x, t, layout=layout)
        assert tuple(per_term) == STRAND_TERMS
        for term, value in per_term.items():
            assert_close(value, reference_term(term, x_np, inputs, CONFIG), RTOL_FLOAT64, f"N=3 {term}")
        total.sum().backward()
        assert torch.count_nonzero(x.grad[..., :2, :]) == 0 and float(x.grad[..., 2, :].abs().max()) > 0.0


# ---------------------------------------------------------------- bad input
def _bad_cases():
    x = torch.zeros((2, 3, 5, 3))
    x[..., 1] = -0.01 * torch.arange(5.0).view(1, 1, 5)
    rest = torch.full((3, 4), 0.01)
    rigid = x[0].clone()
    normals = torch.tensor([[0.0, 1.0, 0.0]]).repeat(3, 1)
    nan_x = x.clone()
    nan_x[1, 2, 3, 0] = float("nan")
    inf_prev = x.clone()
    inf_prev[0, 0, 4, 2] = float("inf")
    return [
        ("x", lambda: ops.strand_energies(x[..., :2], rest)),
        ("x", lambda: ops.strand_energies(x[0, 0], rest)),
        ("x", lambda: ops.strand_energies(x.to(torch.float16), rest)),
        ("x", lambda: ops.strand_energies(x.int(), rest)),
        ("x", lambda: ops.strand_energies(nan_x, rest)),
        ("x", lambda: ops.strand_energies(x[:, :, :2], rest[:, :1])),
        ("x", lambda: ops.strand_energies(x[:, :0], rest[:0])),
        ("x", lambda: ops.smoothness_energy(x.numpy())),
        ("rest_lengths", lambda: ops.strand_energies(x, rest[:, :3])),
        ("rest_lengths", lambda: ops.stretch_energy(x, rest.double())),
        ("rest_lengths", lambda: ops.stretch_energy(x, None)),
        ("rigid", lambda: ops.auxiliary_energy(x, rigid[:2])),
        ("rigid", lambda: ops.auxiliary_energy(x, rigid.to("meta"))),
        ("scalp_normals", lambda: ops.root_alignment_energy(x, normals[:, :2])),
        ("prev", lambda: ops.inertia_energy(x, inf_prev, x)),
        ("prev2", lambda: ops.inertia_energy(x, x, x[:1, :, :, :].repeat(3, 1, 1, 1))),
        ("weight", lambda: ops.smoothness_energy(x, float("nan"))),
        ("weight", lambda: ops.bending_energy(x, "heavy")),
        ("eps", lambda: ops.bending_energy(x, 1.0, -1e-6)),
        ("segments", lambda: ops.root_alignment_energy(x, normals, 1.0, -1)),
        ("segments", lambda: ops.root_alignment_energy(x, normals, 1.0, 2.5)),
        ("time_step", lambda: ops.inertia_energy(x, x, x, 1e-3, 0.0)),
        ("vertex_mass", lambda: ops.gravity_energy(x, -1.0)),
        ("vertex_mass", lambda: ops.gravity_energy(x, torch.full((3, 4), 1e-3))),
        ("vertex_mass", lambda: ops.gravity_energy(x, torch.full((3, 5), -1e-3))),
        ("gravity", lambda: ops.gravity_energy(x, 1e-3, (0.0, -9.81))),
        ("layout", lambda: ops.smoothness_energy(x, layout="warp")),
        ("config", lambda: ops.strand_energies(x, rest, {"stretch_weight": 1.0})),
        ("p_init", lambda: ops.compute_rest_lengths(x[0, 0, :1])),
    ]


@pytest.mark.parametrize("case", range(len(_bad_cases())))
def test_bad_input_raises_value_error_naming_the_argument(case):
    name, call = _bad_cases()[case]
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        call()
