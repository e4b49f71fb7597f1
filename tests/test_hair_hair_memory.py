"""Memory bound of hair-hair contact (`hairwarp.ops.hair_hair_contact`): the pair buffer is
reused across calls, its growth is capped by `max_pairs`, and more pairs than the cap is one
clear error naming it. See docs/contact.md for the bound."""

import numpy as np
import pytest
import torch

from hairwarp.ops import hair_hair_contact_energy, hair_hair_contact_pairs
from hairwarp.ops import hair_hair_contact as hh
from hairwarp.ops.hair_hair_contact import HairHairCapacityError
from hairwarp.torch_reference import hair_hair_contact as torch_ref
from references import hair_hair_contact as ref

XI, DHAT, BP = 2e-3, 3e-3, 0.1


def _cell_runs(monkeypatch) -> list:
    """The `run` of every cells broad phase made from now on (its hit list and long counts)."""
    runs = []
    real = hh._cell_broad_phase

    def spy(*args, **kwargs):
        run, count = real(*args, **kwargs)
        runs.append(run)
        return run, count

    monkeypatch.setattr(hh, "_cell_broad_phase", spy)
    return runs


def _pile(rng):
    """10 strands of 13 vertices packed in 3 mm: every pair of strands is in contact."""
    return torch.tensor(ref.random_hair(rng, batch=1, strands=10, vertices=13, extent=3e-3, segment=5e-4))


def test_growth_beyond_the_cap_is_one_error_naming_max_pairs(rng):
    x = _pile(rng)
    full, info = hair_hair_contact_energy(x, XI, DHAT, BP)
    needed = info.pair_count
    assert needed > 100 and float(full) > 0
    # Room for every pair: the same energy as without a cap, even starting from a tiny buffer.
    capped, info_capped = hair_hair_contact_energy(x, XI, DHAT, BP, capacity=3, max_pairs=needed)
    assert info_capped.pair_count == needed and info_capped.overflow
    np.testing.assert_allclose(capped.numpy(), full.numpy(), rtol=1e-13)
    # One pair short of the need: growth would pass the cap.
    for call in (
        lambda: hair_hair_contact_energy(x, XI, DHAT, BP, capacity=3, max_pairs=needed - 1),
        lambda: hair_hair_contact_pairs(x, XI, DHAT, capacity=3, max_pairs=needed - 1),
    ):
        with pytest.raises(HairHairCapacityError, match=f"max_pairs.*max_pairs >= {needed}") as err:
            call()
        assert err.value.needed == needed and err.value.max_pairs == needed - 1


def test_capacity_is_clamped_to_the_cap(rng):
    x = _pile(rng)
    needed = hair_hair_contact_pairs(x, XI, DHAT).pair_count
    assert needed > 100
    _, info = hair_hair_contact_energy(x, XI, DHAT, BP, capacity=10**9, max_pairs=needed)
    assert info.capacity == needed and not info.overflow


def test_default_cap_is_per_segment():
    assert hh.default_max_pairs(1000) == hh.DEFAULT_MAX_PAIRS_PER_SEGMENT * 1000
    # The default cap bounds the buffer of the benchmark's largest case (1024 x 100 hair,
    # batch 32): 64 pairs per segment, 8 bytes each, under 2 GiB.
    segments = 32 * 1024 * 99
    assert hh.default_max_pairs(segments) * hh.PAIR_BYTES < 2 * 2**30


def test_pair_buffer_is_reused_across_calls(rng):
    x = _pile(rng)
    hair_hair_contact_energy(x, XI, DHAT, BP)  # the buffer exists and is large enough
    buffer = hh._pair_buffers["cpu"]
    before = (buffer.data_ptr(), buffer.shape[0])
    for _ in range(3):
        energy, info = hair_hair_contact_energy(x + 1e-5 * torch.randn_like(x), XI, DHAT, BP)
        assert info.pair_count > 100
    after = hh._pair_buffers["cpu"]
    assert (after.data_ptr(), after.shape[0]) == before


def test_returned_pairs_do_not_alias_the_shared_buffer(rng):
    x = _pile(rng)
    first = hair_hair_contact_pairs(x, XI, DHAT)
    kept = first.pairs.clone()
    assert kept.shape[0] > 100
    # Another call writes other pairs into the shared buffer.
    far = x.clone()
    far[:, ::2] += 1.0
    hair_hair_contact_pairs(far, XI, DHAT)
    torch.testing.assert_close(first.pairs, kept, rtol=0, atol=0)


def test_bad_max_pairs_raises_naming_it(rng):
    x = _pile(rng)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="max_pairs"):
            hair_hair_contact_energy(x, XI, DHAT, BP, max_pairs=bad)


def test_benchmark_torch_peer_item_by_item_equals_whole_batch(rng):
    """The benchmark's plain-torch hair-hair peer runs one batch item at a time to bound its
    memory; it must give the whole-batch result."""
    from hairwarp.bench.energy import torch_hair_hair_by_item
    from hairwarp.config import EnergyConfig

    config = EnergyConfig(hair_diameter=XI, hair_hair_dhat=DHAT, barrier_join_fraction=BP, hair_hair_weight=2.0)
    x = torch.tensor(ref.random_hair(rng, batch=3, strands=8, vertices=12, extent=6e-3, segment=1e-3))
    whole, pairs = torch_ref.hair_hair_contact_energy(x, XI, DHAT, BP, 2.0, config.barrier_variant, method="grid")
    assert pairs.shape[0] > 30 and bool((whole > 0).all())
    torch.testing.assert_close(torch_hair_hair_by_item(x, config), whole, rtol=1e-12, atol=0)


@pytest.mark.parametrize("kind", ["cpu-grid", "cells"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_stretched_and_equal_length_segments_find_every_pair_once(rng, dtype, kind, monkeypatch):
    """The broad phase finds a pair from one query only: the lower id's between typical
    segments, the longer segment's when one is long (> 1.5 x the mean), the lower id's on
    equal lengths. Stretched segments (as an L-BFGS trial point makes) and exactly equal
    lengths (a straight grid) must still give exactly the brute-force pairs, with every broad
    phase (the boxes-in-cells one enters a long segment once and lets it walk its own box)."""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: kind)
    x = ref.random_hair(rng, batch=2, strands=8, vertices=12, extent=0.01, segment=2e-3)
    # Stretch a few segments 5-10x by moving the tail of their strand.
    for b, m, v, factor in ((0, 1, 5, 6.0), (0, 4, 7, 10.0), (1, 2, 3, 5.0), (1, 6, 8, 8.0)):
        step = x[b, m, v + 1] - x[b, m, v]
        x[b, m, v + 1:] += (factor - 1.0) * step
    # Two strands of exactly equal segment lengths crossing near each other.
    grid = np.zeros((1, 2, 12, 3))
    grid[0, 0, :, 0] = np.arange(12) * 2e-3
    grid[0, 1, :, 1] = np.arange(12) * 2e-3 - 11e-3
    grid[0, 1, :, 0] = 11e-3
    grid[0, 1, :, 2] = 3e-3
    # Two long segments crossing 2 mm apart (a long-long pair), among short ones.
    cross = np.zeros((1, 3, 12, 3))
    cross[0, :, :, 0] = np.arange(12) * 2e-3
    cross[0, 1, :, 0] = 11e-3
    cross[0, 1, :, 1] = np.arange(12) * 2e-3 - 11e-3
    cross[0, 1, :, 2] = 2e-3
    cross[0, 2, :, 2] = 4e-3
    cross[0, 0, 6:] += np.array([0.03, 0.0, 0.0])  # segment 5 of strand 0: 32 mm
    cross[0, 1, 6:] += np.array([0.0, 0.04, 0.0])  # segment 5 of strand 1: 42 mm
    for hair in (x, grid, cross):
        hair = torch.tensor(hair).to(dtype).double().numpy()
        _, expected = ref.energy(hair, XI, DHAT, BP)
        assert expected.shape[0] > 0
        found = hair_hair_contact_pairs(torch.tensor(hair, dtype=dtype), XI, DHAT)
        np.testing.assert_array_equal(found.pairs.numpy(), expected)
        assert found.pair_count == expected.shape[0]
    lengths = np.linalg.norm(np.diff(x, axis=2), axis=-1)
    assert lengths.max() > 3 * lengths.mean()  # long segments were present
    assert [5, 16] in found.pairs.tolist()  # the crossing long segments (the last hair) paired


def test_removed_midpoint_broad_phase_is_one_clear_error(rng, monkeypatch):
    """The midpoint grid is gone (issue 30): a broad phase kind other than "cpu-grid" or "cells"
    is one ValueError naming the accepted kinds, from the pair list and the energy alike.
    """
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "midpoints")
    x = _pile(rng)
    message = r"broad phase: expected one of \['cpu-grid', 'cells'\], got 'midpoints'"
    with pytest.raises(ValueError, match=message):
        hair_hair_contact_pairs(x, XI, DHAT)
    with pytest.raises(ValueError, match=message):
        hair_hair_contact_energy(x, XI, DHAT, BP)


@pytest.mark.parametrize("slots", [1, 4])
def test_cell_table_collisions_neither_drop_nor_repeat_pairs(rng, slots, monkeypatch):
    """The boxes-in-cells broad phase hashes cells into a table; with 1 or 4 slots every cell
    (both batch items', a segment's own several cells, long segments' centres) shares a slot,
    and the pairs must still be exactly the brute force's, each once."""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    monkeypatch.setattr(hh, "_cell_table_size", lambda num_segments: slots)
    x = ref.random_hair(rng, batch=2, strands=8, vertices=12, extent=0.01, segment=2e-3)
    x[0, 3, 6:] += 5 * (x[0, 3, 6] - x[0, 3, 5])  # one long segment
    _, expected = ref.energy(x, XI, DHAT, BP)
    found = hair_hair_contact_pairs(torch.tensor(x), XI, DHAT)
    assert expected.shape[0] > 20
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
    assert found.pair_count == expected.shape[0]


@pytest.mark.parametrize("batch", [1, 3])
def test_many_long_segments_share_the_long_lanes(rng, monkeypatch, batch):
    """More long segments than the long-pairs launch serves at once (it strides over its list):
    every fourth segment 40x longer (3.7x the mean), so many of them are long; pairs as the brute
    force's. With 3 batch items each item's long segments are listed apart and pair only among
    themselves. (Long by the mean rule: a quarter of the segments long would raise the cells'
    size past them, `test_cells_sized_for_all_but_a_few_segments_of_a_mixed_groom`.)"""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    monkeypatch.setattr(hh, "_CELL_LONG_FRACTION", 1.0)
    runs = _cell_runs(monkeypatch)
    x = ref.random_hair(rng, batch=batch, strands=24, vertices=12, extent=0.01, segment=1e-3)
    steps = np.diff(x, axis=2)
    steps[:, :, 1::4] *= 40.0
    x = np.concatenate([x[:, :, :1], x[:, :, :1] + np.cumsum(steps, axis=2)], axis=2)
    _, expected = ref.energy(x, XI, DHAT, BP)
    found = hair_hair_contact_pairs(torch.tensor(x), XI, DHAT)
    assert expected.shape[0] > 20
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
    long_count = runs[-1].long_count
    served_at_once = max(1, x.shape[1] * (x.shape[2] - 1) * batch // 32)
    assert int(long_count[-1]) > served_at_once and int(long_count[:-1].sum()) == int(long_count[-1])
    assert bool((long_count[:-1] > 4).all())  # every item has long segments of its own


def test_a_segment_stretched_to_metres_walks_a_tube_and_finds_every_pair(rng, monkeypatch):
    """A wild line-search trial stretches a segment to metres: its box spans millions of cells,
    so the cells broad phase walks only the cells within reach of the segment, slab by slab
    (and long partners from the list of long segments). Two metre-long segments through a dense
    cluster, crossing 1 mm apart: exactly the brute force's pairs."""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    x = ref.random_hair(rng, batch=1, strands=8, vertices=12, extent=0.01, segment=2e-3)
    centre = x[0, :, 2:].reshape(-1, 3).mean(axis=0)
    for strand, direction, offset in ((0, np.array([1.2, 0.9, -0.7]), 0.0), (1, np.array([-0.8, 1.1, 0.6]), 1e-3)):
        # Segment 5 of the strand runs through the cluster's centre, ~1.5 m long.
        half = 0.5 * direction
        shift = centre + np.array([0.0, 0.0, offset]) - 0.5 * (x[0, strand, 5] + x[0, strand, 6])
        x[0, strand] += shift
        x[0, strand, :6] -= half
        x[0, strand, 6:] += half
    lengths = np.linalg.norm(np.diff(x, axis=2), axis=-1)
    assert lengths[0, 0, 5] > 1.4 and lengths[0, 1, 5] > 1.4
    _, expected = ref.energy(x, XI, DHAT, BP)
    found = hair_hair_contact_pairs(torch.tensor(x), XI, DHAT)
    assert expected.shape[0] > 20
    assert [5, 16] in expected.tolist()  # the two metre-long segments cross within the cutoff
    assert any(5 in pair and 16 not in pair for pair in expected.tolist())  # and meet short ones
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
    assert found.pair_count == expected.shape[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grid_scales_match_their_formula_and_repeat_bit_for_bit(rng, dtype, device):
    """`_grid_params` (two kernels, the lengths summed in fixed point) against its formula in
    float64: cell width, long half length H, absolute slack, longest half length; a segment
    stretched to 3 m included; a second call gives the same bits (no atomic-order noise)."""
    x = ref.random_hair(rng, batch=2, strands=7, vertices=11)
    x[1, 3, 6] += np.array([3.0, 0.0, 0.0])  # two segments of ~3 m
    cutoff = XI + DHAT
    params = hh._grid_params(torch.tensor(x, dtype=dtype, device=device), cutoff)
    lengths = np.linalg.norm(x[:, :, 1:] - x[:, :, :-1], axis=-1)
    max_half = 0.5 * lengths.max()
    long_half = min(max_half, 0.5 * hh._LONG_FACTOR * lengths.mean())
    slack = 4.0 * np.abs(x).max() * 2.0**-23
    width = (cutoff + 2.0 * long_half) * hh._CELL_FACTOR * (1.0 + hh._RADIUS_SLACK) + slack
    np.testing.assert_allclose(params.cpu().numpy(), [width, long_half, slack, max_half], rtol=2e-6)
    assert max_half > 1.4 and long_half < 0.1
    assert torch.equal(params, hh._grid_params(torch.tensor(x, dtype=dtype, device=device), cutoff))


@pytest.mark.parametrize("hit_slots, rows_per_segment", [(0, 4), (1, 1), (2, 4), (4, 4)])
def test_cell_hit_list_rows_that_overflow_walk_on(rng, monkeypatch, hit_slots, rows_per_segment):
    """The cells kind's short-short walk writes each entry's first partners to a hit list and
    walks on with the exact test where a row is full or an entry has no row: whatever the list's
    size, the pairs are exactly the brute force's, each once, and the energy and gradient the
    same. The small lists do overflow both ways (rows full, entries past the rows)."""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    monkeypatch.setattr(hh, "_CELL_HIT_SLOTS", hit_slots)
    monkeypatch.setattr(hh, "_CELL_HIT_ROWS_PER_SEGMENT", rows_per_segment)
    x = ref.random_hair(rng, batch=2, strands=10, vertices=12, extent=0.01, segment=2e-3)
    expected_energy, expected = ref.energy(x, XI, DHAT, BP)
    assert expected.shape[0] > 40
    runs = _cell_runs(monkeypatch)
    found = hair_hair_contact_pairs(torch.tensor(x), XI, DHAT)
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
    assert found.pair_count == expected.shape[0]
    xt = torch.tensor(x, requires_grad=True)
    energy, _ = hair_hair_contact_energy(xt, XI, DHAT, BP)
    np.testing.assert_allclose(energy.detach().numpy(), expected_energy, rtol=1e-12)
    (gradient,) = torch.autograd.grad(energy.sum(), xt)
    reference, _ = torch_ref.hair_hair_contact_energy(xt, XI, DHAT, BP, 1.0, "quadratic", method="grid")
    (reference_gradient,) = torch.autograd.grad(reference.sum(), xt)
    np.testing.assert_allclose(gradient.numpy(), reference_gradient.numpy(), rtol=1e-9, atol=1e-9)
    run = runs[-1]
    assert run.hit_slots == hit_slots
    entries = int(run.slot_end[-1])
    if hit_slots == 0:
        assert run.hit_rows == 0  # the walk and the test in one kernel
        return
    state = run.hit_state[: min(run.hit_rows, entries)]
    assert int((state > 0).sum()) > 0  # rows that held hits
    if (hit_slots, rows_per_segment) == (1, 1):
        assert int((state > hit_slots).sum()) > 10  # rows that overflowed
        assert entries > run.hit_rows  # entries with no row


@pytest.mark.parametrize("lanes, hit_slots, steps", [(1, 1, 16), (2, 1, 16), (5, 1, 16), (8, 1, 16), (3, 4, 2),
                                                     (4, 6, 1)])
def test_resumed_walks_shared_by_lanes_find_each_pair_once(rng, monkeypatch, lanes, hit_slots, steps):
    """Lanes that share an entry's resumed walk (every `lanes`-th step each) find exactly the
    brute force's pairs, each once, in crowded cells, where rows fill up or (with lanes) stop
    walking after `steps` steps with slots left empty; the default lane count fills at most
    `_CELL_WALK_THREADS` threads, 1 to 8 lanes."""
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    monkeypatch.setattr(hh, "_CELL_HIT_SLOTS", hit_slots)
    monkeypatch.setattr(hh, "_CELL_HIT_ROWS_PER_SEGMENT", 1)
    monkeypatch.setattr(hh, "_CELL_HIT_WALK_STEPS", steps)
    monkeypatch.setattr(hh, "_cell_walk_lanes", lambda entries: lanes)
    runs = _cell_runs(monkeypatch)
    x = ref.random_hair(rng, batch=2, strands=12, vertices=12, extent=4e-3, segment=1e-3)
    expected_energy, expected = ref.energy(x, XI, DHAT, BP)
    assert expected.shape[0] > 200
    found = hair_hair_contact_pairs(torch.tensor(x), XI, DHAT)
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
    energy, _ = hair_hair_contact_energy(torch.tensor(x), XI, DHAT, BP)
    np.testing.assert_allclose(energy.numpy(), expected_energy, rtol=1e-12)
    state = runs[-1].hit_state[: min(runs[-1].hit_rows, int(runs[-1].slot_end[-1]))]
    capped = state == hit_slots + steps + 1
    if lanes > 1:
        assert int(capped.sum()) > 10  # rows whose walk the pairs kernel's lanes went on with
    monkeypatch.undo()
    threads = hh._CELL_WALK_THREADS
    assert hh._cell_walk_lanes(10) == 8 and hh._cell_walk_lanes(threads) == 1
    assert hh._cell_walk_lanes(threads // 4) == 4 and hh._cell_walk_lanes(threads // 4 + 1) == 2


def test_cells_sized_for_all_but_a_few_segments_of_a_mixed_groom(rng, monkeypatch):
    """Cells sized by the mean length would send every segment of a groom's long strands down
    the long path; the cells kind raises the long length on its ladder (1.25x rungs) until at
    most `_CELL_LONG_FRACTION` of the segments are longer. Even hair keeps the mean rule; a
    mix of strands 10x apart in length gets cells for its long strands, and the same pairs."""
    strands, vertices = 16, 14
    x = ref.random_hair(rng, batch=2, strands=strands, vertices=vertices, extent=0.02, segment=1e-3)
    even = torch.tensor(x)
    mean_rule = hh._grid_params(even, XI + DHAT)
    np.testing.assert_array_equal(hh._grid_params(even, XI + DHAT, hh._CELL_LONG_FRACTION).numpy(),
                                  mean_rule.numpy())
    steps = np.diff(x, axis=2)
    steps[:, ::2] *= 10.0  # every other strand's segments 10x longer: 1.8x the mean
    mixed = np.concatenate([x[:, :, :1], x[:, :, :1] + np.cumsum(steps, axis=2)], axis=2)
    xt = torch.tensor(mixed)
    lengths = np.linalg.norm(np.diff(mixed, axis=2), axis=-1)
    mean_long = float(hh._grid_params(xt, XI + DHAT)[1]) * 2
    assert (lengths > mean_long).mean() > 0.3  # the mean rule calls a third of the segments long
    raised = hh._grid_params(xt, XI + DHAT, hh._CELL_LONG_FRACTION)
    long_length = float(raised[1]) * 2
    assert (lengths > long_length * (1 + 1e-6)).mean() <= hh._CELL_LONG_FRACTION  # float32 params
    assert long_length <= lengths.max() * 1.0001 and long_length > mean_long
    np.testing.assert_allclose(float(raised[0]), (XI + DHAT + long_length) * hh._CELL_FACTOR * (1 + hh._RADIUS_SLACK)
                               + float(raised[2]), rtol=1e-6)
    monkeypatch.setattr(hh, "_broad_phase_kind", lambda device: "cells")
    _, expected = ref.energy(mixed, XI, DHAT, BP)
    assert expected.shape[0] > 20
    found = hair_hair_contact_pairs(xt, XI, DHAT)
    np.testing.assert_array_equal(found.pairs.numpy(), expected)
