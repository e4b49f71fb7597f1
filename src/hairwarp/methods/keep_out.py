"""The body pass: hair pushed out of the body with its rest lengths kept.

The inertial step shows every frame through it, and the network methods by default
(`MethodOptions.keep_out`): a network's drape may leave vertices inside the body, which no
rigid placement with none inside should ever get back.
"""

from __future__ import annotations

import itertools
import math

import torch

# The body pass: vertices nearer the body than half this [m] are pushed to it, in at most this
# many rounds (it stops at the first round that finds none). Pushing only those nearer than half
# the margin ends the rounds early: vertices the projection leaves a hair's breadth under the
# margin would otherwise start one more round each time (a bob and long curly hair at 512
# strands ran all eight rounds; pushing at half the margin, four and five).
KEEP_OUT_MARGIN = 1.0e-3
KEEP_OUT_PASSES = 8
KEEP_OUT_TRIGGER = 0.5
# Vertices still inside after the last round and shallower than this many margins are pushed out
# without the projection.
KEEP_OUT_FINAL_DEPTH = 1.0
# Rounds of turning strands out of pinches between body parts (`_turn_out_of_pinches`).
KEEP_OUT_TURNS = 12
# Distances queried exactly up to this [m]; farther vertices are left alone.
_KEEP_OUT_QUERY = 1.0e-2


def keep_out_of_body(x: torch.Tensor, rigid: torch.Tensor, body, *, margin: float = KEEP_OUT_MARGIN,
                     passes: int = KEEP_OUT_PASSES, trigger: float = KEEP_OUT_TRIGGER,
                     turns: int = KEEP_OUT_TURNS, final_depth: float = KEEP_OUT_FINAL_DEPTH) -> torch.Tensor:
    """Hair pushed out of the body with its rest lengths kept (up to a crease: see below).

    Each round pushes every moving vertex (index >= 2) that lies inside the body or nearer its
    surface than `trigger` x `margin` along the signed distance's gradient to `margin`
    (`hairwarp.ops.hair_body_keep_out_push`: a query and a push kernel, the count left on the
    device), then projects the strands back onto the rigid placement's segment lengths
    (follow-the-leader), which can move later vertices in again: hence a few rounds
    (`pushed_out_of_body`). Should every round find some, each
    strand still inside is turned out of the pinch that holds it (`_turn_out_of_pinches`, up to
    `turns` rounds), then the vertices still inside and less than `final_depth` x `margin` deep
    are pushed out without the projection (each by `margin` plus its depth, which stretches its
    two segments by as much); deeper ones stay.

    Args:
        x: (B, M, N, 3) hair positions [m].
        rigid: (B, M, N, 3) the rigid placement of the same frames (its rest lengths) [m].
        body: the frames' `BodyMesh` (batch 1 or B).
        margin: [m] >= 0.
        passes: at most this many rounds (>= 1); the pass stops at a round that moves nothing.
        trigger: the share of `margin` below which a round pushes a vertex, in (0, 1].
        turns: at most this many rounds of `_turn_out_of_pinches` (0: none).
        final_depth: vertices left inside less than this many margins deep are pushed out
            without the projection (0: none; inf: every one).

    Returns:
        (B, M, N, 3) positions [m] (no autograd).

    Raises:
        ValueError: naming the argument for a wrong shape, dtype or device, NaN/Inf in `x`, or a
            margin that is not a finite number >= 0 (checked once, not per round).
    """
    from hairwarp.ops import hair_body_keep_out_push

    _check_arguments(x, rigid, body, margin)
    x, rounds = pushed_out_of_body(x, rigid, body, margin=margin, passes=passes, trigger=trigger, check=False)
    if rounds < passes:
        return x
    # The rounds ran out. Where two body parts meet (the arm against the torso) the push takes a
    # vertex out of one into the other: those strands are turned out of the pinch instead.
    x = _turn_out_of_pinches(x, rigid, body, margin=margin, rounds=turns)
    # A segment across a crease of the body can still take its end back inside at every
    # projection (one vertex in 10^5 of long straight hair on the shoulders, 0.3 mm deep).
    # Those shallow vertices alone are pushed out without the projection, each by the margin plus
    # its depth (its two segments stretch by as much). Deeper ones stay: pushed without the
    # projection they stretched whole strands (whiplash at full size: a frame's segments 1.5 %
    # longer on average, eighteenth session).
    return hair_body_keep_out_push(x, body, margin=margin, push_below=0.0, push_above=-final_depth * margin,
                                   max_distance=_KEEP_OUT_QUERY, check=False)[0]


def pushed_out_of_body(x: torch.Tensor, rigid: torch.Tensor, body, *, margin: float = KEEP_OUT_MARGIN,
                       passes: int = KEEP_OUT_PASSES, trigger: float = KEEP_OUT_TRIGGER,
                       check: bool = True) -> tuple[torch.Tensor, int]:
    """The rounds of `keep_out_of_body` alone: push (`hair_body_keep_out_push`), then project
    (follow-the-leader), until a round pushes nothing or `passes` rounds have pushed; each round
    after the first queries only the strands the round before it pushed.

    Args:
        x, rigid, body, margin, passes, trigger: as `keep_out_of_body`'s.
        check: validate the arguments (False: a caller that did).

    Returns:
        ((B, M, N, 3) positions [m]: the input of the first round that pushed nothing, bit for
        bit, or the last round's projection; the number of rounds that pushed, == passes when
        every round did).
    """
    from hairwarp.ops import follow_the_leader, hair_body_keep_out_push

    if check:
        _check_arguments(x, rigid, body, margin)
    pushed_counts = _RoundCounts(passes, x.device)
    # After the first round only the strands the last round pushed are queried: the others are
    # as that round found them (the projection leaves a strand at its rest lengths where it
    # was, up to rounding), so none of their vertices is near. At full size most rounds after
    # the first push a few strands of 1 024: the rest of each round's queries were wasted.
    flags = torch.zeros((2, *x.shape[:-2]), dtype=torch.int32, device=x.device)
    for k in range(passes):
        active, flagged = (None if k == 0 else flags[(k - 1) % 2]), flags[k % 2]
        flagged.zero_()
        pushed, _ = hair_body_keep_out_push(x, body, margin=margin, push_below=trigger * margin,
                                            max_distance=_KEEP_OUT_QUERY, pushed_count=pushed_counts.slot(k),
                                            active_strands=active, pushed_strands=flagged, check=False)
        # The count is read after the projection is queued (`_RoundCounts`: why every round).
        pushed_counts.send(k)
        projected = follow_the_leader(rigid, pushed, check=False)
        if pushed_counts.read(k) == 0:
            return x, k
        x = projected
    return x, passes


class _RoundCounts:
    """The pushed-vertex count of each round on the device, read by the host a round at a time.

    The rounds stop at the first that pushes nothing, so each round's count is read: one host
    synchronisation per round. On CUDA the read waits for the push alone: the count is copied
    to pinned host memory behind it and the round's projection is queued before the host waits,
    so the GPU projects while the host reads the count and queues the next round. A round that
    pushed nothing so wastes one projection (18 us on an H100 at 1 024 x 100, the tile kernel,
    docs/physics.md section 1), where reading first would idle the GPU for a host round trip
    (a copy, a wake-up and two launches: tens of microseconds, estimated, not measured) in
    every round that goes on. Measured on the 2-core CPU (long straight hair grown on the body
    at 128 x 100, its network drape), where every launch has finished when it returns: a read
    costs 1.3 us, a round (push and projection) 5.6 ms, a round's three launches alone ~40 us
    of host time. Rejected: reading every other round (a stop after an odd number of rounds
    then runs one more whole round: 5.6 ms there, an extra query on CUDA); kernels that skip on
    a device flag with one read at the end (all `passes` rounds are launched, ~40 us of host
    time each on the CPU, that rounds which stop early, the common case, never spend; it pays
    only for rounds replayed from a CUDA graph, and the pass's pinch turns are host-driven and
    its body and hair change from call to call). Built and measured in the twenty-first session,
    then removed: full size, one H100, alternated with this, 2.95 against 2.20 ms a drape (bob),
    4.20 against 4.02 (long curly), 7.40 against 7.51 (long straight); on the 2-core CPU 3-23 %
    slower. The GPU's rounds are bound by the host's launches, not by these reads.
    """

    def __init__(self, passes: int, device: torch.device):
        self._device = torch.zeros(max(passes, 1), dtype=torch.int32, device=device)
        self._cuda = device.type == "cuda"
        if self._cuda:
            self._host = torch.empty(max(passes, 1), dtype=torch.int32, pin_memory=True)
            self._sent = torch.cuda.Event()

    def slot(self, k: int) -> torch.Tensor:
        """Round k's counter, (1,) int32 on the device (zeroed)."""
        return self._device[k:k + 1]

    def send(self, k: int) -> None:
        """Start copying round k's count to the host (after the work queued so far)."""
        if self._cuda:
            self._host[k:k + 1].copy_(self._device[k:k + 1], non_blocking=True)
            self._sent.record()

    def read(self, k: int) -> int:
        """Round k's count, once `send(k)`'s copy has landed."""
        if self._cuda:
            self._sent.synchronize()
            return int(self._host[k])
        return int(self._device[k])


def _check_arguments(x: torch.Tensor, rigid: torch.Tensor, body, margin: float) -> None:
    """The body pass's arguments, checked once (its rounds run unchecked)."""
    from hairwarp._validate import check_tensor
    from hairwarp.ops import BodyMesh

    if not isinstance(body, BodyMesh):
        raise ValueError(f"body: expected a BodyMesh, got {type(body).__name__}")
    check_tensor("x", x, shape=(None, None, None, 3), device=body.device, allow_empty=False)
    check_tensor("rigid", rigid, shape=tuple(x.shape), dtypes=(x.dtype,), device=x.device, finite=False)
    if not (math.isfinite(float(margin)) and float(margin) >= 0.0):
        raise ValueError(f"margin: expected a finite number >= 0, got {margin}")


def _axes(like: torch.Tensor) -> torch.Tensor:
    """The 26 unit directions to a cube's faces, edges and corners, (26, 3)."""
    axes = torch.tensor([v for v in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(v)])
    return (axes / axes.norm(dim=-1, keepdim=True)).to(like)


def _slots(frame: torch.Tensor) -> torch.Tensor:
    """Each item's place among the items of its frame: (S,) long, from (S,) frame indices."""
    slot = torch.zeros_like(frame)
    for b in torch.unique(frame).tolist():
        chosen = frame == b
        slot[chosen] = torch.arange(int(chosen.sum()), device=frame.device)
    return slot


def _turn_out_of_pinches(x: torch.Tensor, rigid: torch.Tensor, body, *, margin: float, rounds: int) -> torch.Tensor:
    """(B, M, N, 3) positions [m] with each strand's first vertex inside the body turned about its
    predecessor, its segment's length kept, to the direction nearest its own that clears the body
    by half the margin (its own blended with the 26 axis and diagonal directions at five weights,
    and those 26 alone), the rest of the strand following (follow-the-leader); up to `rounds`
    times. Only the strands with a vertex inside are queried: a few in a groom.

    Where two body parts meet, the signed distance's gradient leads out of one part into the
    other, so pushing along it leaves a vertex inside; turning the segment finds the way out.
    The demo's scene on the 2-core CPU, the inertial step's 61 frames: 0.032 % of the vertices
    inside after the pushes, 0.0004 % with 12 rounds of this (`tools/keep_out_settings.py --scene
    demo`).
    """
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.ops import follow_the_leader, hair_body_signed_distance_and_normal

    if rounds <= 0:
        return x

    def signed_distance(points):
        # Only signs and clearances below half the margin are read: the capped query (exact inside
        # at any depth) skips the unbounded walk of every far vertex, which was the pass's largest
        # kernel where the rounds ran out (307-630 us of a drape on an H100, twenty-first session).
        return hair_body_signed_distance_and_normal(points, body, _KEEP_OUT_QUERY)[0]

    distance = signed_distance(x)
    inside = distance[..., NUM_FIXED_VERTICES:] < 0
    bs, ms = torch.nonzero(inside.any(-1), as_tuple=True)
    if len(bs) == 0:
        return x
    batch, n = x.shape[0], x.shape[2]
    # The stuck strands of every frame in one (B, S, ...) tensor, padded with the frame's first
    # strand (queried with them, never written back).
    slot = _slots(bs)
    width = int(slot.max()) + 1
    strands = x[:, :1].expand(batch, width, n, 3).clone()
    strands[bs, slot] = x[bs, ms]
    rest = rigid[:, :1].expand(batch, width, n, 3).clone()
    rest[bs, slot] = rigid[bs, ms]
    axes = _axes(x)
    weights = torch.tensor([0.25, 0.5, 1.0, 2.0, 4.0], dtype=x.dtype, device=x.device)
    index = torch.arange(n, device=x.device)
    inside_before = inside[bs, ms].sum(-1)
    for k in range(rounds + 1):
        distance = signed_distance(strands)[bs, slot]  # (S, N)
        stuck = distance < 0
        stuck[:, :NUM_FIXED_VERTICES] = False
        if k == rounds or not bool(stuck.any()):
            break
        first = torch.where(stuck, index, torch.full_like(index, n)).min(-1).values
        rows = torch.nonzero(first < n)[:, 0]
        i = first[rows]
        b, s = bs[rows], slot[rows]
        before, at = strands[b, s, i - 1], strands[b, s, i]
        length = (rest[b, s, i] - rest[b, s, i - 1]).norm(dim=-1, keepdim=True)
        own = (at - before) / (at - before).norm(dim=-1, keepdim=True).clamp_min(1e-12)
        blends = (own[:, None, None] + weights[None, :, None, None] * axes[None, None]).reshape(len(i), -1, 3)
        turns = torch.cat([blends, axes[None].expand(len(i), -1, -1)], 1)
        turns = turns / turns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        candidates = before[:, None] + length[:, None] * turns  # (R, K, 3)
        # Every candidate queried in one call: (B, R', K, 3), padded with the frame's root.
        cslot = _slots(b)
        grid = x[:, :1, :1].expand(batch, int(cslot.max()) + 1, candidates.shape[1], 3).clone()
        grid[b, cslot] = candidates
        clearance = signed_distance(grid)[b, cslot]
        score = torch.where(clearance >= 0.5 * margin, (turns * own[:, None]).sum(-1), clearance - 10.0)
        strands[b, s, i] = candidates[torch.arange(len(i), device=x.device), score.argmax(-1)]
        strands = follow_the_leader(rest, strands, check=False)
    # A turn can take later vertices of its strand into another part of the body: a strand left
    # with as many vertices inside as it had keeps its old place (whiplash at full size, the
    # swept inertial step: the turns raised the worst frame's share inside from 1.06 % to 1.13 %).
    better = stuck.sum(-1) < inside_before
    x = x.clone()
    x[bs[better], ms[better]] = strands[bs[better], slot[better]]
    return x


def keep_out_of_body_in_frames(x: torch.Tensor, frames, **settings) -> torch.Tensor:
    """`keep_out_of_body` of (T, M, N, 3) positions [m] of `frames`, a chunk of frames (and
    their bodies) at a time; `settings` are its keyword arguments.
    """
    rigid = frames.rigid.positions
    start = 0
    for chunk in frames.chunks():
        stop = start + chunk.num_frames
        x[start:stop] = keep_out_of_body(x[start:stop], rigid[start:stop], chunk.body_mesh, **settings)
        start = stop
    return x


__all__ = ["KEEP_OUT_FINAL_DEPTH", "KEEP_OUT_MARGIN", "KEEP_OUT_PASSES", "KEEP_OUT_TRIGGER", "KEEP_OUT_TURNS",
           "keep_out_of_body", "keep_out_of_body_in_frames", "pushed_out_of_body"]
