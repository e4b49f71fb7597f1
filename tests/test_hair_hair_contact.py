"""Tests of hair-hair contact (HairFormer Eq. 12 with d = segment-segment distance):
`hairwarp.ops.hair_hair_contact_energy` / `hair_hair_contact_pairs` (Warp) against the numpy
float64 brute-force reference and the plain-torch reference."""

import numpy as np
import pytest
import torch

from hairwarp.ops import barrier, edge_edge_distance, hair_hair_contact_energy, hair_hair_contact_pairs
from hairwarp.ops.hair_hair_contact import HairHairCapacityError
from hairwarp.torch_reference import hair_hair_contact as torch_ref
from references import hair_hair_contact as ref

XI, DHAT = 2e-3, 3e-3  # the paper's hair-hair barrier for a 2 mm guide: dhat = 1.5 xi
BP = 0.1
WEIGHT = 2.5
# float64 kernel vs numpy reference: the brute-force distances agree to ~1e-15 m; B(d) is
# steep near xi (relative condition ~ xi / (d - xi)), so allow 1e-9 relative on the sum.
F64_RTOL = 1e-9
# float32 kernel vs float64 reference on positions rounded to float32: a few ulps of the
# distances, amplified by the barrier's log near xi.
F32_RTOL = 2e-4
# Central differences in float64, h = 1e-8 m on 2-6 mm gaps.
FD_H = 1e-8
FD_RTOL = 1e-5


@pytest.fixture(autouse=True, params=["cpu-grid", "cells", "cells-overflow", "cells-lanes"])
def broad_phase(request, monkeypatch):
    """Every test of this module runs each broad phase: the CPU's own grid and the device's
    (the boxes in hashed cells), whichever device runs it.
    "cells-overflow" is the cells kind with a hit list of one partner for one entry per segment:
    most walks go on past their row and many entries have none (`_cell_broad_phase`);
    "cells-lanes" a hit list of two partners whose walks stop after 3 steps, the pairs kernel
    going on with each in 3 lanes (`_cell_walk_lanes`, `_CELL_HIT_WALK_STEPS`)."""
    import hairwarp.ops.hair_hair_contact as hh

    device_kind = hh._broad_phase_kind
    chosen = request.param
    if chosen == "cells-overflow":
        monkeypatch.setattr(hh, "_CELL_HIT_SLOTS", 1)
        monkeypatch.setattr(hh, "_CELL_HIT_ROWS_PER_SEGMENT", 1)
        chosen = "cells"
    if chosen == "cells-lanes":
        monkeypatch.setattr(hh, "_CELL_HIT_SLOTS", 2)
        monkeypatch.setattr(hh, "_CELL_HIT_WALK_STEPS", 3)
        monkeypatch.setattr(hh, "_cell_walk_lanes", lambda entries: 3)
        chosen = "cells"

    def kind(device):
        # The CPU grid is the CPU's own: CUDA tensors keep the device kind.
        return device_kind(device) if request.param == "cpu-grid" and device.type != "cpu" else chosen

    monkeypatch.setattr(hh, "_broad_phase_kind", kind)
    monkeypatch.setattr(hh, "_learned_capacity", {})  # each kind learns its own
    return chosen


def _t(a, dtype=torch.float64, device="cpu"):
    return torch.tensor(np.asarray(a), dtype=dtype, device=device)


def _pair_distances(x4, pairs):
    """Distances of flat segment-id pairs, through the public distance op."""
    b, m, n, _ = x4.shape
    p0 = x4[:, :, :-1].reshape(-1, 3)
    p1 = x4[:, :, 1:].reshape(-1, 3)
    i, j = pairs[:, 0], pairs[:, 1]
    return edge_edge_distance(p0[i], p1[i], p0[j], p1[j])


def test_crossing_strands_at_known_distance(device):
    gap = 3e-3
    x = _t(ref.crossing_strands(gap), device=device)
    found = hair_hair_contact_pairs(x, XI, DHAT)
    assert found.pair_count > 0 and found.pairs.shape == (found.pair_count, 2)
    assert not found.overflow
    # Every pair joins strand 0 to strand 1, past the root segments.
    bms = found.unravel().cpu()
    assert bool((bms[:, 0, 1] == 0).all() and (bms[:, 1, 1] == 1).all() and (bms[:, :, 2] >= 2).all())
    d = _pair_distances(x[None], found.pairs)
    assert abs(float(d.min()) - gap) < 1e-15
    assert bool((d < XI + DHAT).all())
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, weight=WEIGHT)
    assert energy.shape == () and energy.device.type == device.type
    assert info.pair_count == found.pair_count and info["pair_count"] == found.pair_count
    expected = WEIGHT * barrier(d, XI, DHAT, BP).sum()
    assert float(energy) > 0
    assert float(energy) == pytest.approx(float(expected), rel=1e-12)
    ref_energy, ref_pairs = ref.energy(x.cpu().numpy()[None], XI, DHAT, BP, WEIGHT)
    np.testing.assert_array_equal(found.pairs.cpu().numpy(), ref_pairs)
    np.testing.assert_allclose(float(energy), ref_energy[0], rtol=F64_RTOL)
    # The same strands 6 mm apart are out of reach: no pair, no energy.
    far = _t(ref.crossing_strands(6e-3), device=device)
    energy_far, info_far = hair_hair_contact_energy(far, XI, DHAT, BP)
    assert info_far.pair_count == 0 and float(energy_far) == 0.0


@pytest.mark.parametrize("variant", ["quadratic", "monotone", "paper"])
def test_random_hair_matches_numpy_reference(rng, variant):
    x_np = ref.random_hair(rng, batch=2, strands=6, vertices=10)
    expected, expected_pairs = ref.energy(x_np, XI, DHAT, BP, WEIGHT, variant)
    assert expected_pairs.shape[0] > 30 and np.all(expected > 0)
    x = _t(x_np)
    found = hair_hair_contact_pairs(x, XI, DHAT)
    np.testing.assert_array_equal(found.pairs.numpy(), expected_pairs)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, weight=WEIGHT, variant=variant)
    assert energy.shape == (2,) and info.pair_count == expected_pairs.shape[0] and not info.overflow
    np.testing.assert_allclose(energy.numpy(), expected, rtol=F64_RTOL)
    # Penetrating pairs (d < xi) exercise the extrapolated piece of the barrier.
    d = _pair_distances(x, found.pairs)
    assert int((d < XI).sum()) > 5
    # float32 on the same (rounded) positions.
    x32 = x.float()
    expected32, _ = ref.energy(x32.double().numpy(), XI, DHAT, BP, WEIGHT, variant)
    energy32, _ = hair_hair_contact_energy(x32, XI, DHAT, BP, weight=WEIGHT, variant=variant)
    assert energy32.dtype == torch.float32
    np.testing.assert_allclose(energy32.double().numpy(), expected32, rtol=F32_RTOL)


def test_torch_reference_matches_kernel(rng):
    x_np = ref.random_hair(rng, batch=2, strands=6, vertices=10)
    x = _t(x_np).requires_grad_(True)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, weight=WEIGHT)
    (grad,) = torch.autograd.grad(energy.sum(), x)
    assert info.pair_count > 30 and float(grad.norm()) > 0
    for method in ("bruteforce", "grid"):
        xr = _t(x_np).requires_grad_(True)
        energy_ref, pairs_ref = torch_ref.hair_hair_contact_energy(xr, XI, DHAT, BP, WEIGHT, method=method)
        (grad_ref,) = torch.autograd.grad(energy_ref.sum(), xr)
        assert pairs_ref.shape[0] == info.pair_count
        np.testing.assert_allclose(energy_ref.detach().numpy(), energy.detach().numpy(), rtol=1e-12)
        atol = 1e-12 * float(grad.abs().max())
        np.testing.assert_allclose(grad_ref.numpy(), grad.numpy(), rtol=0, atol=atol)


def test_torch_grid_search_matches_kernel_on_hanging_hair():
    """The voxel-grid search of the torch reference and the Warp hash grid find the same pairs."""
    x = _t(ref.hanging_hair(side=8, vertices=40, length=0.12, spacing=5e-3))
    found = hair_hair_contact_pairs(x, XI, DHAT)
    assert found.pair_count > 100
    grid_pairs = torch_ref.pairs_grid(x[None], XI + DHAT)
    np.testing.assert_array_equal(grid_pairs.numpy(), found.pairs.numpy())
    brute_pairs = torch_ref.pairs_bruteforce(x[None], XI + DHAT)
    np.testing.assert_array_equal(brute_pairs.numpy(), found.pairs.numpy())


def test_gradient_matches_central_differences():
    rng = np.random.default_rng(11)
    x_np = ref.random_hair(rng, batch=1, strands=4, vertices=7, extent=0.01)
    x = _t(x_np).requires_grad_(True)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, weight=WEIGHT)
    (grad,) = torch.autograd.grad(energy.sum(), x)
    assert info.pair_count > 5
    moving = grad[:, :, 2:]
    assert int((moving.abs() > 0).sum()) > 10
    fd = np.zeros_like(x_np)
    for idx in np.ndindex(*x_np.shape):
        if idx[2] < 2:
            continue  # fixed vertices: checked to be exactly zero below
        plus, minus = x_np.copy(), x_np.copy()
        plus[idx] += FD_H
        minus[idx] -= FD_H
        e_plus, _ = hair_hair_contact_energy(_t(plus), XI, DHAT, BP, weight=WEIGHT)
        e_minus, _ = hair_hair_contact_energy(_t(minus), XI, DHAT, BP, weight=WEIGHT)
        fd[idx] = (float(e_plus) - float(e_minus)) / (2 * FD_H)
    np.testing.assert_allclose(grad.numpy(), fd, rtol=0, atol=FD_RTOL * np.abs(fd).max())
    assert bool((grad[:, :, :2] == 0).all())
    # torch's own check on a smaller case (it perturbs every coordinate, fixed ones included).
    small = _t(ref.crossing_strands(3e-3, num_vertices=8, length=0.02)).requires_grad_(True)

    def f(t):
        return hair_hair_contact_energy(t, XI, DHAT, BP, weight=1e6)[0]

    assert float(f(small).detach()) > 0
    assert torch.autograd.gradcheck(f, (small,), eps=1e-8, atol=1e-6, rtol=1e-5)


def test_fixed_vertices_and_root_segments():
    """Roots closer than a diameter: no contact with the default rule; no root gradient ever."""
    x_np = ref.crossing_strands(1e-3, num_vertices=8, length=0.02)
    # Re-root both strands at their crossing: make vertices 0..2 of each strand touch.
    x_np = x_np[:, [3, 4, 5, 6, 7, 2, 1, 0]]
    x = _t(x_np)
    default = hair_hair_contact_pairs(x, XI, DHAT)
    everything = hair_hair_contact_pairs(x, XI, DHAT, skip_root_segments=0)
    assert everything.pair_count > default.pair_count
    assert bool((default.unravel()[:, :, 2] >= 2).all())
    assert bool((everything.unravel()[:, :, 2] < 2).any())
    xg = x.clone().requires_grad_(True)
    energy, info = hair_hair_contact_energy(xg, XI, DHAT, BP, skip_root_segments=0)
    (grad,) = torch.autograd.grad(energy, xg)
    assert info.pair_count == everything.pair_count and float(energy.detach()) > 0
    assert bool((grad[:, :2] == 0).all()) and float(grad[:, 2:].abs().max()) > 0
    expected, _ = ref.energy(x_np[None], XI, DHAT, BP, 1.0, skip_root_segments=0)
    np.testing.assert_allclose(float(energy.detach()), expected[0], rtol=F64_RTOL)


def test_same_strand_segments_never_pair():
    """A strand folded back on itself (a hairpin 1 mm wide) has no contact with itself."""
    t = np.linspace(0.0, 0.03, 11)
    down = np.stack([np.zeros_like(t), -t, np.zeros_like(t)], axis=1)
    up = down[::-1] + np.array([1e-3, 0.0, 0.0])
    strand = np.concatenate([down, up])
    x = _t(strand[None])
    assert hair_hair_contact_pairs(x, XI, DHAT).pair_count == 0
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP)
    assert float(energy) == 0.0 and info.pair_count == 0
    # A second, identical strand beside it does pair with it.
    two = _t(np.stack([strand, strand + np.array([0.0, 0.0, 2.5e-3])]))
    assert hair_hair_contact_pairs(two, XI, DHAT).pair_count > 10


def test_far_apart_strands_have_no_pairs(rng):
    x_np = ref.random_hair(rng, batch=1, strands=5, vertices=9)
    x_np[0] += np.arange(5)[:, None, None] * np.array([0.2, 0.0, 0.0])  # 20 cm apart
    x = _t(x_np).requires_grad_(True)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP)
    (grad,) = torch.autograd.grad(energy.sum(), x)
    assert info.pair_count == 0 and not info.overflow
    assert float(energy[0].detach()) == 0.0 and float(grad.abs().max()) == 0.0
    assert hair_hair_contact_pairs(x, XI, DHAT).pairs.shape == (0, 2)


def test_overflow_reported_with_tiny_capacity(rng, broad_phase):
    x = _t(ref.random_hair(rng, batch=2, strands=6, vertices=10))
    full, info_full = hair_hair_contact_energy(x, XI, DHAT, BP)
    needed = info_full.pair_count
    assert needed > 30 and not info_full.overflow
    # "grow": complete energy, overflow reported.
    grown, info = hair_hair_contact_energy(x, XI, DHAT, BP, capacity=3)
    assert info.overflow and info.pair_count == needed and info.capacity == 3
    np.testing.assert_allclose(grown.numpy(), full.numpy(), rtol=1e-12)
    # "raise": the needed count in the error.
    with pytest.raises(HairHairCapacityError, match=f"capacity >= {needed}") as err:
        hair_hair_contact_energy(x, XI, DHAT, BP, capacity=3, on_overflow="raise")
    assert err.value.needed == needed
    with pytest.raises(HairHairCapacityError):
        hair_hair_contact_pairs(x, XI, DHAT, capacity=0, on_overflow="raise")
    # "warn": a warning naming the needed capacity; the energy over the pairs kept only, except
    # with the cells broad phase, which keeps no list: its energy holds every pair.
    with pytest.warns(RuntimeWarning, match=str(needed)):
        partial, info = hair_hair_contact_energy(x, XI, DHAT, BP, capacity=3, on_overflow="warn")
    assert info.overflow and info.pair_count == needed
    if broad_phase == "cells":
        np.testing.assert_allclose(partial.numpy(), full.numpy(), rtol=1e-12)
    else:
        assert float(partial.sum()) < float(full.sum())
    with pytest.warns(RuntimeWarning):
        kept = hair_hair_contact_pairs(x, XI, DHAT, capacity=3, on_overflow="warn")
    assert kept.pairs.shape == (3, 2) and kept.pair_count == needed and kept.overflow
    # Exactly enough room is no overflow.
    _, info = hair_hair_contact_energy(x, XI, DHAT, BP, capacity=needed, on_overflow="raise")
    assert not info.overflow


def test_deferred_overflow_reads_nothing_until_checked(rng, broad_phase):
    """on_overflow="defer" (the CUDA-graph path): with room, the same energy and gradient as
    "grow"; without, the first `capacity` pairs only (the cells broad phase: all of them, it
    keeps no list), and `check()` raises naming the capacity."""
    x = _t(ref.random_hair(rng, batch=2, strands=6, vertices=10)).requires_grad_(True)
    full, info_full = hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT)
    (g_full,) = torch.autograd.grad(full.sum(), x)
    needed = info_full.pair_count
    deferred, info = hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT, capacity=needed + 5, on_overflow="defer")
    (g_deferred,) = torch.autograd.grad(deferred.sum(), x)
    np.testing.assert_allclose(deferred.detach().numpy(), full.detach().numpy(), rtol=1e-12)
    np.testing.assert_allclose(g_deferred.numpy(), g_full.numpy(), rtol=1e-12, atol=1e-18)
    assert info.pair_count == needed and not info.overflow
    info.check()
    partial, info = hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT, capacity=3, on_overflow="defer")
    if broad_phase == "cells":
        np.testing.assert_allclose(partial.detach().numpy(), full.detach().numpy(), rtol=1e-12)
    else:
        assert float(partial.detach().sum()) < float(full.detach().sum())
    assert info.overflow and info.pair_count == needed
    with pytest.raises(HairHairCapacityError, match=f"capacity >= {needed}"):
        info.check()
    with pytest.raises(ValueError, match="on_overflow"):
        hair_hair_contact_pairs(x, XI, DHAT, on_overflow="defer")


def test_grow_without_a_list_reads_nothing_and_needs_no_cap(rng, broad_phase):
    """The cells broad phase's energy keeps no pair list: under "grow" nothing is read back
    (an eager CUDA call waits for nothing) and `max_pairs`, which bounds a list's memory, does
    not apply; the energy holds every pair and `info` reads the count when asked. The broad
    phases that keep a list still raise past the cap."""
    import hairwarp.ops.hair_hair_contact as hh

    x = _t(ref.random_hair(rng, batch=2, strands=6, vertices=10))
    full, info_full = hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT)
    needed = info_full.pair_count
    assert needed > 4
    if broad_phase != "cells":
        with pytest.raises(HairHairCapacityError, match="max_pairs"):
            hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT, capacity=2, max_pairs=needed - 1)
        return
    reads = []
    real_policy = hh._overflow_policy

    def policy(count, *args):
        item = count.item
        count.item = lambda: reads.append(1) or item()
        return real_policy(count, *args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(hh, "_overflow_policy", policy)
        energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT, capacity=2, max_pairs=needed - 1)
    assert reads == []
    np.testing.assert_allclose(energy.numpy(), full.numpy(), rtol=1e-12)
    assert info.pair_count == needed and info.overflow and info.capacity == 2


def test_batched_equals_separate_calls(rng):
    x_np = ref.random_hair(rng, batch=3, strands=5, vertices=9)
    x = _t(x_np).requires_grad_(True)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP, weight=WEIGHT)
    (grad,) = torch.autograd.grad((energy * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)).sum(), x)
    total = 0
    for b in range(3):
        xb = _t(x_np[b]).requires_grad_(True)
        eb, ib = hair_hair_contact_energy(xb, XI, DHAT, BP, weight=WEIGHT)
        (gb,) = torch.autograd.grad(eb, xb)
        assert eb.shape == () and ib.pair_count > 0
        total += ib.pair_count
        np.testing.assert_allclose(float(energy[b].detach()), float(eb.detach()), rtol=1e-13)
        np.testing.assert_allclose(grad[b].numpy(), (b + 1) * gb.numpy(), rtol=1e-12, atol=1e-300)
    assert info.pair_count == total
    # Identical items overlapping in space must not pair across the batch.
    same = _t(np.stack([x_np[0]] * 3))
    e_same, i_same = hair_hair_contact_energy(same, XI, DHAT, BP)
    e_one, i_one = hair_hair_contact_energy(_t(x_np[0]), XI, DHAT, BP)
    assert i_same.pair_count == 3 * i_one.pair_count
    np.testing.assert_allclose(e_same.numpy(), [float(e_one)] * 3, rtol=1e-13)


def test_empty_and_trivial_inputs(device):
    for shape in [(0, 4, 10, 3), (2, 0, 10, 3), (2, 1, 10, 3), (2, 4, 1, 3), (2, 4, 2, 3), (2, 4, 3, 3)]:
        x = torch.zeros(shape, dtype=torch.float32, device=device, requires_grad=True)
        energy, info = hair_hair_contact_energy(x, XI, DHAT, BP)
        assert energy.shape == (shape[0],) and info.pair_count == 0, shape
        assert float(energy.detach().abs().sum()) == 0.0
        if shape[0] > 0:
            (grad,) = torch.autograd.grad(energy.sum(), x)
            assert grad.shape == x.shape and float(grad.abs().sum()) == 0.0
        assert hair_hair_contact_pairs(x, XI, DHAT).pairs.shape == (0, 2)
    # Strands all at one point (zero-length segments, d = 0 everywhere): finite, no NaN.
    x = torch.zeros(1, 3, 5, 3, dtype=torch.float64, device=device, requires_grad=True)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP)
    (grad,) = torch.autograd.grad(energy.sum(), x)
    assert info.pair_count == 3 * 2 * 2 and float(energy.detach()) > 0
    assert bool(torch.isfinite(grad).all())


def test_bad_inputs_raise_naming_the_argument():
    x = torch.rand(2, 3, 6, 3, dtype=torch.float64) * 0.01
    bad_shapes = (torch.rand(3, 6, 2), torch.rand(6, 3), torch.rand(1, 2, 3, 6, 3))
    for bad in bad_shapes + (torch.ones(2, 3, 6, 3, dtype=torch.int64),):
        with pytest.raises(ValueError, match="x"):
            hair_hair_contact_energy(bad, XI, DHAT, BP)
        with pytest.raises(ValueError, match="x"):
            hair_hair_contact_pairs(bad, XI, DHAT)
    nan = x.clone()
    nan[1, 2, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="x"):
        hair_hair_contact_energy(nan, XI, DHAT, BP)
    with pytest.raises(ValueError, match="x"):
        hair_hair_contact_energy(x.numpy(), XI, DHAT, BP)
    cases = [
        ({"xi": 0.0}, "xi"),
        ({"xi": -1e-3}, "xi"),
        ({"dhat": 0.0}, "dhat"),
        ({"bp": 0.0}, "bp"),
        ({"bp": 1.0}, "bp"),
        ({"weight": -1.0}, "weight"),
        ({"weight": float("nan")}, "weight"),
        ({"variant": "cubic"}, "variant"),
        ({"capacity": -1}, "capacity"),
        ({"capacity": 2.5}, "capacity"),
        ({"on_overflow": "ignore"}, "on_overflow"),
        ({"skip_root_segments": -1}, "skip_root_segments"),
    ]
    for change, name in cases:
        kwargs = {"xi": XI, "dhat": DHAT, "bp": BP} | change
        with pytest.raises(ValueError, match=name):
            hair_hair_contact_energy(x, **kwargs)


def test_default_capacity_learns_from_growth(rng, broad_phase):
    """capacity=None: a call that had to grow its pair list raises the default for later calls
    of that size. The cells broad phase's energy keeps no list: it learns nothing (and needs
    nothing: its energy holds every pair), its pair list does."""
    from hairwarp.ops.hair_hair_contact import default_capacity

    # 10 strands of 13 vertices packed in 3 mm: every pair of strands is in contact.
    x = _t(ref.random_hair(rng, batch=1, strands=10, vertices=13, extent=3e-3, segment=5e-4))
    num_segments = 10 * 12
    first = default_capacity(num_segments)
    energy, info = hair_hair_contact_energy(x, XI, DHAT, BP)
    assert info.pair_count > first and info.overflow and info.capacity == first
    if broad_phase == "cells":
        energy_again, info_again = hair_hair_contact_energy(x, XI, DHAT, BP)
        assert info_again.capacity == first == default_capacity(num_segments) and info_again.overflow
        grown = hair_hair_contact_pairs(x, XI, DHAT)
        assert grown.overflow and grown.pair_count == info.pair_count
    energy_again, info_again = hair_hair_contact_energy(x, XI, DHAT, BP)
    if broad_phase != "cells":
        assert not info_again.overflow and info_again.capacity >= info.pair_count
        assert default_capacity(num_segments) == info_again.capacity
    else:
        assert default_capacity(num_segments) >= info.pair_count
        assert not hair_hair_contact_pairs(x, XI, DHAT).overflow
    np.testing.assert_allclose(energy_again.numpy(), energy.numpy(), rtol=1e-13)


def test_float32_energy_sum_stays_accurate_with_many_pairs():
    """~1.6e5 pair energies summed: float32 input, float64 accumulation."""
    x32 = torch.tensor(ref.hanging_hair(side=16, vertices=100), dtype=torch.float32)
    e32, info = hair_hair_contact_energy(x32, XI, DHAT, 0.01, capacity=1_000_000)
    e64, info64 = hair_hair_contact_energy(x32.double(), XI, DHAT, 0.01, capacity=1_000_000)
    assert info.pair_count > 100_000 and info.pair_count == info64.pair_count
    # Same positions, same pairs: only the per-pair float32 arithmetic differs (a running
    # float32 sum of these terms was measured 2.3e-4 off).
    assert float(e32) == pytest.approx(float(e64), rel=1e-5)
