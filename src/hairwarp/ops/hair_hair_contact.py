"""Hair-hair contact energy (HairFormer Eq. 12-14 with d = segment-segment distance): torch
bridge over `hairwarp.kernels.hair_hair_contact`.

Which segment pairs count:
    - Segments of *different* strands only. Non-adjacent segments of the same strand are left
      out: with the paper's discretisation (100 vertices, segments of a few mm) segments i and
      i + 2 of one strand are always closer than xi + dhat (5 mm for a 2 mm guide), so
      self-contact would need an arbitrary exclusion window along the strand, and a curl whose
      pitch is below xi + dhat would be pushed open by its own barrier. A strand's own shape is
      the job of the stretch, bending and smoothness terms (Eq. 7-10).
    - Segments with index >= `skip_root_segments` (default 2) only: segment 0 joins the two
      fixed vertices and segment 1 touches vertex 1. Roots are packed on the scalp closer than a
      guide bundle's diameter (5 mm grid spacing vs xi + dhat = 5 mm), so contact there is not
      physical, and vertices 0, 1 are fixed anyway (Section 3.4), so the penalty could only act
      through a lever on vertex 2. Whatever the setting, vertices 0 and 1 get zero gradient.

Normalisation: energy = weight * sum over pairs of B(d), a sum (not a mean), per batch item;
`weight` is lambda_hh of Eq. 12 [J per pair at B = 1].

Broad phase, on CUDA (`_cell_broad_phase`): each segment's
bounding box grown by (xi + dhat) / 2 is entered in the <= 8 cells it touches (cells as wide as a
typical box, hashed with the batch item into one table for the whole batch); two segments closer
than xi + dhat have overlapping boxes and are tested once, in the cell of the low corner of the
boxes' intersection; segments wider than two cells are listed and walk their own box. The pairs
kernels add each kept pair's energy as they find it. The CPU has its own grid (`_CpuGrid`) and
pair cache.

Host synchronisations: none to launch. With `on_overflow` "grow", "raise" or "warn" the pair
count is read back once (to size the narrow phase and handle overflow). With "defer" nothing is
read: the narrow phase runs over the whole buffer (slots past the device count return at once),
and the count and overflow are read only when `HairHairContactInfo` is asked for them
(`check()` raises on overflow): the path a CUDA graph captures.

Memory: the pair buffer is one per device, reused across eager calls (grown to 1.25 x a call's
need, never shrunk), capped at `max_pairs` pairs of 8 bytes (default 64 per segment: 1.6 GiB for
1024 x 100 hair at batch 32, of which a drape touches ~1 pair per segment, 26 MiB); a call being
captured in a CUDA graph gets buffers of its own, sized by its capacity (the graph keeps them).
Besides it, a call of the cells kind holds ~450 bytes per segment (room for 8 entries with their
boxes, the table, the hit list; `_cell_broad_phase`) and the gradient (the size of `x`). See
docs/contact.md.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from hairwarp import _warp
from hairwarp._validate import check_positive, check_tensor
from hairwarp.config import EnergyConfig
from hairwarp.kernels import hair_hair_contact as hh_kernels
from hairwarp.ops.barrier import barrier_variant_id, check_barrier_parameters, join_fraction_tensor
from hairwarp.ops.reductions import row_sums
from hairwarp.runtime import StreamFork

OVERFLOW_POLICIES = ("grow", "raise", "warn", "defer")
DEFAULT_SKIP_ROOT_SEGMENTS = 2
# The grid works on float32 midpoints; this relative slack on the query radius covers their
# rounding, so no pair within the cutoff is missed (the exact test uses the input precision).
_RADIUS_SLACK = 1e-4
# Broad-phase shape, measured on the CPU and an H100 (docs/contact.md): a segment longer than _LONG_FACTOR
# times the mean is "long" (found from its own query), and grid cells are _CELL_FACTOR times
# a typical query's radius (fewer, fuller cells: each visited cell costs a lookup).
_LONG_FACTOR = 1.5
_CELL_FACTOR = 1.0
# The broad phases: "cpu-grid" (`_CpuGrid`, the CPU's) and "cells" (segment boxes in hashed cells,
# `_cell_broad_phase`, the device's; any device in the tests).
_BROAD_PHASE_KINDS = ("cpu-grid", "cells")
# The cells kind's long segments: longer than _LONG_FACTOR x the mean, raised until at most
# _CELL_LONG_FRACTION of the segments are (`_grid_params`; its cells are as wide as the box of a
# segment that long). A groom mixing strands of 10x different lengths (half the strands' segments
# 1.8x the mean) spent 46 ms of a 54 ms batch-32 energy on long segments with the mean rule alone
# (docs/contact.md 11).
_CELL_LONG_FRACTION = 0.05
# The cells kind's hit list (`_cell_broad_phase`): room for _CELL_HIT_SLOTS partners (4 bytes
# each, plus 4 for the row's state) of each of the first _CELL_HIT_ROWS_PER_SEGMENT x segments
# entries (84 bytes per segment; entries past the rows are walked with the exact test inline).
# _CELL_HIT_SLOTS = 0: the walk and the test in one kernel. Chosen on an H100 among 4-12 slots
# and 3-4 rows (docs/contact.md 11): 6 x 3 fastest at batch 32 with the least memory but one.
_CELL_HIT_SLOTS = 6
_CELL_HIT_ROWS_PER_SEGMENT = 3
# Steps of a walk the hits kernel takes at most when the pairs kernel has lanes to go on with it
# (`_cell_walk_lanes`): a row of a crowded cell finding few partners otherwise walks half the
# cell, one thread (docs/contact.md 12).
_CELL_HIT_WALK_STEPS = 16
# The CPU grid (`_CpuGrid`): cells of _CPU_CELL_FACTOR x the device path's width (a query walks
# one contiguous range per z row, so finer cells cost little and bring fewer candidates), at
# most _CPU_MAX_CELLS_PER_SEGMENT cells per segment (4 bytes each).
_CPU_CELL_FACTOR = 0.5
_CPU_MAX_CELLS_PER_SEGMENT = 8


class HairHairCapacityError(RuntimeError):
    """The pair buffer was too small: with `on_overflow="raise"` (message names `capacity`), or
    more pairs than the cap `max_pairs` that growth may reach (message names `max_pairs`).
    `needed` holds the pair count found.
    """

    def __init__(self, needed: int, capacity: int, max_pairs: int | None = None):
        if max_pairs is None:
            message = (
                f"capacity: hair-hair contact found {needed} segment pairs but the pair buffer holds {capacity}; "
                f"pass capacity >= {needed} (or on_overflow='grow')"
            )
        else:
            message = (
                f"max_pairs: hair-hair contact found {needed} segment pairs, more than the pair buffer may grow to "
                f"(max_pairs = {max_pairs}, {PAIR_BYTES * max_pairs / 2**20:.0f} MiB); the hair is piled far denser "
                f"than a drape (~1 pair per segment), or pass max_pairs >= {needed}"
            )
        super().__init__(message)
        self.needed = needed
        self.capacity = capacity
        self.max_pairs = max_pairs


class HairHairContactInfo:
    """Diagnostics of one hair-hair contact evaluation.

    The pair count stays on the device until asked for ("defer": nothing read back at the call).

    Attributes:
        pair_count: number of segment pairs closer than xi + dhat (the energy sums over all of
            them unless `on_overflow` "warn" or "defer" had to drop some); reading it reads
            the device.
        overflow: True if `pair_count` exceeded the capacity the call was given.
        capacity: the pair-buffer capacity the call was given.
    """

    def __init__(self, count, capacity: int, max_pairs: int | None = None):
        self._count = count
        self.capacity = int(capacity)
        self._max_pairs = max_pairs

    @property
    def pair_count(self) -> int:
        # Read on every access: a CUDA graph's replays rewrite the device count in place.
        if isinstance(self._count, torch.Tensor):
            return int(self._count.reshape(-1)[0].item())
        return self._count

    @property
    def overflow(self) -> bool:
        return self.pair_count > self.capacity

    @property
    def device_count(self) -> torch.Tensor | int:
        """The pair count as the call left it: a device tensor (not read back) or an int."""
        return self._count

    def check(self) -> None:
        """Raise `HairHairCapacityError` if pairs were dropped (reads the device once).

        Raises:
            HairHairCapacityError: the count exceeded the capacity (the energy missed pairs).
        """
        if self.overflow:
            raise HairHairCapacityError(self.pair_count, self.capacity)

    def __getitem__(self, key: str):
        return getattr(self, key)

    def __repr__(self) -> str:
        count = "on device" if isinstance(self._count, torch.Tensor) else self._count
        return f"HairHairContactInfo(pair_count={count}, capacity={self.capacity})"


@dataclass
class HairHairPairs:
    """Result of the hair-hair broad phase.

    Attributes:
        pairs: (P, 2) int64 flat segment ids (i < j) of the pairs closer than xi + dhat, sorted;
            segment (b, m, i) has id (b * M + m) * (N - 1) + i. P = min(pair_count, capacity).
        pair_count: number of pairs found (may exceed `capacity` when `overflow`).
        overflow: True if `pair_count` exceeded the capacity the call was given.
        capacity: the pair-buffer capacity the call was given.
        shape: (B, M, N) of the hair the pairs index into.
    """

    pairs: torch.Tensor
    pair_count: int
    overflow: bool
    capacity: int
    shape: tuple[int, int, int]

    def __getitem__(self, key: str):
        return getattr(self, key)

    def unravel(self) -> torch.Tensor:
        """(P, 2, 3) int64: (batch item, strand, segment index) of both segments of each pair."""
        _, m, n = self.shape
        seg = self.pairs
        strand = seg // (n - 1)
        return torch.stack([strand // m, strand % m, seg % (n - 1)], dim=-1)


def _check_hair(x) -> torch.Tensor:
    """x: (M, N, 3) or (B, M, N, 3) float32/float64, finite; returned as (B, M, N, 3)."""
    check_tensor("x", x, shape=("...", 3))
    if x.dim() not in (3, 4):
        raise ValueError(f"x: expected shape (M, N, 3) or (B, M, N, 3), got {tuple(x.shape)}")
    return x if x.dim() == 4 else x.unsqueeze(0)


def _check_options(capacity, skip_root_segments, on_overflow, max_pairs=None):
    if capacity is not None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 0:
            raise ValueError(f"capacity: expected None or an int >= 0, got {capacity!r}")
    if max_pairs is not None:
        if isinstance(max_pairs, bool) or not isinstance(max_pairs, int) or max_pairs < 0:
            raise ValueError(f"max_pairs: expected None or an int >= 0, got {max_pairs!r}")
    skip = skip_root_segments
    if isinstance(skip, bool) or not isinstance(skip, int) or skip < 0:
        raise ValueError(f"skip_root_segments: expected an int >= 0, got {skip_root_segments!r}")
    if on_overflow not in OVERFLOW_POLICIES:
        raise ValueError(f"on_overflow: expected one of {list(OVERFLOW_POLICIES)}, got {on_overflow!r}")


# Pair counts that outgrew the default capacity, by number of segments: a call with
# capacity=None starts at 1.25 x the largest such count, so a training loop over one hairstyle
# pays the "grow" rerun once, not every step. A performance memo only: results never depend on it.
_learned_capacity: dict[int, int] = {}


# Growth cap of the pair buffer for max_pairs=None, per segment: a draped groom has about one
# pair per segment (1024 x 100 hair on the default body: 103 021 pairs for 99 328 segments);
# 64 per segment means every segment within xi + dhat of 64 others, a pile, not a drape.
DEFAULT_MAX_PAIRS_PER_SEGMENT = 64
# Bytes per pair in the buffer (two int32 segment ids).
PAIR_BYTES = 8


def default_max_pairs(num_segments: int) -> int:
    """Cap on the pair buffer for max_pairs=None: `DEFAULT_MAX_PAIRS_PER_SEGMENT` per segment."""
    return DEFAULT_MAX_PAIRS_PER_SEGMENT * num_segments


# The pair buffer, one per device, reused across calls: it grows (to 1.25 x what a call needs,
# within that call's cap) and never shrinks, so a loop over one hairstyle allocates it once.
_pair_buffers: dict[str, torch.Tensor] = {}


def _capturing(device: torch.device) -> bool:
    return device.type == "cuda" and torch.cuda.is_current_stream_capturing()


def _pair_buffer(device: torch.device, rows: int, cap: int) -> torch.Tensor:
    """A (>= rows, 2) int32 buffer on `device`, reused across calls; rows <= cap. A call being
    captured gets its own (a later call must not free or grow what a graph replays).
    """
    if _capturing(device):
        return torch.empty(max(rows, 1), 2, dtype=torch.int32, device=device)
    key = str(device)
    buffer = _pair_buffers.get(key)
    if buffer is None or buffer.shape[0] < rows:
        size = min(max(rows + rows // 4, 1), max(cap, 1))
        _pair_buffers.pop(key, None)  # free the old one before allocating the new one
        buffer = torch.empty(max(size, rows, 1), 2, dtype=torch.int32, device=device)
        _pair_buffers[key] = buffer
    return buffer


def default_capacity(num_segments: int) -> int:
    """Pair-buffer capacity used for capacity=None.

    `EnergyConfig.hair_hair_capacity_per_segment` times `num_segments`, or 1.25 times the
    largest pair count an earlier call with as many segments needed, whichever is larger.
    """
    configured = EnergyConfig.hair_hair_capacity_per_segment * num_segments  # the field's default
    return max(configured, _learned_capacity.get(num_segments, 0))


def _grid_params(x4: torch.Tensor, cutoff: float, long_fraction: float | None = None) -> torch.Tensor:
    """(4,) float32 on the device: cell width, long half length H, absolute slack, longest half
    length [m] (no host read; `segment_stats_kernel` then `grid_params_kernel`: two launches
    where torch took ten small kernels, the longest path of the energy's graph at batch 1).

    Two segments closer than the cutoff have midpoints at most cutoff + (l_i + l_j) / 2 apart;
    the float32 midpoints add up to |coordinate| * 2^-24 each. Segments longer than
    _LONG_FACTOR x the mean are "long": their pairs are found from their own (wider) queries, so
    the others query within cutoff + their length / 2 + H only. With `long_fraction` (the
    cells kind's), the long length is raised, on a ladder of 1.25x steps, until at most that
    fraction of the segments is longer (`length_ladder_kernel`: a groom mixing short and long
    strands would otherwise send all of its long strands' segments down the long path). Cells
    are _CELL_FACTOR x a typical query's radius. Sizing both by the longest segment made every query pay for it: an L-BFGS
    trial point with one segment stretched to 72 mm took 0.6-1.2 s (docs/contact.md). The
    mean length is summed in fixed point (1 nm), so the scales are the same in every run.
    """
    b, m, n, _ = x4.shape
    device = x4.device
    num_segments = b * m * (n - 1)
    slots = int(hh_kernels.SEGMENT_STAT_SLOTS)
    length_sums = torch.zeros(slots, dtype=torch.int64, device=device)
    maxima = torch.zeros(2, slots, dtype=torch.float32, device=device)  # longest length, largest |x|
    params = torch.empty(4, dtype=torch.float32, device=device)
    wp_device = _warp.warp_device(device)
    stats = [_warp.as_warp(length_sums), _warp.as_warp(maxima[0]), _warp.as_warp(maxima[1])]
    with _warp.launch_scope(device):
        _warp.launch(hh_kernels.segment_stats_kernel, dim=num_segments,
                     inputs=[_warp.as_warp(x4, vec3=True), n], outputs=stats, device=wp_device)
        _warp.launch(hh_kernels.grid_params_kernel, dim=1,
                     inputs=stats + [num_segments, float(cutoff), _LONG_FACTOR, _CELL_FACTOR, _RADIUS_SLACK],
                     outputs=[_warp.as_warp(params)], device=wp_device)
        if long_fraction is not None:
            counts = torch.zeros(int(hh_kernels.LENGTH_LADDER_STEPS) * int(hh_kernels.LENGTH_LADDER_SLOTS),
                                 dtype=torch.int32, device=device)
            params_wp = _warp.as_warp(params)
            _warp.launch(hh_kernels.length_ladder_kernel, dim=num_segments,
                         inputs=[_warp.as_warp(x4, vec3=True), n, params_wp], outputs=[_warp.as_warp(counts)],
                         device=wp_device)
            _warp.launch(hh_kernels.grid_params_from_ladder_kernel, dim=1,
                         inputs=[_warp.as_warp(counts), num_segments, float(long_fraction), float(cutoff), _CELL_FACTOR,
                                 _RADIUS_SLACK], outputs=[params_wp], device=wp_device)
    return params


class _CpuGrid:
    """The broad phase's grid on the CPU, for `hair_hair_pairs_cpu_kernel`: a dense grid over
    the hair's bounding box (cells `_CPU_CELL_FACTOR` x `_grid_params`'s width, at most
    `_CPU_MAX_CELLS_PER_SEGMENT` per segment: wider cells past that), the segments sorted by
    cell key with their midpoints and half lengths packed (x, y, z, half length), and each
    key's first index (`cell_start`, one past the end at key + 1).

    Each segment queries within a radius set by its own length (the kernel's docstring), so
    every pair closer than the cutoff is found once: the pairs of the device's cells kind. The
    bounding box is read back to size the grid: there is no graph to capture on the CPU.
    """

    def __init__(self, x4: torch.Tensor, cutoff: float):
        b, m, n, _ = x4.shape
        self.shape = (b, m, n)
        self.num_segments = b * m * (n - 1)
        self.params = _grid_params(x4, cutoff)
        flat = x4.detach().reshape(-1, 3)
        low = flat.min(dim=0).values.to(torch.float32)
        extent = (flat.max(dim=0).values.to(torch.float32) - low).tolist()
        width = float(self.params[0]) * _CPU_CELL_FACTOR
        max_cells = max(_CPU_MAX_CELLS_PER_SEGMENT * self.num_segments, 4096)
        while True:
            dims = [int(e / width) + 1 for e in extent]
            if b * dims[0] * dims[1] * dims[2] <= max_cells:
                break
            width *= 1.25  # wider cells: more candidates per query, never a missed pair
        self.origin = wp.vec3(*low.tolist())
        self.inv_width = 1.0 / width
        self.dims = wp.vec3i(*dims)
        num_cells = b * dims[0] * dims[1] * dims[2]
        bounds = torch.empty(self.num_segments, 4, dtype=torch.float32)
        keys = torch.empty(self.num_segments, dtype=torch.int32)
        self.x_wp = _warp.as_warp(flat, vec3=True)
        self.params_wp = _warp.as_warp(self.params)
        _warp.launch(hh_kernels.segment_keys_kernel, dim=self.num_segments,
                     inputs=[self.x_wp, n, m, self.origin, self.inv_width, self.dims],
                     outputs=[wp.from_torch(bounds, dtype=wp.vec4), _warp.as_warp(keys)], device="cpu")
        self.ids = torch.empty(self.num_segments, dtype=torch.int32)
        self.half_lengths = bounds[:, 3]
        self.bounds = torch.empty_like(bounds)
        cell_start = torch.zeros(num_cells + 2, dtype=torch.int32)
        _warp.launch(hh_kernels.dense_counting_sort_kernel, dim=1,
                     inputs=[_warp.as_warp(keys), wp.from_torch(bounds, dtype=wp.vec4), num_cells],
                     outputs=[_warp.as_warp(cell_start), _warp.as_warp(self.ids),
                           wp.from_torch(self.bounds, dtype=wp.vec4)], device="cpu")
        self.cell_start = cell_start[:num_cells + 1]

    def long_segments(self) -> torch.Tensor:
        """(S,) bool by segment id: half length above the grid's long threshold H (as the kernel decides)."""
        return self.half_lengths > self.params[1]

    def pairs(self, x4, skip_root_segments, cutoff, queried, count, pairs, room, energy=None) -> None:
        """Launch `hair_hair_pairs_cpu_kernel`: every segment queries (`queried` None), or those
        with queried[id] != 0 (int32 by id), adding to `count` and `pairs` (room for `room`),
        and with `energy` (a `_PairEnergyArgs`) each pair's energy and gradient.
        """
        b, m, n = self.shape
        if queried is None:
            ranks = _arange_int32(self.num_segments)
            by_rank = ranks[:1]
            all_queried = 1
        else:
            by_rank = queried[self.ids]
            ranks = torch.nonzero(by_rank).reshape(-1).to(torch.int32)
            all_queried = 0
        if ranks.shape[0] == 0:
            return
        _warp.launch(
            hh_kernels.hair_hair_pairs_cpu_kernel,
            dim=ranks.shape[0],
            inputs=[self.x_wp, wp.from_torch(self.bounds, dtype=wp.vec4), _warp.as_warp(self.ids),
                    _warp.as_warp(self.cell_start), self.origin, self.inv_width, self.dims, _warp.as_warp(ranks),
                    _warp.as_warp(by_rank), all_queried, self.params_wp, n, m, skip_root_segments, float(cutoff),
                    _RADIUS_SLACK, _warp.scalar(cutoff, x4.dtype), room,
                    *_PairEnergyArgs.inputs(energy, x4)],
            outputs=[_warp.as_warp(count), _warp.as_warp(pairs), *_PairEnergyArgs.outputs(energy, x4.dtype)],
            device="cpu",
        )


@dataclass
class _PairEnergyArgs:
    """What the CPU pair kernels need to add each pair's energy and gradient as they find it
    (the arguments of `hair_hair_energy_kernel`): barrier parameters, weight, variant id, and
    the (B,) float64 energy and (B, M, N, 3) gradient they add to.
    """

    xi: float
    dhat: float
    bp: torch.Tensor  # (1,): `join_fraction_tensor`
    weight: float
    variant_id: int
    energy: torch.Tensor
    gradient: torch.Tensor

    @staticmethod
    def inputs(args: _PairEnergyArgs | None, like: torch.Tensor, mode: int = 1) -> list:
        """with_energy, xi, dhat, bp, weight, variant of the kernels (zeros without `args`);
        `mode` the kernels' with_energy (1: every pair found adds to energy[batch item]; 3: to
        energy[lower segment id], counted per segment, no pair list).
        """
        dtype = like.dtype
        if args is None:  # the kernels read a join fraction all the same: a stand-in
            zero = _warp.scalar(0.0, dtype)
            return [0, zero, zero, _warp.as_warp(torch.zeros(1, dtype=dtype, device=like.device)), zero, 0]
        return [mode, _warp.scalar(args.xi, dtype), _warp.scalar(args.dhat, dtype),
                _warp.as_warp(args.bp), _warp.scalar(args.weight, dtype), args.variant_id]

    @staticmethod
    def outputs(args: _PairEnergyArgs | None, dtype: torch.dtype) -> list:
        """energy_out, gradient_out of the kernels (one-element stand-ins without `args`)."""
        if args is None:
            stand_in = _energy_stand_ins.get(dtype)
            if stand_in is None:
                stand_in = _energy_stand_ins[dtype] = (torch.zeros(1, dtype=torch.float64),
                                                       torch.zeros(1, 3, dtype=dtype))
            return [_warp.as_warp(stand_in[0]), _warp.as_warp(stand_in[1], vec3=True)]
        return [_warp.as_warp(args.energy), _warp.as_warp(args.gradient, vec3=True)]


# Unwritten stand-ins for the energy outputs of a pair kernel launched without energy, by dtype.
_energy_stand_ins: dict[torch.dtype, tuple[torch.Tensor, torch.Tensor]] = {}


_aranges: dict[int, torch.Tensor] = {}


def _arange_int32(n: int) -> torch.Tensor:
    """0..n-1 as int32 on the CPU, kept per n (every call of one hair size needs the same)."""
    r = _aranges.get(n)
    if r is None:
        _aranges.clear()
        r = _aranges[n] = torch.arange(n, dtype=torch.int32)
    return r


def _broad_phase(x4, cutoff, capacity, skip_root_segments, on_overflow, max_pairs=None):
    """Broad phase on (B, M, N, 3) contiguous detached hair: the pair list.

    Returns:
        pairs (P, 2) int32 flat segment ids (unordered; in eager calls a view of the shared pair
        buffer, valid until the next call; with "defer" the whole buffer, rows past the count
        unused), count (the (1,) int32 device count), the count read back (None with
        "defer"), and the capacity used first.
    """
    b, m, n, _ = x4.shape
    num_segments = b * m * max(n - 1, 0)
    cap = default_max_pairs(num_segments) if max_pairs is None else max_pairs
    requested = default_capacity(num_segments) if capacity is None else capacity
    # The buffer never exceeds the cap; a larger capacity request is clamped to it.
    requested = min(requested, cap)
    device = x4.device
    if num_segments == 0 or m < 2:
        return (torch.zeros(0, 2, dtype=torch.int32, device=device), torch.zeros(1, dtype=torch.int32, device=device),
                0, requested)

    kind = _broad_phase_kind(device)
    if kind not in _BROAD_PHASE_KINDS:
        raise ValueError(f"broad phase: expected one of {list(_BROAD_PHASE_KINDS)}, got {kind!r}")
    if kind == "cpu-grid":
        if device.type != "cpu":
            raise ValueError(f"x: the CPU grid runs on the CPU only, got a tensor on {device}")
        grid = _CpuGrid(x4, cutoff)
        count = torch.zeros(1, dtype=torch.int32, device=device)

        def run(room):
            count.zero_()
            pairs = _pair_buffer(device, room, cap)
            grid.pairs(x4, skip_root_segments, cutoff, None, count, pairs, room)
            return pairs

        return _collect(run, count, requested, cap, capacity, num_segments, on_overflow)

    run, count = _cell_broad_phase(x4, cutoff, skip_root_segments, cap)
    return _collect(run, count, requested, cap, capacity, num_segments, on_overflow)


def _broad_phase_kind(device: torch.device) -> str:
    """"cpu-grid" (`_CpuGrid`) on the CPU, "cells" (`_cell_broad_phase`) on CUDA (the tests run
    the cells kind on the CPU by replacing this).
    """
    return "cpu-grid" if device.type == "cpu" else "cells"


# Threads of `hair_hair_cell_pairs_kernel` at most: each entry's resumed walk is shared by as
# many lanes (a power of two, at most 8) as keep the launch within this. A small batch leaves most
# of the GPU idle while the entries of crowded cells walk a hundred partners each, one thread
# apiece; at batch 32 the entries alone fill it (one lane).
_CELL_WALK_THREADS = 1 << 22


def _cell_walk_lanes(entries: int) -> int:
    """Lanes per entry of the resumed walks (`_CELL_WALK_THREADS`)."""
    lanes = 1
    while lanes < 8 and 2 * lanes * entries <= _CELL_WALK_THREADS:
        lanes *= 2
    return lanes


def _cell_table_size(num_segments: int) -> int:
    """Slots of the cell table: a power of two >= 4 slots per segment (a drape enters ~3 cells
    per segment, so most slots hold one cell).
    """
    return 1 << max(10, (4 * num_segments - 1).bit_length())


def _cell_broad_phase(x4, cutoff, skip_root_segments, cap, energy=None):
    """The device broad phase of boxes in hashed cells (`kernels.hair_hair_contact`,
    `segment_boxes_kernel` ...): returns (run, count) as `_collect` takes them (`run(room,
    out)` writes at most `room` pairs into `out`, by default the shared pair buffer). Any device
    (the CPU runs it in the tests); nothing read back to launch, so it can be captured.

    With `energy` (a `_PairEnergyArgs` whose `energy` holds one float64 per segment) the kernels
    write no pair list: every pair adds its energy and gradient, counted per segment
    (with_energy 3); `count` is then (S,) per segment and `run`'s room unused.

    Memory per call: room for 8 entries per segment (rank, packed id and box: 288 bytes), the
    segment's box, long flag and places in the long lists (36 bytes), the table (8 bytes per
    slot, 4-8 slots per segment) and the hit list (4 (_CELL_HIT_SLOTS + 1)
    _CELL_HIT_ROWS_PER_SEGMENT bytes: 84): ~450 bytes
    per segment (1.4 GiB for 1024 x 100 hair at batch 32), besides the pair buffer.
    """
    b, m, n, _ = x4.shape
    num_segments = b * m * (n - 1)
    device = x4.device
    wp_device = _warp.warp_device(device)
    params = _grid_params(x4, cutoff, _CELL_LONG_FRACTION)
    table = _cell_table_size(num_segments)
    entries = num_segments * int(hh_kernels.MAX_CELLS_PER_SEGMENT)
    box_lo = torch.empty(num_segments, 3, dtype=torch.float32, device=device)
    box_hi = torch.empty(num_segments, 3, dtype=torch.float32, device=device)
    long_flags = torch.empty(num_segments, dtype=torch.int32, device=device)
    long_count = torch.zeros(b + 1, dtype=torch.int32, device=device)  # per item, then all
    long_list = torch.empty(2 * num_segments, dtype=torch.int32, device=device)  # all, then per item
    ranks = torch.empty(entries, dtype=torch.int32, device=device)
    slot_count = torch.zeros(table, dtype=torch.int32, device=device)
    sorted_entries = torch.empty(entries, dtype=torch.int32, device=device)
    sorted_lo = torch.empty(entries, 3, dtype=torch.float32, device=device)
    sorted_hi = torch.empty(entries, 3, dtype=torch.float32, device=device)
    count = torch.zeros(1 if energy is None else num_segments, dtype=torch.int32, device=device)
    x_wp = _warp.as_warp(x4.reshape(-1, 3), vec3=True)
    params_wp = _warp.as_warp(params)
    half_cutoff32 = 0.5 * float(cutoff)
    boxes = [_warp.as_warp(box_lo, vec3=True), _warp.as_warp(box_hi, vec3=True), _warp.as_warp(long_flags)]
    with _warp.launch_scope(device):
        _warp.launch(hh_kernels.segment_boxes_kernel, dim=num_segments,
                     inputs=[x_wp, n, m, skip_root_segments, params_wp, half_cutoff32, _RADIUS_SLACK, table - 1],
                     outputs=boxes + [_warp.as_warp(ranks), _warp.as_warp(slot_count), _warp.as_warp(long_count),
                                   _warp.as_warp(long_list)], device=wp_device)
    slot_end = torch.cumsum(slot_count, 0, dtype=torch.int32)
    table_wp = [_warp.as_warp(slot_end), _warp.as_warp(slot_count)]
    sorted_wp = [_warp.as_warp(sorted_entries), _warp.as_warp(sorted_lo, vec3=True),
                 _warp.as_warp(sorted_hi, vec3=True)]
    with _warp.launch_scope(device):
        _warp.launch(hh_kernels.scatter_entries_kernel, dim=entries,
                     inputs=boxes + [_warp.as_warp(ranks)] + table_wp + [params_wp, n, m, table - 1],
                     outputs=sorted_wp, device=wp_device)

    # The short-short walk in two kernels (docs/contact.md 11): the first `hit_slots` partners of
    # each of the first `hit_rows` entries to a hit list, exactly tested over the list; what a
    # row could not hold, and the entries past the rows, walked again with the test inline.
    hit_slots = _CELL_HIT_SLOTS
    hit_rows = min(entries, _CELL_HIT_ROWS_PER_SEGMENT * num_segments) if hit_slots > 0 else 0
    hits = torch.empty(max(1, hit_rows * hit_slots), dtype=torch.int32, device=device)
    hit_state = torch.empty(max(1, hit_rows), dtype=torch.int32, device=device)
    hits_wp, hit_state_wp = _warp.as_warp(hits), _warp.as_warp(hit_state)

    walk_lanes = _cell_walk_lanes(entries)
    # With lanes to share them, the hits kernel leaves long walks to the pairs kernel.
    hit_walk_steps = _CELL_HIT_WALK_STEPS if walk_lanes > 1 else 1 << 30
    lanes = int(hh_kernels.LONG_LANES)
    list_stride = max(1, num_segments // lanes)  # long segments served at once (more: in turn)

    def run(room, out=None):
        count.zero_()
        if energy is not None:  # a rerun ("grow") starts the sums again
            energy.energy.zero_()
            energy.gradient.zero_()
        if energy is not None:
            room = 0  # no pair list
        pairs = _pair_buffer(device, room, cap) if out is None else out
        common_out = [_warp.as_warp(count), _warp.as_warp(pairs)] + _PairEnergyArgs.outputs(energy, x4.dtype)
        pair_inputs = [_warp.scalar(cutoff, x4.dtype), room] + _PairEnergyArgs.inputs(energy, x4, 3)
        # The long segments' kernel beside the cells kernel (CUDA): a few hundred threads
        # walking wide boxes, latency more than work (both add to the sums atomically).
        fork = StreamFork(device, "hair_hair_long")
        with fork, _warp.launch_scope(device):
            _warp.launch(hh_kernels.hair_hair_long_pairs_kernel, dim=list_stride * lanes,
                         inputs=[x_wp, boxes[0], boxes[1], _warp.as_warp(long_count), _warp.as_warp(long_list)]
                         + sorted_wp + table_wp
                         + [params_wp, n, m, skip_root_segments, table - 1, list_stride] + pair_inputs,
                         outputs=common_out, device=wp_device)
        with _warp.launch_scope(device):
            walk = sorted_wp + table_wp
            if hit_rows > 0:
                _warp.launch(hh_kernels.hair_hair_cell_hits_kernel, dim=entries,
                             inputs=walk + [params_wp, n, m, skip_root_segments, table - 1, hit_rows, hit_slots,
                                            hit_walk_steps],
                             outputs=[hits_wp, hit_state_wp], device=wp_device)
                _warp.launch(hh_kernels.hair_hair_hit_pairs_kernel, dim=hit_rows * hit_slots,
                             inputs=[x_wp, sorted_wp[0], hits_wp, hit_state_wp, hit_slots, n, m, skip_root_segments]
                             + pair_inputs,
                             outputs=common_out, device=wp_device)
            _warp.launch(hh_kernels.hair_hair_cell_pairs_kernel, dim=entries * walk_lanes,
                         inputs=[x_wp] + walk + [hit_state_wp, hit_rows, hit_slots, walk_lanes, entries, params_wp, n, m,
                                                 skip_root_segments, table - 1] + pair_inputs,
                         outputs=common_out, device=wp_device)
        fork.join()
        return pairs

    # What the hit list held, for tests and benchmarks: row states and the entries' end; the
    # long segments counted (per batch item, then all).
    run.hit_state, run.slot_end, run.hit_rows, run.hit_slots = hit_state, slot_end, hit_rows, hit_slots
    run.long_count = long_count
    return run, count


def _over_capacity(found, requested, cap, capacity, num_segments, on_overflow) -> None:
    """The rules every broad phase applies when it found more pairs than `requested`: "raise"
    raises; "grow" raises past the cap `max_pairs` and, for a default capacity, learns the count
    for later calls with as many segments ("warn" warns where the caller knows what was kept).
    """
    if on_overflow == "raise":
        raise HairHairCapacityError(found, requested)
    if on_overflow == "grow":
        if found > cap:
            raise HairHairCapacityError(found, requested, cap)
        if capacity is None:
            _learned_capacity[num_segments] = max(_learned_capacity.get(num_segments, 0), found + found // 4)


def _overflow_policy(count, capacity, num_segments, on_overflow, max_pairs) -> int:
    """`_collect`'s rules for a broad phase that summed every pair without a list (the cells
    energy): returns the capacity the call was given. "raise" and "warn" read `count` ((1,)
    device) and raise or warn as `_collect` does; "grow" and "defer" read nothing: with no list
    there is nothing to grow and no memory for `max_pairs` to bound, and the energy is complete
    either way (the count stays on the device for `HairHairContactInfo`). So an eager call on
    CUDA waits for nothing (a host read there cost 0.43 ms per call on an H100, docs/contact.md 9).
    """
    cap = default_max_pairs(num_segments) if max_pairs is None else max_pairs
    requested = min(default_capacity(num_segments) if capacity is None else capacity, cap)
    if on_overflow in ("defer", "grow"):
        return requested
    found = int(count.item())  # the one host read of an eager call
    if found > requested:
        _over_capacity(found, requested, cap, capacity, num_segments, on_overflow)
        if on_overflow == "warn":
            warnings.warn(
                f"hair-hair contact: {found} segment pairs found but capacity is {requested}; the energy "
                f"holds them all (the cells broad phase keeps no list). Pass capacity >= {found}.",
                RuntimeWarning,
                stacklevel=4,
            )
    return requested


def _collect(run, count, requested, cap, capacity, num_segments, on_overflow):
    """Run the pairs kernel (`run(room)` fills the pair buffer and `count`) and apply the
    overflow policy; returns what `_broad_phase` returns.
    """
    pairs = run(requested)
    if on_overflow == "defer":
        return pairs[:requested], count, None, requested
    found = int(count.item())  # the one host read of an eager call
    kept = found
    if found > requested:
        _over_capacity(found, requested, cap, capacity, num_segments, on_overflow)
        if on_overflow == "grow":
            # The same positions give the same pairs: one rerun with exactly enough room.
            pairs = run(found)
            again = int(count.item())
            if again != found:
                raise RuntimeError(f"hair-hair broad phase: rerun found {again} pairs, first run {found}")
        else:
            kept = requested
            warnings.warn(
                f"hair-hair contact: {found} segment pairs found but capacity is {requested}; "
                f"{found - requested} pairs dropped from the energy. Pass capacity >= {found}.",
                RuntimeWarning,
                stacklevel=4,
            )
    return pairs[:kept], count, found, requested


class HairHairPairCache:
    """A hair-hair pair list kept across calls on the CPU, for an optimizer's many evaluations
    of slowly changing hair (a Verlet list, requeried per segment).

    A build stores the positions x_ref and every pair closer than cutoff + `skin` there. At a
    later call, a segment "moved" if one of its vertices is more than `skin` * 0.45 from x_ref.
    Two segments that did not move are closer now than cutoff only if they were closer than
    cutoff + 0.9 `skin` at x_ref (a segment distance changes by at most the two segments'
    largest vertex displacements), so their pairs are the stored list's, filtered by the exact
    distance. The segments that moved (and every long one, see `hair_hair_pairs_cpu_kernel`)
    query the grid at the current positions for all their pairs. So the result is exactly the
    pairs a fresh broad phase finds, at any positions; only the cost depends on the motion.
    The list is rebuilt when more than `rebuild_fraction` of the segments moved, or when the
    shape, dtype, cutoff or root-segment rule change.

    Why per segment: in L-BFGS on a drape the free hair ends move by centimetres on a line
    search's trial points while ~70 % of the segments (resting on the body, near the roots)
    move by micrometres; a list rebuilt whenever any vertex moved more than half the skin was
    rebuilt at 44 of 45 evaluations (docs/contact.md).

    The energy and gradient are added by the pair kernels as they find each pair (the exact
    distance computed once; `_PairEnergyArgs`), in the same order of the two segments as
    `hair_hair_energy_kernel`, so the same numbers up to summation order.

    Args:
        skin: margin of the stored list [m], > 0 (1 mm: on the L-BFGS drape of docs/contact.md
            0.5-2 mm cost the same within noise, 3 mm more; the hanging tips move centimetres).
        rebuild_fraction: rebuild when more than this share of the segments moved, in (0, 1].

    Attributes:
        builds: lists built so far.
        calls: calls served.
        requeried: segments that queried the grid at the last call (0 after a build).
    """

    def __init__(self, skin: float = 1e-3, rebuild_fraction: float = 0.5):
        self.skin = check_positive("skin", skin)
        if not 0.0 < float(rebuild_fraction) <= 1.0:
            raise ValueError(f"rebuild_fraction: expected a number in (0, 1], got {rebuild_fraction!r}")
        self.rebuild_fraction = float(rebuild_fraction)
        self.builds = 0
        self.calls = 0
        self.requeried = 0
        self._key = None
        self._reference = None
        self._candidates = None
        self._stored = None  # (1,) int32: the rows of _candidates
        self._room = 0  # pair-buffer rows for the next call: 1.25 x the last call's pairs

    def reset(self) -> None:
        """Forget the stored list (the next call builds one)."""
        self._key = self._reference = self._candidates = self._stored = None

    def __repr__(self) -> str:
        stored = 0 if self._candidates is None else self._candidates.shape[0]
        return (f"HairHairPairCache(skin={self.skin}, rebuild_fraction={self.rebuild_fraction}, builds={self.builds}, "
                f"calls={self.calls}, stored_pairs={stored})")


def _moved_segments(x4: torch.Tensor, reference: torch.Tensor, threshold: float) -> torch.Tensor:
    """(S,) bool by flat segment id: a vertex of the segment is more than `threshold` [m] from `reference`."""
    d = (x4 - reference).square().sum(dim=-1)
    seg = torch.maximum(d[..., 1:], d[..., :-1])
    return (seg > threshold * threshold).reshape(-1)


def _cached_broad_phase(x4, cutoff, skip_root_segments, max_pairs, cache: HairHairPairCache, energy=None):
    """`_broad_phase` ("grow") on the CPU through `cache` (see `HairHairPairCache`): the same pairs.

    With `energy` (a `_PairEnergyArgs`) the pair kernels add each pair's energy and gradient
    to it as they find the pair (the exact distance computed once) and write no pair list:
    the pairs returned are then empty, the count is the pairs' count.
    """
    b, m, n, _ = x4.shape
    num_segments = b * m * max(n - 1, 0)
    cap = default_max_pairs(num_segments) if max_pairs is None else max_pairs
    device = x4.device
    cache.calls += 1
    if num_segments == 0 or m < 2:
        return (torch.zeros(0, 2, dtype=torch.int32, device=device), torch.zeros(1, dtype=torch.int32, device=device),
                0, 0)
    key = (tuple(x4.shape), x4.dtype, float(cutoff), skip_root_segments)
    moved = None
    if cache._key == key:
        moved = _moved_segments(x4, cache._reference, 0.45 * cache.skin)
        if int(moved.sum()) > cache.rebuild_fraction * num_segments:
            moved = None
    if moved is None:
        # Build: every pair within cutoff + skin here, from a grid sized for that reach.
        wide = cutoff + cache.skin
        grid = _CpuGrid(x4, wide)
        count = torch.zeros(1, dtype=torch.int32)
        room = max(4 * num_segments, 1) if cache._candidates is None else cache._candidates.shape[0] * 5 // 4 + 1
        for _ in range(2):
            candidates = torch.empty(room, 2, dtype=torch.int32)
            count.zero_()
            grid.pairs(x4, skip_root_segments, wide, None, count, candidates, room)
            stored = int(count.item())
            if stored <= room or stored > cap:
                break
            room = stored
        if stored > cap:
            # A pile far denser than a drape: no list kept (its memory stays within max_pairs).
            cache.reset()
            pairs, count, found, requested = _broad_phase(x4, cutoff, None, skip_root_segments, "grow", max_pairs)
            if energy is not None:
                _pair_energies(x4, pairs, count, energy)
                pairs = pairs[:0]
            return pairs, count, found, requested
        cache._candidates = candidates[:stored].clone()
        cache._stored = torch.tensor([stored], dtype=torch.int32)
        cache._reference = x4.detach().clone()
        cache._key = key
        cache.builds += 1
        queried = torch.zeros(num_segments, dtype=torch.int32)
        grid = None
    else:
        grid = _CpuGrid(x4, cutoff)
        queried = (moved | grid.long_segments()).to(torch.int32)
    cache.requeried = int(queried.sum())
    candidates = cache._candidates
    count = torch.zeros(1, dtype=torch.int32)
    x_wp = _warp.as_warp(x4.reshape(-1, 3), vec3=True)

    def run(room):
        count.zero_()
        pairs = _pair_buffer(device, room, cap)
        if grid is not None and cache.requeried > 0:
            grid.pairs(x4, skip_root_segments, cutoff, queried, count, pairs, room, energy)
        if candidates.shape[0] > 0:
            _warp.launch(hh_kernels.hair_hair_candidates_kernel, dim=candidates.shape[0],
                         inputs=[x_wp, _warp.as_warp(candidates), _warp.as_warp(cache._stored),
                                 _warp.as_warp(queried), n, m,
                              _warp.scalar(cutoff, x4.dtype), room, *_PairEnergyArgs.inputs(energy, x4)],
                         outputs=[_warp.as_warp(count), _warp.as_warp(pairs),
                               *_PairEnergyArgs.outputs(energy, x4.dtype)], device="cpu")
        return pairs

    # Room for the config's pairs per segment, or 1.25 x the last call's count: no rerun as the
    # count jumps on a line search's trial point (pages never written cost nothing on the CPU).
    requested = min(max(cache._room, default_capacity(num_segments), 1), cap)
    if energy is not None:
        # Nothing written, so nothing to grow: one pass, the count checked against the cap.
        run(0)
        found = int(count.item())
        if found > cap:
            raise HairHairCapacityError(found, requested, cap)
        cache._room = max(found + found // 4, 1)
        return torch.zeros(0, 2, dtype=torch.int32), count, found, requested
    pairs, count, found, requested = _collect(run, count, requested, cap, requested, num_segments, "grow")
    cache._room = max(found + found // 4, 1)
    return pairs, count, found, requested


class HairHairPairList:
    """A hair-hair pair list kept in device buffers across the calls of CUDA graphs (a Verlet
    list): the physics' implicit-Euler steps move the hair millimetres over a step's hundred
    energy calls, where the cells broad phase at every call was 0.31-0.50 ms of a ~1 ms
    iteration on one H100 (docs/physics.md, section 2).

    `build(x)` stores every pair within cutoff + `skin` at x (the cells broad phase into a fixed
    buffer) and x itself. An energy call over the list (`hair_hair_contact_energy(...,
    pair_list=...)`) sums the stored pairs within the cutoff, by their exact distances. While no
    vertex is more than 0.45 `skin` from where the list was built, the list holds every pair
    within the cutoff (two segments' distance changes by at most the sum of their vertices'
    largest moves, 0.9 `skin`), so the energy and gradient are a fresh broad phase's up to the
    float order of the sums; `mark_stale(x)` raises `stale` where x is past that. Nothing here
    reads the device: the caller checks the points it keeps (the physics: its iterate, once a
    chunk; a line search's far trial that is rejected needs no list) and builds again.

    Args:
        shape: (B, M, N) of the hair.
        cutoff: xi + dhat of the contact [m].
        skin: the list's margin [m], > 0.
        capacity: rows of the pair buffer; a build that finds more pairs writes the first ones
            and counts them all (`overflowed()`).
        device, dtype: of the hair.
        skip_root_segments: as `hair_hair_contact_energy`'s.

    Attributes:
        pairs: (capacity, 2) int32 flat segment ids (i < j) of the last build.
        count: (1,) int32 the pairs the last build found (may exceed `capacity`).
        reference: (B, M, N, 3) the positions of the last build [m].
        stale: (1,) int32, 1 once `mark_stale` saw a vertex beyond 0.45 `skin` of `reference`.
    """

    def __init__(self, shape, cutoff: float, skin: float, capacity: int, device, dtype=torch.float32, *,
                 skip_root_segments: int = DEFAULT_SKIP_ROOT_SEGMENTS):
        b, m, n = (int(v) for v in shape)
        self.cutoff = check_positive("cutoff", cutoff)
        self.skin = check_positive("skin", skin)
        if int(capacity) < 1:
            raise ValueError(f"capacity: expected >= 1 pair rows, got {capacity}")
        self.capacity = int(capacity)
        self.skip_root_segments = int(skip_root_segments)
        self.shape = (b, m, n)
        device = torch.device(device)
        self.pairs = torch.zeros(self.capacity, 2, dtype=torch.int32, device=device)
        self.count = torch.zeros(1, dtype=torch.int32, device=device)
        self.reference = torch.zeros(b, m, n, 3, dtype=dtype, device=device)
        self.stale = torch.zeros(1, dtype=torch.int32, device=device)
        self._none_queried = torch.zeros(max(b * m * (n - 1), 1), dtype=torch.int32, device=device)

    def build(self, x: torch.Tensor) -> None:
        """Store the pairs within cutoff + skin of hair x (B, M, N, 3) and x (graph-safe)."""
        x4 = x.detach().reshape(*self.shape, 3).contiguous()
        num_segments = self.shape[0] * self.shape[1] * (self.shape[2] - 1)
        run, count = _cell_broad_phase(x4, self.cutoff + self.skin, self.skip_root_segments,
                                       max(self.capacity, default_max_pairs(num_segments)))
        run(self.capacity, out=self.pairs)
        self.count.copy_(count)
        self.reference.copy_(x4)
        self.stale.zero_()

    def overflowed(self) -> bool:
        """Whether the last build found more pairs than the buffer holds (reads the device)."""
        return int(self.count) > self.capacity

    def mark_stale(self, x: torch.Tensor) -> None:
        """Stale = 1 if a vertex of hair x (B, M, N, 3) is more than 0.45 `skin` from `reference`
        (graph-safe; stays 1 until the next build).
        """
        x4 = x.detach().reshape(*self.shape, 3).contiguous()
        with _warp.launch_scope(x4.device):
            _warp.launch(hh_kernels.pair_list_stale_kernel, dim=x4.numel() // 3,
                         inputs=[_warp.as_warp(x4.reshape(-1, 3), vec3=True),
                                 _warp.as_warp(self.reference.reshape(-1, 3), vec3=True),
                                 _warp.scalar(0.45 * self.skin, x4.dtype)],
                         outputs=[_warp.as_warp(self.stale)], device=_warp.warp_device(x4.device))

    def add_energy(self, x4: torch.Tensor, energy: _PairEnergyArgs) -> None:
        """Add the listed pairs' energies and gradients at x4 to `energy` (per segment: with_energy
        3; graph-safe).
        """
        b, m, n, _ = x4.shape
        x_wp = _warp.as_warp(x4.reshape(-1, 3), vec3=True)
        wp_device = _warp.warp_device(x4.device)
        per_segment = torch.zeros(b * m * (n - 1), dtype=torch.int32, device=x4.device)
        with _warp.launch_scope(x4.device):
            _warp.launch(hh_kernels.hair_hair_candidates_kernel, dim=self.capacity,
                         inputs=[x_wp, _warp.as_warp(self.pairs), _warp.as_warp(self.count),
                                 _warp.as_warp(self._none_queried), n, m, _warp.scalar(self.cutoff, x4.dtype), 0,
                                 *_PairEnergyArgs.inputs(energy, x4, 3)],
                         outputs=[_warp.as_warp(per_segment), _warp.as_warp(self.pairs),
                                  *_PairEnergyArgs.outputs(energy, x4.dtype)], device=wp_device)


def _pair_energies(x4, pairs, count, energy) -> None:
    """Add the energy and gradient of the (P, 2) int32 `pairs` to `energy` (a `_PairEnergyArgs`)."""
    b, m, n, _ = x4.shape
    if pairs.shape[0] == 0:
        return
    with _warp.launch_scope(x4.device):
        _warp.launch(
            hh_kernels.hair_hair_energy_kernel,
            dim=pairs.shape[0],
            inputs=[_warp.as_warp(x4, vec3=True), _warp.as_warp(pairs.contiguous()), _warp.as_warp(count),
                    pairs.shape[0], n, m, _warp.scalar(energy.xi, x4.dtype), _warp.scalar(energy.dhat, x4.dtype),
                    _warp.as_warp(energy.bp), _warp.scalar(energy.weight, x4.dtype), energy.variant_id],
            outputs=[_warp.as_warp(energy.energy), _warp.as_warp(energy.gradient, vec3=True)],
            device=_warp.warp_device(x4.device),
        )


class _PrecomputedContactEnergy(torch.autograd.Function):
    """The (B,) energy and its gradient computed together outside autograd (the pair cache's
    fused pass): forward returns the energy, backward scales the stored gradient.
    """

    @staticmethod
    def forward(ctx, x4, energy, gradient):
        ctx.save_for_backward(gradient)
        return energy.to(x4.dtype, copy=True)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_energy):
        (gradient,) = ctx.saved_tensors
        return grad_energy[:, None, None, None] * gradient, None, None


class _HairHairContactEnergy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x4, pairs, count, xi, dhat, bp, weight, variant_id):
        b, m, n, _ = x4.shape
        energy = torch.zeros(b, dtype=torch.float64, device=x4.device)  # float64 sum: see the kernel
        gradient = torch.zeros_like(x4)
        num_pairs = pairs.shape[0]
        if num_pairs > 0:
            with _warp.launch_scope(x4.device):
                _warp.launch(
                    hh_kernels.hair_hair_energy_kernel,
                    dim=num_pairs,
                    inputs=[
                        _warp.as_warp(x4, vec3=True),
                        _warp.as_warp(pairs),
                        _warp.as_warp(count),
                        num_pairs,
                        n,
                        m,
                        _warp.scalar(xi, x4.dtype),
                        _warp.scalar(dhat, x4.dtype),
                        _warp.as_warp(join_fraction_tensor(bp, x4)),
                        _warp.scalar(weight, x4.dtype),
                        variant_id,
                    ],
                    outputs=[_warp.as_warp(energy), _warp.as_warp(gradient, vec3=True)],
                    device=_warp.warp_device(x4.device),
                )
        ctx.save_for_backward(gradient)
        return energy.to(x4.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_energy):
        (gradient,) = ctx.saved_tensors
        return grad_energy[:, None, None, None] * gradient, None, None, None, None, None, None, None


def hair_hair_contact_pairs(
    x: torch.Tensor,
    xi: float,
    dhat: float,
    capacity: int | None = None,
    *,
    skip_root_segments: int = DEFAULT_SKIP_ROOT_SEGMENTS,
    on_overflow: str = "grow",
    max_pairs: int | None = None,
) -> HairHairPairs:
    """Broad phase of hair-hair contact: segment pairs closer than xi + dhat (not differentiable).

    Args:
        x: hair positions [m], (M, N, 3) or (B, M, N, 3), float32 or float64; vertex 0 the root.
        xi: hard barrier [m] (the guide bundle's diameter).
        dhat: soft barrier width [m]; pairs with distance < xi + dhat are returned.
        capacity: pair-buffer size; None = `default_capacity(B * M * (N - 1))`: the config's
            `hair_hair_capacity_per_segment` per segment, raised after a call had to grow.
        skip_root_segments: segments with index below this along each strand take no part
            (2: those touching the fixed vertices 0 and 1; see the module notes).
        on_overflow: what to do when more pairs than `capacity` are found: "grow" (rerun with
            a buffer of exactly the needed size; complete result), "raise"
            (`HairHairCapacityError` with the needed count) or "warn" (RuntimeWarning, keep the
            first `capacity` pairs found; which ones is arbitrary on the GPU).
        max_pairs: cap on the pair buffer [pairs], 8 bytes each; None =
            `DEFAULT_MAX_PAIRS_PER_SEGMENT` (64) per segment. `capacity` is clamped to it, and
            "grow" never grows past it: more pairs than that raise `HairHairCapacityError`
            naming `max_pairs`.

    Returns:
        `HairHairPairs` (pairs (P, 2) int64 flat segment ids, sorted; pair_count; overflow;
        capacity; shape).

    Raises:
        ValueError: naming the argument, for bad inputs.
        HairHairCapacityError: on overflow with `on_overflow="raise"`, or more pairs than
            `max_pairs` (not with the device's broad phase, boxes in hashed cells: its energy
            keeps no pair list, so nothing grows and nothing needs a cap; the count is read only
            when `info` is asked).
    """
    x4 = _check_hair(x)
    xi, dhat, _ = check_barrier_parameters(xi, dhat, 0.5)
    _check_options(capacity, skip_root_segments, on_overflow, max_pairs)
    if on_overflow == "defer":
        raise ValueError("on_overflow: 'defer' is for the energy (a CUDA graph); the pair list needs the count")
    x4 = x4.detach().contiguous()
    pairs, _, found, requested = _broad_phase(
        x4, xi + dhat, capacity, skip_root_segments, on_overflow, max_pairs
    )
    overflow = found > requested
    pairs = pairs.long()
    if pairs.shape[0] > 1:
        # Deterministic order (GPU atomics write in any order): lexicographic by (i, j).
        key = pairs[:, 0] * max(1, x4.shape[0] * x4.shape[1] * (x4.shape[2] - 1)) + pairs[:, 1]
        pairs = pairs[torch.argsort(key)]
    return HairHairPairs(pairs, found, overflow, requested, tuple(x4.shape[:3]))


def hair_hair_contact_energy(
    x: torch.Tensor,
    xi: float,
    dhat: float,
    bp: float | torch.Tensor,
    weight: float = 1.0,
    variant: str = "quadratic",
    capacity: int | None = None,
    *,
    skip_root_segments: int = DEFAULT_SKIP_ROOT_SEGMENTS,
    on_overflow: str = "grow",
    max_pairs: int | None = None,
    pair_cache: HairHairPairCache | None = None,
    pair_list: HairHairPairList | None = None,
) -> tuple[torch.Tensor, HairHairContactInfo]:
    """Hair-hair contact energy L_hh of HairFormer Eq. 12, differentiable w.r.t. `x`.

    L_hh = weight * sum over pairs (segment of strand m, segment of strand m' != m) with
    distance d < xi + dhat of B(d), per batch item (a sum, not a mean). Segments touching the
    fixed vertices 0 and 1 are left out (`skip_root_segments`), and those vertices get zero
    gradient; see the module notes for the rules and why.

    Args:
        x: hair positions [m], (M, N, 3) or (B, M, N, 3), float32 or float64; vertex 0 the root.
        xi: hard barrier [m]: the guide bundle's diameter (`EnergyConfig.hair_diameter`).
        dhat: soft barrier width [m] (`EnergyConfig.hair_hair_dhat`, 1.5 xi in the paper).
        bp: join fraction of the barrier in (0, 1) (`EnergyConfig.barrier_join_fraction`): a
            float, or a one-element tensor the kernels read at launch (a captured graph follows
            its value).
        weight: lambda_hh [J per pair at B = 1], >= 0 (`EnergyConfig.hair_hair_weight`).
        variant: barrier extrapolation, "quadratic" (default), "monotone" or "paper" (see `ops.barrier`).
        capacity: pair-buffer size; None = `EnergyConfig.hair_hair_capacity_per_segment` times
            the number of segments B * M * (N - 1), or 1.25 times the largest count an earlier
            call with as many segments had to grow to, if larger (`default_capacity`).
        skip_root_segments: segments with index below this along each strand take no part.
        on_overflow: "grow" (default: rerun with enough room, the energy is complete), "raise"
            (`HairHairCapacityError`), "warn" (RuntimeWarning; energy over the pairs kept) or
            "defer" (no host read at all, for CUDA graphs: the energy sums the first `capacity`
            pairs, and `info.check()` raises afterwards if more were found).
        max_pairs: cap on the pair buffer [pairs], 8 bytes each; None =
            `DEFAULT_MAX_PAIRS_PER_SEGMENT` (64) per segment. `capacity` is clamped to it, and
            "grow" never grows past it: more pairs than that raise `HairHairCapacityError`
            naming `max_pairs`.
        pair_cache: a `HairHairPairCache` to keep the pair list across calls (CPU only, with
            `on_overflow="grow"`; `capacity` is then ignored: the buffer follows the last
            call's count). The pairs, so the energy and gradient, are those of a call without
            it; calls on slowly moving hair (an optimizer's iterations) cost less.
        pair_list: a built `HairHairPairList` of this hair's shape: the energy of its stored
            pairs (any device, graph-safe; `capacity`, `on_overflow` and `max_pairs` are then
            the list's own), exact while x is within its reach (`HairHairPairList.mark_stale`).
            The info's pair count is the list's.

    Returns:
        (energy, info): energy of shape (B,) for batched input, () for (M, N, 3), dtype and
        device of `x`; info a `HairHairContactInfo` (pair_count, overflow, capacity; also
        readable as info["pair_count"]).

    Raises:
        ValueError: naming the argument, for bad inputs (shape, dtype, NaN/Inf, barrier
            parameters, variant, capacity, on_overflow).
        HairHairCapacityError: on overflow with `on_overflow="raise"`, or more pairs than
            `max_pairs` (not with the device's broad phase, boxes in hashed cells: its energy
            keeps no pair list, so nothing grows and nothing needs a cap; the count is read only
            when `info` is asked).
    """
    x4 = _check_hair(x)
    xi, dhat, bp = check_barrier_parameters(xi, dhat, bp)
    weight = check_positive("weight", weight, allow_zero=True)
    variant_id = barrier_variant_id(variant)
    _check_options(capacity, skip_root_segments, on_overflow, max_pairs)
    x4c = x4.contiguous()
    if pair_list is not None:
        if not isinstance(pair_list, HairHairPairList):
            raise ValueError(f"pair_list: expected None or a HairHairPairList, got {type(pair_list).__name__}")
        if pair_cache is not None:
            raise ValueError("pair_list, pair_cache: pass one of them")
        if tuple(x4c.shape[:3]) != pair_list.shape or pair_list.cutoff != xi + dhat:
            raise ValueError(f"pair_list: built for hair {pair_list.shape} and cutoff {pair_list.cutoff} m, got "
                             f"{tuple(x4c.shape[:3])} and {xi + dhat} m")
        b, m, n = x4c.shape[:3]
        args = _PairEnergyArgs(xi, dhat, join_fraction_tensor(bp, x4c), weight, variant_id,
                               torch.zeros(max(b * m * (n - 1), 1), dtype=torch.float64, device=x4c.device),
                               torch.zeros_like(x4c, memory_format=torch.contiguous_format))
        pair_list.add_energy(x4c.detach(), args)
        energy = _PrecomputedContactEnergy.apply(x4c, row_sums(args.energy[:b * m * (n - 1)].view(b, -1)),
                                                 args.gradient)
        if x.dim() == 3:
            energy = energy[0]
        return energy, HairHairContactInfo(pair_list.count, pair_list.capacity)
    if pair_cache is not None:
        if not isinstance(pair_cache, HairHairPairCache):
            raise ValueError(f"pair_cache: expected None or a HairHairPairCache, got {type(pair_cache).__name__}")
        if x4c.device.type != "cpu":
            raise ValueError(f"pair_cache: CPU only (x is on {x4c.device}); on CUDA use CapturedEnergy")
        if on_overflow != "grow":
            raise ValueError(f"pair_cache: needs on_overflow='grow', got {on_overflow!r}")
        b = x4c.shape[0]
        args = _PairEnergyArgs(xi, dhat, join_fraction_tensor(bp, x4c), weight, variant_id,
                               torch.zeros(b, dtype=torch.float64),
                               torch.zeros_like(x4c, memory_format=torch.contiguous_format))
        _, count, found, requested = _cached_broad_phase(
            x4c.detach(), xi + dhat, skip_root_segments, max_pairs, pair_cache, energy=args
        )
        energy = _PrecomputedContactEnergy.apply(x4c, args.energy, args.gradient)
        if x.dim() == 3:
            energy = energy[0]
        return energy, HairHairContactInfo(found, requested)
    if _broad_phase_kind(x4c.device) == "cells" and x4c.shape[0] >= 1 and x4c.shape[1] >= 2 and x4c.shape[2] >= 2:
        # The pair energies added by the pairs kernels as they find each pair, summed per segment:
        # no pair list (so no buffer to fill: the energy holds every pair, whatever the capacity),
        # no second launch, no counter or energy that every thread's atomics queue on. The count
        # is compared with the capacity as the other broad phases do (the same errors, warnings
        # and `info`), only the energy is never partial.
        b, m, n = x4c.shape[:3]
        num_segments = b * m * (n - 1)
        args = _PairEnergyArgs(xi, dhat, join_fraction_tensor(bp, x4c), weight, variant_id,
                               torch.zeros(num_segments, dtype=torch.float64, device=x4c.device),
                               torch.zeros_like(x4c, memory_format=torch.contiguous_format))
        run, per_segment = _cell_broad_phase(x4c.detach(), xi + dhat, skip_root_segments,
                                             default_max_pairs(num_segments) if max_pairs is None else max_pairs, args)
        run(0)
        count = per_segment.sum(dtype=torch.int32).reshape(1)
        requested = _overflow_policy(count, capacity, num_segments, on_overflow, max_pairs)
        energy = _PrecomputedContactEnergy.apply(x4c, row_sums(args.energy.view(b, -1)), args.gradient)
        if x.dim() == 3:
            energy = energy[0]
        return energy, HairHairContactInfo(count, requested)
    pairs, count, found, requested = _broad_phase(
        x4c.detach(), xi + dhat, capacity, skip_root_segments, on_overflow, max_pairs
    )
    energy = _HairHairContactEnergy.apply(x4c, pairs.contiguous(), count, xi, dhat, bp, weight, variant_id)
    if x.dim() == 3:
        energy = energy[0]
    return energy, HairHairContactInfo(count if found is None else found, requested)


__all__ = [
    "HairHairCapacityError",
    "HairHairContactInfo",
    "HairHairPairCache",
    "HairHairPairList",
    "HairHairPairs",
    "hair_hair_contact_energy",
    "hair_hair_contact_pairs",
]
