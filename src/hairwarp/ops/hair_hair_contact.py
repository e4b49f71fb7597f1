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

Broad phase: one grid over all segment midpoints of the whole batch, the batch item part of
each cell's slot, so a query only visits its own item: one sort and one launch for any batch
size, with no cross-item candidates to reject (one grid per item would cost B builds and B
launches; one grid without the item over items that overlap in space, as poses of one hairstyle
do, would make every query visit B times the candidates). Segments are sorted by slot with
`torch.sort`; cells are as wide as a typical query's radius (max segment length capped at
1.5 x the mean, + xi + dhat), computed on the device with the other scales of the grid.

Host synchronisations: none to launch. With `on_overflow` "grow", "raise" or "warn" the pair
count is read back once (to size the narrow phase and handle overflow). With "defer" nothing is
read: the narrow phase runs over the whole buffer (slots past the device count return at once),
and the count and overflow are read only when `HairHairContactInfo` is asked for them
(`check()` raises on overflow): the path a CUDA graph captures.

Memory: the pair buffer is one per device, reused across eager calls (grown to 1.25 x a call's
need, never shrunk), capped at `max_pairs` pairs of 8 bytes (default 64 per segment: 1.6 GiB for
1024 x 100 hair at batch 32, of which a drape touches ~1 pair per segment, 26 MiB); a call being
captured in a CUDA graph gets buffers of its own, sized by its capacity (the graph keeps them).
Besides it, a call holds ~36 bytes per segment (midpoint, half length, group, slot, sorted order),
the grid's slot table (2 MiB per batch item: 64^3 start and end indices) and the gradient (the
size of `x`). See docs/contact.md.
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
from hairwarp.ops.barrier import barrier_variant_id, check_barrier_parameters

OVERFLOW_POLICIES = ("grow", "raise", "warn", "defer")
DEFAULT_SKIP_ROOT_SEGMENTS = 2
# Slots of the grid table per batch item (`kernels.hair_hair_contact.GRID_DIM` cubed).
_GRID_SLOTS = 64**3
# The grid works on float32 midpoints; this relative slack on the query radius covers their
# rounding, so no pair within the cutoff is missed (the exact test uses the input precision).
_RADIUS_SLACK = 1e-4
# Broad-phase shape, measured on the CPU and an H100 (docs/contact.md): a segment longer than _LONG_FACTOR
# times the mean is "long" (found from its own query), and grid cells are _CELL_FACTOR times
# a typical query's radius (fewer, fuller cells: each visited cell costs a lookup).
_LONG_FACTOR = 1.5
_CELL_FACTOR = 1.0


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
    configured = EnergyConfig().hair_hair_capacity_per_segment * num_segments
    return max(configured, _learned_capacity.get(num_segments, 0))


def _grid_params(x4: torch.Tensor, cutoff: float) -> torch.Tensor:
    """(3,) float32 on the device: cell width, long half length H, absolute slack [m] (no host read).

    Two segments closer than the cutoff have midpoints at most cutoff + (l_i + l_j) / 2 apart;
    the float32 midpoints add up to |coordinate| * 2^-24 each. Segments longer than
    _LONG_FACTOR x the mean are "long": their pairs are found from their own (wider) queries, so
    the others query within cutoff + their length / 2 + H only. Cells are _CELL_FACTOR x a typical
    query's radius. Sizing both by the longest segment made every query pay for it: an L-BFGS
    trial point with one segment stretched to 72 mm took 0.6-1.2 s (docs/contact.md).
    """
    lengths = (x4[:, :, 1:] - x4[:, :, :-1]).norm(dim=-1)
    long_half = 0.5 * torch.minimum(lengths.max(), _LONG_FACTOR * lengths.mean())
    absolute_slack = 4.0 * x4.abs().max() * 2.0**-23
    cell_width = (cutoff + 2.0 * long_half) * _CELL_FACTOR * (1.0 + _RADIUS_SLACK) + absolute_slack
    return torch.stack([cell_width, long_half, absolute_slack]).to(torch.float32)


def _broad_phase(x4, cutoff, capacity, skip_root_segments, on_overflow, max_pairs=None):
    """Broad phase on (B, M, N, 3) contiguous detached hair.

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

    x_flat = x4.detach().reshape(-1, 3)
    params = _grid_params(x4, cutoff)
    wp_device = _warp.warp_device(device)
    midpoints = torch.empty(num_segments, 3, dtype=torch.float32, device=device)
    half_lengths = torch.empty(num_segments, dtype=torch.float32, device=device)
    groups = torch.empty(num_segments, dtype=torch.int32, device=device)
    slots = torch.empty(num_segments, dtype=torch.int32, device=device)
    slot_start = torch.zeros(b * _GRID_SLOTS, dtype=torch.int32, device=device)
    slot_end = torch.zeros(b * _GRID_SLOTS, dtype=torch.int32, device=device)
    count = torch.zeros(1, dtype=torch.int32, device=device)
    x_wp = _warp.as_warp(x_flat, vec3=True)
    params_wp = _warp.as_warp(params)
    with _warp.launch_scope(device):
        mid_wp = wp.from_torch(midpoints, dtype=wp.vec3)
        half_wp = _warp.as_warp(half_lengths)
        group_wp = _warp.as_warp(groups)
        wp.launch(hh_kernels.segment_cells_kernel, dim=num_segments, inputs=[x_wp, n, m, params_wp],
                  outputs=[mid_wp, half_wp, group_wp, _warp.as_warp(slots)], device=wp_device)
    sorted_slots, order = torch.sort(slots)
    sorted_midpoints = midpoints[order]
    sorted_half_lengths = half_lengths[order]
    with _warp.launch_scope(device):
        wp.launch(hh_kernels.grid_ranges_kernel, dim=num_segments, inputs=[_warp.as_warp(sorted_slots), num_segments],
                  outputs=[_warp.as_warp(slot_start), _warp.as_warp(slot_end)], device=wp_device)
    order_wp = _warp.as_warp(order)

    def run(room):
        count.zero_()
        pairs = _pair_buffer(device, room, cap)
        with _warp.launch_scope(device):
            wp.launch(
                hh_kernels.hair_hair_pairs_kernel,
                dim=num_segments,
                inputs=[x_wp, wp.from_torch(sorted_midpoints, dtype=wp.vec3), _warp.as_warp(sorted_half_lengths),
                        group_wp, order_wp, _warp.as_warp(slot_start),
                        _warp.as_warp(slot_end), params_wp, n, skip_root_segments, float(cutoff), _RADIUS_SLACK,
                        _warp.scalar(cutoff, x4.dtype), room],
                outputs=[_warp.as_warp(count), _warp.as_warp(pairs)],
                device=wp_device,
            )
        return pairs

    pairs = run(requested)
    if on_overflow == "defer":
        return pairs[:requested], count, None, requested
    found = int(count.item())  # the one host read of an eager call
    kept = found
    if found > requested:
        if on_overflow == "raise":
            raise HairHairCapacityError(found, requested)
        if on_overflow == "grow" and found > cap:
            raise HairHairCapacityError(found, requested, cap)
        if on_overflow == "grow":
            if capacity is None:
                learned = max(_learned_capacity.get(num_segments, 0), found + found // 4)
                _learned_capacity[num_segments] = learned
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
                stacklevel=3,
            )
    return pairs[:kept], count, found, requested


class _HairHairContactEnergy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x4, pairs, count, xi, dhat, bp, weight, variant_id):
        b, m, n, _ = x4.shape
        energy = torch.zeros(b, dtype=torch.float64, device=x4.device)  # float64 sum: see the kernel
        gradient = torch.zeros_like(x4)
        num_pairs = pairs.shape[0]
        if num_pairs > 0:
            with _warp.launch_scope(x4.device):
                wp.launch(
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
                        _warp.scalar(bp, x4.dtype),
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
            `max_pairs`.
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
    bp: float,
    weight: float = 1.0,
    variant: str = "quadratic",
    capacity: int | None = None,
    *,
    skip_root_segments: int = DEFAULT_SKIP_ROOT_SEGMENTS,
    on_overflow: str = "grow",
    max_pairs: int | None = None,
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
        bp: join fraction of the barrier in (0, 1) (`EnergyConfig.barrier_join_fraction`).
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

    Returns:
        (energy, info): energy of shape (B,) for batched input, () for (M, N, 3), dtype and
        device of `x`; info a `HairHairContactInfo` (pair_count, overflow, capacity; also
        readable as info["pair_count"]).

    Raises:
        ValueError: naming the argument, for bad inputs (shape, dtype, NaN/Inf, barrier
            parameters, variant, capacity, on_overflow).
        HairHairCapacityError: on overflow with `on_overflow="raise"`, or more pairs than
            `max_pairs`.
    """
    x4 = _check_hair(x)
    xi, dhat, bp = check_barrier_parameters(xi, dhat, bp)
    weight = check_positive("weight", weight, allow_zero=True)
    variant_id = barrier_variant_id(variant)
    _check_options(capacity, skip_root_segments, on_overflow, max_pairs)
    x4c = x4.contiguous()
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
    "HairHairPairs",
    "hair_hair_contact_energy",
    "hair_hair_contact_pairs",
]
