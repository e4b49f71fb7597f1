"""The hair-hair pair list kept across calls on the CPU (`hairwarp.ops.hair_hair_contact.HairHairPairCache`):
at any positions it gives exactly the pairs, energy and gradient of a fresh broad phase; it
requeries the segments that moved past the skin and rebuilds when too many did."""

import numpy as np
import pytest
import torch

from hairwarp.ops import hair_hair_contact as hh
from hairwarp.ops import hair_hair_contact_energy, hair_hair_contact_pairs
from hairwarp.ops.hair_hair_contact import HairHairPairCache
from references import hair_hair_contact as ref

XI, DHAT, BP, WEIGHT = 2e-3, 3e-3, 0.1, 2.5
SKIN = 2e-3
# float64 inputs: the same pairs summed in another order (energy in float64, gradient per vertex).
RTOL = 1e-12


def _cached_pairs(x, cache):
    """Sorted (P, 2) int64 pairs of the cached broad phase at x (B, M, N, 3)."""
    pairs, _, found, _ = hh._cached_broad_phase(x.contiguous(), XI + DHAT, 2, None, cache)
    pairs = pairs[:found].long()
    n = x.shape[0] * x.shape[1] * (x.shape[2] - 1)
    return pairs[torch.argsort(pairs[:, 0] * n + pairs[:, 1])]


def _energy_and_gradient(x, cache=None):
    xg = x.detach().clone().requires_grad_(True)
    energy, info = hair_hair_contact_energy(xg, XI, DHAT, BP, WEIGHT, pair_cache=cache)
    (grad,) = torch.autograd.grad(energy.sum(), xg)
    return energy.detach(), grad, info.pair_count


def _sequence(rng):
    """Hair at rest, then moves of growing size: all vertices by micrometres, a few strands'
    tails by centimetres (new contacts, a stretched segment), then everything far."""
    x0 = ref.random_hair(rng, batch=2, strands=12, vertices=14, extent=0.015, segment=3e-3)
    steps = [x0]
    x = x0 + rng.normal(scale=2e-6, size=x0.shape)  # within the skin: the stored list serves
    steps.append(x)
    x = x.copy()
    x[0, 3, 6:] += np.array([0.004, -0.003, 0.002])  # a tail swings by 5 mm
    x[1, 7, 9:] += np.array([-0.02, 0.0, 0.01])  # a tail stretched by 2 cm (long segment)
    x[0, 5, 4:] = x[0, 8, 4:] + np.array([0.0, 1e-3, 0.0])  # strand 5 laid 1 mm beside strand 8
    steps.append(x)
    steps.append(x + rng.normal(scale=1e-6, size=x.shape))
    steps.append(x0 + rng.normal(scale=5e-3, size=x0.shape))  # everything moved: rebuilt
    return [torch.tensor(s) for s in steps]


def test_reused_list_gives_the_fresh_pairs_energy_and_gradient(rng):
    cache = HairHairPairCache(skin=SKIN, rebuild_fraction=0.5)
    requeried = []
    for x in _sequence(rng):
        expected = hair_hair_contact_pairs(x, XI, DHAT).pairs
        assert expected.shape[0] > 0
        np.testing.assert_array_equal(_cached_pairs(x, cache).numpy(), expected.numpy())
        requeried.append(cache.requeried)
    # Built once at the start, requeried only the moved segments, rebuilt when all moved.
    assert cache.builds == 2 and cache.calls == 5
    assert requeried[0] == 0 and requeried[1] == 0 and requeried[4] == 0
    segments = 2 * 12 * 13
    assert 0 < requeried[2] < segments // 2 and 0 < requeried[3] < segments // 2

    cache = HairHairPairCache(skin=SKIN)
    for x in _sequence(rng):
        e_fresh, g_fresh, n_fresh = _energy_and_gradient(x)
        e_cached, g_cached, n_cached = _energy_and_gradient(x, cache)
        assert n_fresh > 0 and n_cached == n_fresh and float(g_fresh.abs().max()) > 0
        np.testing.assert_allclose(e_cached.numpy(), e_fresh.numpy(), rtol=RTOL)
        np.testing.assert_allclose(g_cached.numpy(), g_fresh.numpy(), rtol=RTOL, atol=1e-12 * float(g_fresh.abs().max()))


def test_a_segment_moved_beyond_the_skin_is_requeried_and_its_new_contact_found():
    # Two parallel strands 20 mm apart: no contact, nothing stored within cutoff + skin.
    x = np.zeros((1, 2, 10, 3))
    x[0, :, :, 1] = -np.arange(10) * 3e-3
    x[0, 1, :, 0] = 0.02
    x = torch.tensor(x)
    cache = HairHairPairCache(skin=SKIN, rebuild_fraction=0.9)
    assert _cached_pairs(x, cache).shape[0] == 0 and cache.builds == 1
    # Moved by 0.4 skin (within 0.45 skin): the list serves, nothing requeried.
    nudged = x.clone()
    nudged[0, 1, 5:, 0] -= 0.4 * SKIN
    assert _cached_pairs(nudged, cache).shape[0] == 0 and cache.requeried == 0
    # The tail of strand 1 swung onto strand 0 (far past the skin): requeried, pairs found.
    moved = x.clone()
    moved[0, 1, 5:, 0] = 1e-3
    pairs = _cached_pairs(moved, cache)
    expected = hair_hair_contact_pairs(moved, XI, DHAT).pairs
    assert expected.shape[0] > 0 and cache.builds == 1 and cache.requeried > 0
    np.testing.assert_array_equal(pairs.numpy(), expected.numpy())


def test_rebuilt_when_the_shape_or_the_cutoff_changes(rng):
    cache = HairHairPairCache()
    x = torch.tensor(ref.random_hair(rng, batch=1, strands=8, vertices=10, extent=0.01, segment=3e-3))
    _energy_and_gradient(x, cache)
    _energy_and_gradient(x, cache)
    assert cache.builds == 1
    _energy_and_gradient(x[:, :6], cache)
    assert cache.builds == 2
    xg = x.clone().requires_grad_(True)
    e_wide, info = hair_hair_contact_energy(xg, XI, 2 * DHAT, BP, pair_cache=cache)
    e_fresh, info_fresh = hair_hair_contact_energy(x, XI, 2 * DHAT, BP)
    assert cache.builds == 3 and info.pair_count == info_fresh.pair_count > 0
    np.testing.assert_allclose(e_wide.detach().numpy(), e_fresh.numpy(), rtol=RTOL)
    cache.reset()
    _energy_and_gradient(x, cache)
    assert cache.builds == 4 and "builds=4" in repr(cache)


def test_total_energy_and_lbfgs_with_the_cache_equal_without():
    from hairwarp.config import EnergyConfig
    from hairwarp.energy import EnergyInputs, total_energy
    from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

    x = torch.tensor(ref.hanging_hair(side=6, vertices=20, length=0.06, spacing=2e-3), dtype=torch.float32)[None]
    rest = (x[0, :, 1:] - x[0, :, :-1]).norm(dim=-1)
    inputs = EnergyInputs(rest_lengths=rest, rigid=x.clone())
    config = EnergyConfig(hair_diameter=XI, hair_hair_dhat=DHAT)
    cache = HairHairPairCache()
    plain = total_energy(x, inputs, config)
    cached = total_energy(x, inputs, config, hair_hair_cache=cache)
    assert plain.hair_hair_pairs > 0 and cached.hair_hair_pairs == plain.hair_hair_pairs and cache.builds == 1
    np.testing.assert_allclose(cached.total.numpy(), plain.total.numpy(), rtol=1e-6)
    with pytest.raises(ValueError, match="hair_hair_cache"):
        total_energy(x, inputs, config, graph_safe=True, hair_hair_cache=cache)
    runs = [optimize_drape(x, inputs, config, DirectOptimizationConfig(method="lbfgs", max_iterations=5,
                                                                       pair_cache=use))
            for use in (False, True)]
    assert runs[0].evaluations == runs[1].evaluations > 5
    np.testing.assert_allclose(runs[1].loss, runs[0].loss, rtol=1e-5)
    np.testing.assert_allclose(runs[1].positions.numpy(), runs[0].positions.numpy(), atol=1e-6)


def test_bad_cache_arguments_raise_naming_them(rng):
    x = torch.tensor(ref.random_hair(rng, batch=1, strands=4, vertices=8))
    with pytest.raises(ValueError, match="skin"):
        HairHairPairCache(skin=0.0)
    with pytest.raises(ValueError, match="rebuild_fraction"):
        HairHairPairCache(rebuild_fraction=0.0)
    with pytest.raises(ValueError, match="pair_cache"):
        hair_hair_contact_energy(x, XI, DHAT, BP, pair_cache="yes")
    with pytest.raises(ValueError, match="pair_cache"):
        hair_hair_contact_energy(x, XI, DHAT, BP, on_overflow="defer", pair_cache=HairHairPairCache())


def test_a_pile_past_max_pairs_keeps_no_list(rng):
    """A stored list wider than the pair cap is not kept: the call falls back to the plain broad phase."""
    pile = torch.tensor(ref.random_hair(rng, batch=1, strands=10, vertices=13, extent=3e-3, segment=5e-4))
    full, info = hair_hair_contact_energy(pile, XI, DHAT, BP)
    needed = info.pair_count
    assert needed > 100
    cache = HairHairPairCache(skin=5e-3)
    capped, info_capped = hair_hair_contact_energy(pile, XI, DHAT, BP, max_pairs=needed, pair_cache=cache)
    assert info_capped.pair_count == needed and cache.builds == 0 and "stored_pairs=0" in repr(cache)
    np.testing.assert_allclose(capped.numpy(), full.numpy(), rtol=RTOL)


def _segment_pairs_at_the_cutoff(rng, count=200):
    """Hair of `count` two-strand groups, each a pair of segments (vertices 2-3 of each strand)
    at a distance within 0.02 % of the cutoff, at angles from parallel to crossing, closest
    points inside or at the ends: the cases where the cheap line-distance reject and the exact
    test meet."""
    cutoff = XI + DHAT
    strands = []
    for k in range(count):
        angle = [0.0, 1e-4, 1e-2, 0.1, 0.5, np.pi / 2][k % 6]
        gap = cutoff * (1.0 + rng.uniform(-2e-4, 2e-4))
        origin = np.array([0.05 * k, 0.0, 0.0])
        a = np.stack([origin + [0.0, -i * 3e-3, 0.0] for i in range(5)])
        direction = np.array([np.sin(angle), -np.cos(angle), 0.0])
        shift = rng.uniform(-4e-3, 4e-3) if k % 2 else 0.0  # slide along: an end-to-segment case
        b = np.stack([a[2] + [0.0, shift, gap] + (i - 2) * 3e-3 * direction for i in range(5)])
        strands += [a, b]
    return torch.tensor(np.stack(strands)[None])


def test_pairs_at_the_cutoff_match_the_float64_reference_at_every_angle(rng):
    x = _segment_pairs_at_the_cutoff(rng)
    # The reference per group (the groups are 50 mm apart: no pair across them).
    segs = x.shape[2] - 1
    expected = np.concatenate([ref.segment_pairs(x[:, 2 * k:2 * k + 2].numpy(), XI, DHAT)[0] + 2 * k * segs
                               for k in range(x.shape[1] // 2)])
    groups_in_contact = np.unique(expected[:, 0] // (2 * segs)).shape[0]
    assert 0 < groups_in_contact < x.shape[1] // 2  # both sides of the cutoff
    fresh = hair_hair_contact_pairs(x, XI, DHAT).pairs
    np.testing.assert_array_equal(fresh.numpy(), expected)
    cache = HairHairPairCache(skin=SKIN)
    np.testing.assert_array_equal(_cached_pairs(x, cache).numpy(), expected)
    moved = x.clone()
    moved[0, 1::2, 2:] += torch.tensor([0.0, 0.0, 1e-3], dtype=x.dtype)  # the second strands away and back
    moved[0, 1::2, 2:] -= torch.tensor([0.0, 0.0, 1e-3], dtype=x.dtype)
    np.testing.assert_array_equal(_cached_pairs(moved, cache).numpy(), expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_pass_gives_the_pair_energies_of_the_plain_pass(rng, dtype):
    """The cache adds each pair's energy as its kernel finds it: per batch item and per vertex
    the same as the plain pass over the pair list, in float32 too (the lower id first in both)."""
    cache = HairHairPairCache(skin=SKIN)
    for x in _sequence(rng):
        x = x.to(dtype)
        e_fresh, g_fresh, n_fresh = _energy_and_gradient(x)
        e_cached, g_cached, n_cached = _energy_and_gradient(x, cache)
        assert n_fresh > 0 and n_cached == n_fresh
        rtol = RTOL if dtype == torch.float64 else 1e-5  # float32 gradient: summation order
        np.testing.assert_allclose(e_cached.numpy(), e_fresh.numpy(), rtol=RTOL)
        np.testing.assert_allclose(g_cached.numpy(), g_fresh.numpy(), rtol=rtol,
                                   atol=rtol * float(g_fresh.abs().max()))
    assert cache.builds >= 1 and cache.calls == 5


def test_device_pair_list_gives_the_fresh_energy_within_reach_and_marks_stale_past_it(rng):
    """`HairHairPairList` (the physics' list in CUDA graphs; the cells broad phase runs on the CPU
    here): at positions moved less than 0.45 skin from its build, the energy and gradient of a
    fresh broad phase; `mark_stale` stays 0 there and turns 1 once a vertex moved farther; a
    build there serves again."""
    x0 = torch.tensor(ref.random_hair(rng, batch=2, strands=12, vertices=14, extent=0.015, segment=3e-3))
    pair_list = hh.HairHairPairList(x0.shape[:3], XI + DHAT, SKIN, capacity=4096, device="cpu", dtype=x0.dtype)
    pair_list.build(x0)
    assert 0 < int(pair_list.count) <= pair_list.capacity and not pair_list.overflowed()

    def energy(x):
        xg = x.clone().requires_grad_(True)
        e, info = hair_hair_contact_energy(xg, XI, DHAT, BP, WEIGHT, pair_list=pair_list)
        (g,) = torch.autograd.grad(e.sum(), xg)
        return e.detach(), g, info

    near = x0 + torch.tensor(rng.uniform(-1.0, 1.0, size=x0.shape)) * (0.25 * SKIN)  # every vertex within 0.45 skin
    for x in (x0, near):
        e_fresh, g_fresh, n_fresh = _energy_and_gradient(x)
        e_list, g_list, info = energy(x)
        assert n_fresh > 0 and float(g_fresh.abs().max()) > 0
        torch.testing.assert_close(e_list, e_fresh, rtol=RTOL, atol=0)
        torch.testing.assert_close(g_list, g_fresh, rtol=RTOL, atol=1e-12 * float(g_fresh.abs().max()))
        assert info.pair_count == int(pair_list.count)
        pair_list.mark_stale(x)
        assert int(pair_list.stale) == 0
    far = near.clone()
    far[1, 4, 9:] += torch.tensor([0.6 * SKIN, 0.0, 0.0], dtype=far.dtype)
    pair_list.mark_stale(far)
    assert int(pair_list.stale) == 1
    pair_list.build(far)
    assert int(pair_list.stale) == 0
    torch.testing.assert_close(energy(far)[0], _energy_and_gradient(far)[0], rtol=RTOL, atol=0)


def test_device_pair_list_overflow_and_arguments():
    x = torch.zeros(1, 3, 5, 3)
    x[:, :, :, 2] = torch.linspace(0, 0.01, 5)
    x[0, 1, :, 0] = 1e-3
    x[0, 2, :, 0] = 2e-3
    pair_list = hh.HairHairPairList(x.shape[:3], XI + DHAT, SKIN, capacity=1, device="cpu")
    pair_list.build(x)
    assert int(pair_list.count) > 1 and pair_list.overflowed()
    with pytest.raises(ValueError, match="capacity"):
        hh.HairHairPairList(x.shape[:3], XI + DHAT, SKIN, capacity=0, device="cpu")
    with pytest.raises(ValueError, match="skin"):
        hh.HairHairPairList(x.shape[:3], XI + DHAT, 0.0, capacity=8, device="cpu")
    with pytest.raises(ValueError, match="pair_list"):
        hair_hair_contact_energy(torch.zeros(1, 2, 5, 3), XI, DHAT, BP, WEIGHT, pair_list=pair_list)
    with pytest.raises(ValueError, match="pair_list"):
        hair_hair_contact_energy(x, XI, DHAT, BP, WEIGHT, pair_list=pair_list, pair_cache=HairHairPairCache())
