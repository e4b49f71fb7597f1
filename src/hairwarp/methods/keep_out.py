"""The body pass: hair pushed out of the body with its rest lengths kept.

The inertial step shows every frame through it, and the network methods by default
(`MethodOptions.keep_out`): a network's drape may leave vertices inside the body, which no
rigid placement with none inside should ever get back.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import torch

from hairwarp.runtime import CapturedCall

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
# The turns stop after this many rounds in a row that take no strand's first vertex inside
# further along it than so far (`_TurnProgress`). On a body of 49 overlapping primitives every frame ran all 12
# rounds and the state's pass took 272 ms a frame there (docs/contact.md, twenty-fifth session).
KEEP_OUT_TURN_PATIENCE = 2
# Distances are queried exactly up to this [m], or twice the margin where that is more; farther
# vertices are left alone (`_query_cap`).
_KEEP_OUT_QUERY = 2.0e-3


def _query_cap(margin: float) -> float:
    """The pass's query cap [m]: every decision reads a distance below the margin (the push
    below `trigger` x margin, the turns' clearance of half the margin) or a sign (exact inside at
    any depth), so a cap above the margin changes no position. A tighter cap prunes the tree
    walk of hair lying on the body: the same positions bit for bit at 1 cm, 3 mm and 1 mm on the
    three scenes of benchmarks/bm_keep_out.py at full size, 187 / 92 / 162 ms a drape at 1 cm
    against 150 / 61 / 144 at 3 mm on the 2-core CPU (twenty-second session).
    """
    return max(_KEEP_OUT_QUERY, 2.0 * float(margin))


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
    two segments by as much); deeper ones stay. At batch 1 on CUDA, from the third call on the
    same body, shape and settings, the same work replays from CUDA graphs (`_ReplayedPass`: the
    same positions bit for bit, 3-5x less time a drape on an H100).

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
    _check_arguments(x, rigid, body, margin)
    settings = dict(margin=float(margin), passes=int(passes), trigger=float(trigger), turns=int(turns),
                    final_depth=float(final_depth))
    replayed = _replayed_pass(x, rigid, body, settings)
    if replayed is not None:
        return replayed(x, rigid)
    x, rounds = pushed_out_of_body(x, rigid, body, margin=margin, passes=passes, trigger=trigger, check=False)
    if rounds < passes:
        return x
    # The rounds ran out. Where two body parts meet (the arm against the torso) the push takes a
    # vertex out of one into the other: those strands are turned out of the pinch instead.
    x = _turn_out_of_pinches(x, rigid, body, margin=margin, rounds=turns)
    return _pushed_out_of_creases(x, body, margin=margin, final_depth=final_depth)


def _pushed_out_of_creases(x: torch.Tensor, body, *, margin: float, final_depth: float) -> torch.Tensor:
    """The pass's last push, after the turns: vertices inside less than `final_depth` margins deep
    pushed to `margin` outside without the projection.

    A segment across a crease of the body can still take its end back inside at every
    projection (one vertex in 10^5 of long straight hair on the shoulders, 0.3 mm deep).
    Those shallow vertices alone are pushed out without the projection, each by the margin plus
    its depth (its two segments stretch by as much). Deeper ones stay: pushed without the
    projection they stretched whole strands (whiplash at full size: a frame's segments 1.5 %
    longer on average, eighteenth session).
    """
    from hairwarp.ops import hair_body_keep_out_push

    return hair_body_keep_out_push(x, body, margin=margin, push_below=0.0, push_above=-final_depth * margin,
                                   max_distance=_query_cap(margin), check=False)[0]


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
    if check:
        _check_arguments(x, rigid, body, margin)
    pushed_counts = _RoundCounts(passes, x.device)
    # After the first round only the strands the last round pushed are queried: the others are
    # as that round found them (the projection leaves a strand at its rest lengths where it
    # was, up to rounding), so none of their vertices is near. At full size most rounds after
    # the first push a few strands of 1 024: the rest of each round's queries were wasted.
    flags = torch.zeros((2, *x.shape[:-2]), dtype=torch.int32, device=x.device)
    for k in range(passes):
        projected = _push_round(x, rigid, body, k, flags, pushed_counts.slot(k), margin=margin, trigger=trigger)
        # The count is read after the projection is queued (`_RoundCounts`: why every round).
        pushed_counts.send(k)
        if pushed_counts.read(k) == 0:
            return x, k
        x = projected
    return x, passes


def _push_round(x: torch.Tensor, rigid: torch.Tensor, body, k: int, flags: torch.Tensor, count: torch.Tensor, *,
                margin: float, trigger: float) -> torch.Tensor:
    """Round k of `pushed_out_of_body`: the push (`hair_body_keep_out_push`, round 0 every strand,
    later rounds the strands `flags[(k - 1) % 2]` flags; those it pushes flagged in
    `flags[k % 2]`, their vertices counted into `count`), then the projection. No host read.
    """
    from hairwarp.ops import follow_the_leader, hair_body_keep_out_push

    active, flagged = (None if k == 0 else flags[(k - 1) % 2]), flags[k % 2]
    flagged.zero_()
    pushed, _ = hair_body_keep_out_push(x, body, margin=margin, push_below=trigger * margin,
                                        max_distance=_query_cap(margin), pushed_count=count,
                                        active_strands=active, pushed_strands=flagged, check=False)
    return follow_the_leader(rigid, pushed, check=False)


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
    only for rounds replayed from a CUDA graph). Built and measured in the twenty-first session,
    then removed: full size, one H100, alternated with this, 2.95 against 2.20 ms a drape (bob),
    4.20 against 4.02 (long curly), 7.40 against 7.51 (long straight); on the 2-core CPU 3-23 %
    slower. The GPU's rounds were bound by the host's launches, not by these reads: a pass
    called again and again at batch 1 on CUDA now replays every round from a graph with one
    read after them (`_ReplayedPass`, twenty-second session); this class serves the eager pass.
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


# The weights of a turn's own direction blended with each axis (`_pinch_turn_round`).
_TURN_WEIGHTS = (0.25, 0.5, 1.0, 2.0, 4.0)


def _capped_signed_distance(points: torch.Tensor, body, margin: float) -> torch.Tensor:
    """(B, S, K) signed distances [m] of (B, S, K, 3) polylines, capped at `_query_cap(margin)`.

    Only signs and clearances below half the margin are read: the capped query (exact inside at
    any depth) skips the unbounded walk of every far vertex, which was the pass's largest kernel
    where the rounds ran out (307-630 us of a drape on an H100, twenty-first session).
    """
    from hairwarp.ops import hair_body_signed_distance_and_normal

    return hair_body_signed_distance_and_normal(points, body, _query_cap(margin))[0]


def _vertices_inside(x: torch.Tensor, body, margin: float) -> torch.Tensor:
    """(B, M) int64: each strand's moving vertices inside the body."""
    from hairwarp.config import NUM_FIXED_VERTICES

    return (_capped_signed_distance(x, body, margin)[..., NUM_FIXED_VERTICES:] < 0).sum(-1)


def _stuck_slots(inside: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The strands with a vertex inside, `width` slots per frame, in strand order.

    Args:
        inside: (B, M) vertices inside per strand.
        width: slots per frame (<= M); a frame with fewer stuck strands fills the rest with
            strands that are not (never written back).

    Returns:
        ((B, width) long strand indices, (B, width) bool: the slot holds a stuck strand).
    """
    stuck = inside > 0
    # A stable sort of "not stuck" puts the stuck strands first, in strand order, with no host
    # read: the same work whether replayed from a graph or not.
    order = torch.argsort((~stuck).to(torch.uint8), dim=-1, stable=True)[:, :width]
    return order, stuck.gather(1, order)


def _strand_rows(x: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """(B, S, N, 3): the strands `order` (B, S) of (B, M, N, 3) `x`."""
    return x.gather(1, order[..., None, None].expand(-1, -1, x.shape[2], 3))


def _at_vertex(strands: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B, S, 3): vertex index[b, s] of each strand of (B, S, N, 3) `strands`."""
    return strands.gather(2, index[..., None, None].expand(-1, -1, 1, 3))[..., 0, :]


class _TurnProgress:
    """Whether the pinch turns go on, kept on the device (no host read, so a CUDA graph replays it).

    A round frees a strand's first vertex inside, so the turns progress along the strands: the
    measure is the sum over the turn slots of the index of their strand's first vertex inside
    (the strand's length where none is) at a round's start. Kept: the largest so far, and how many
    rounds in a row found none larger. A round goes on while the one before turned some strand
    and fewer than `KEEP_OUT_TURN_PATIENCE` rounds in a row made no progress (a strand held
    where no turn clears it turns in place round after round); a round that does not go on
    changes nothing, so a replay of several rounds stops where the eager rounds do. The count
    of vertices inside is no such measure: freeing a strand's first vertex can take later ones
    in, and two spheres' lens needs rounds that do.
    """

    def __init__(self, device: torch.device):
        self.go_on = torch.ones((), dtype=torch.bool, device=device)
        self.furthest = torch.zeros((), dtype=torch.long, device=device)
        self.stale = torch.zeros((), dtype=torch.long, device=device)
        self.reset()

    def reset(self) -> None:
        """The turns' start (in place: a captured graph keeps reading these tensors)."""
        self.go_on.fill_(True)
        self.furthest.fill_(-1)
        self.stale.zero_()

    def update(self, turned: torch.Tensor, reach: torch.Tensor) -> None:
        """After a round that turned `turned` strands, `reach` the measure at its start."""
        further = reach > self.furthest
        self.furthest.copy_(torch.maximum(self.furthest, reach))
        self.stale.copy_(torch.where(further, torch.zeros_like(self.stale), self.stale + 1))
        self.go_on.copy_(self.go_on & (turned > 0) & (self.stale < KEEP_OUT_TURN_PATIENCE))


def _pinch_turn_round(strands: torch.Tensor, rest: torch.Tensor, valid: torch.Tensor, body, *, margin: float,
                      axes: torch.Tensor, weights: torch.Tensor, progress: _TurnProgress) -> None:
    """One round of `_turn_out_of_pinches` on (B, S, N, 3) `strands` in place: in each valid slot
    the first moving vertex inside the body is turned about its predecessor, its segment's
    length (from `rest`) kept, to the direction nearest its own that clears the body by half the
    margin (its own blended with the 26 `axes` at the `weights`, and the axes alone; if none
    clears, the one that goes least deep), then every slot is projected onto its rest lengths
    (follow-the-leader) if any turned. Nothing changes where `progress` says the turns stopped;
    the round updates it. Fixed shapes and no host read: a CUDA graph replays it.
    """
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.ops import follow_the_leader

    batch, width, n = strands.shape[:3]
    stuck = (_capped_signed_distance(strands, body, margin) < 0) & valid[..., None]
    stuck[..., :NUM_FIXED_VERTICES] = False
    index = torch.arange(n, device=strands.device)
    first = torch.where(stuck, index, torch.full_like(index, n)).min(-1).values  # (B, S)
    turned = (first < n) & progress.go_on
    i = first.clamp(NUM_FIXED_VERTICES, n - 1)
    before, at = _at_vertex(strands, i - 1), _at_vertex(strands, i)
    length = (_at_vertex(rest, i) - _at_vertex(rest, i - 1)).norm(dim=-1, keepdim=True)
    own = (at - before) / (at - before).norm(dim=-1, keepdim=True).clamp_min(1e-12)
    blends = (own[..., None, None, :] + weights[:, None, None] * axes[None]).reshape(batch, width, -1, 3)
    turns = torch.cat([blends, axes.expand(batch, width, -1, 3)], 2)
    turns = turns / turns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    candidates = before[..., None, :] + length[..., None, :] * turns  # (B, S, K, 3)
    clearance = _capped_signed_distance(candidates, body, margin)  # every candidate in one query
    score = torch.where(clearance >= 0.5 * margin, (turns * own[..., None, :]).sum(-1), clearance - 10.0)
    best = candidates.gather(2, score.argmax(-1)[..., None, None].expand(-1, -1, 1, 3))
    moved = strands.scatter(2, i[..., None, None].expand(-1, -1, 1, 3), best)
    moved = torch.where(turned[..., None, None], moved, strands)
    count = turned.sum()
    strands.copy_(torch.where(count > 0, follow_the_leader(rest, moved, check=False), strands))
    progress.update(count, first.sum())


def _keep_better(x: torch.Tensor, strands: torch.Tensor, order: torch.Tensor, valid: torch.Tensor,
                 inside_before: torch.Tensor, body, margin: float) -> torch.Tensor:
    """(B, M, N, 3) `x` with the turned `strands` (B, S, N, 3) written back to their places
    `order` where a valid slot ends with fewer vertices inside than `inside_before` (B, S) had.

    A turn can take later vertices of its strand into another part of the body: a strand left
    with as many vertices inside as it had keeps its old place (whiplash at full size, the swept
    inertial step: the turns raised the worst frame's share inside from 1.06 % to 1.13 %).
    """
    better = valid & (_vertices_inside(strands, body, margin) < inside_before)
    places = order[..., None, None].expand(-1, -1, x.shape[2], 3)
    return x.scatter(1, places, torch.where(better[..., None, None], strands, x.gather(1, places)))


def _turn_out_of_pinches(x: torch.Tensor, rigid: torch.Tensor, body, *, margin: float, rounds: int) -> torch.Tensor:
    """(B, M, N, 3) positions [m] with each strand's first vertex inside the body turned about its
    predecessor, its segment's length kept, to the direction nearest its own that clears the body
    by half the margin (its own blended with the 26 axis and diagonal directions at five weights,
    and those 26 alone), the rest of the strand following (follow-the-leader); up to `rounds`
    times (`_pinch_turn_round`), stopping at a round that finds none or after
    `KEEP_OUT_TURN_PATIENCE` rounds in a row that free no strand further (`_TurnProgress`). Only the
    strands with a vertex inside are queried: a few in a groom.

    Where two body parts meet, the signed distance's gradient leads out of one part into the
    other, so pushing along it leaves a vertex inside; turning the segment finds the way out.
    The demo's scene on the 2-core CPU, the inertial step's 61 frames: 0.032 % of the vertices
    inside after the pushes, 0.0004 % with 12 rounds of this (`tools/keep_out_settings.py --scene
    demo`). `_ReplayedPass` replays the same rounds from CUDA graphs.
    """
    if rounds <= 0:
        return x
    inside = _vertices_inside(x, body, margin)
    width = int((inside > 0).sum(-1).max())
    if width == 0:
        return x
    order, valid = _stuck_slots(inside, width)
    strands, rest = _strand_rows(x, order), _strand_rows(rigid, order)
    axes = _axes(x)
    weights = torch.tensor(_TURN_WEIGHTS, dtype=x.dtype, device=x.device)
    progress = _TurnProgress(x.device)
    for _ in range(rounds):
        _pinch_turn_round(strands, rest, valid, body, margin=margin, axes=axes, weights=weights, progress=progress)
        if not bool(progress.go_on):
            break
    return _keep_better(x, strands, order, valid, inside.gather(1, order), body, margin)


# Whether a pass at batch 1 on CUDA replays its launches from CUDA graphs (`_ReplayedPass`) after
# `KEEP_OUT_EAGER_CALLS` eager calls on the same body, shape and settings; False: every call is eager.
KEEP_OUT_GRAPHS = True
KEEP_OUT_EAGER_CALLS = 2
# Turn slots a replayed pass starts with; a frame with more stuck strands captures more.
_REPLAYED_TURN_SLOTS = 16
# Pinch-turn rounds per replay of a replayed pass, a host read after each. More rounds a replay
# save reads but waste the device's work where the rounds stop early: one H100, 1 024 x 100,
# long straight hair grown on the body, 1 / 3 / 12 rounds a replay 2.13 / 2.41 / 5.20 ms a pass
# (`python3 benchmarks/bm_keep_out.py --device cuda --turn-rounds-per-replay 1,3,12`, twenty-second
# session).
_TURN_ROUNDS_PER_REPLAY = 1


def _replayed_pass(x: torch.Tensor, rigid: torch.Tensor, body, settings: dict) -> _ReplayedPass | None:
    """The body's `_ReplayedPass` for `x`'s shape and these settings, or None where the pass
    runs eagerly: off CUDA, a batch of frames, `KEEP_OUT_GRAPHS` off, inside another capture, or
    the first `KEEP_OUT_EAGER_CALLS` calls with this key. A body passed once, or twice by a method that
    times its second call after a warm-up (`hairwarp.runtime.timed`), is not worth a capture
    (its warm-ups and the capture cost more than the launches they save); a body passed again
    and again (a drape per frame of a live pose, a benchmark) is.
    """
    if not (KEEP_OUT_GRAPHS and x.is_cuda and x.shape[0] == 1) or torch.cuda.is_current_stream_capturing():
        return None
    key = (tuple(x.shape), x.dtype, x.device, tuple(sorted(settings.items())))
    # Kept on the body: the graphs read its buffers (`BodyMesh.update` moves it in place, and
    # they follow) and go with it. One key at a time: the eager calls so far, then the pass.
    held = body.__dict__.setdefault("_replayed_keep_out", {})
    if key not in held:
        held.clear()
        held[key] = 0
    if isinstance(held[key], int):
        held[key] += 1
        if held[key] <= KEEP_OUT_EAGER_CALLS:
            return None
        held[key] = _ReplayedPass(x, rigid, body, settings)
    return held[key]


class _ReplayedPass:
    """`keep_out_of_body` at batch 1 on CUDA from CUDA graphs over fixed buffers.

    The pass is bound by the host's launches on a GPU (docs/gpu.md, twenty-first session: the
    device busy 0.6-1.9 ms of a 2.4-12 ms drape at 1 024 x 100). Here the rounds are one graph:
    every round is launched, and a round after one that pushed nothing queries no strand (each
    round queries only the strands the round before pushed) and keeps its input, so the result
    is the eager pass's; one count is read after it. Where the rounds ran out, the pinch turns
    replay a selection graph (how many strands are stuck: one read), one graph per turn round
    (a read of how many it turned, as the eager rounds stop) and the write-back; then the
    crease push. The same positions bit for bit as the eager pass
    (`test_replayed_keep_out_equals_the_eager_pass`).

    Args:
        x, rigid: (1, M, N, 3) the inputs of the call that captures (the warm-ups before each
            capture run on them).
        body: the `BodyMesh` the graphs query (held weakly: it holds this pass).
        settings: `keep_out_of_body`'s keyword arguments.
    """

    def __init__(self, x: torch.Tensor, rigid: torch.Tensor, body, settings: dict):
        import weakref

        self.settings = settings
        self.body = weakref.ref(body)
        self.x = x.detach().clone()
        self.rigid = rigid.detach().clone()
        self.positions = self.x.clone()
        self.out = self.x.clone()
        passes = settings["passes"]
        self.counts = torch.zeros(max(passes, 1), dtype=torch.int32, device=x.device)
        self.flags = torch.zeros((2, 1, x.shape[1]), dtype=torch.int32, device=x.device)
        self.axes = _axes(x)
        self.weights = torch.tensor(_TURN_WEIGHTS, dtype=x.dtype, device=x.device)
        self.width = min(_REPLAYED_TURN_SLOTS, x.shape[1])
        self.turn_rounds_per_replay = _TURN_ROUNDS_PER_REPLAY
        self.turn_graphs: dict[int, dict] = {}
        self.rounds = self._captured(self._rounds)
        self.crease = self._captured(self._crease)

    def __call__(self, x: torch.Tensor, rigid: torch.Tensor) -> torch.Tensor:
        s = self.settings
        self.x.copy_(x)
        self.rigid.copy_(rigid)
        self.rounds()
        if s["passes"] > 0 and int(self.counts[s["passes"] - 1]) == 0:
            return self.positions.clone()
        if s["turns"] > 0:
            turns = self._turn_graphs(self.width)
            turns["select"]()
            stuck = int(turns["stuck"])
            if stuck > self.width:
                self.width = min(1 << (stuck - 1).bit_length(), x.shape[1])
                turns = self._turn_graphs(self.width)
                turns["select"]()
            if stuck > 0:
                # Groups of rounds, a read after each: a round after the turns stopped changes
                # nothing (`_TurnProgress`), so the eager rounds' stop is kept.
                for group in self._turn_groups():
                    turns[group]()
                    if not bool(turns["progress"].go_on):
                        break
                turns["keep"]()
        self.crease()
        return self.out.clone()

    def _turn_groups(self) -> list[tuple[str, int]]:
        """The turn rounds as replays: keys ("rounds", count) of `turn_rounds_per_replay` rounds
        each (`_TURN_ROUNDS_PER_REPLAY`; set before the first call that turns), the remainder last.
        """
        turns, per = self.settings["turns"], max(1, min(self.turn_rounds_per_replay, self.settings["turns"]))
        return [("rounds", per)] * (turns // per) + ([("rounds", turns % per)] if turns % per else [])

    def _captured(self, fn) -> CapturedCall | Callable[[], None]:
        if self.x.device.type != "cuda":
            return fn  # the same fixed work, called (the tests check it on the CPU)
        with torch.cuda.device(self.x.device), torch.no_grad():
            return CapturedCall(fn, warmup=1)

    def _rounds(self) -> None:
        s = self.settings
        self.counts.zero_()
        x = self.x
        for k in range(s["passes"]):
            projected = _push_round(x, self.rigid, self.body(), k, self.flags, self.counts[k:k + 1],
                                    margin=s["margin"], trigger=s["trigger"])
            x = torch.where(self.counts[k] > 0, projected, x)
        self.positions.copy_(x)

    def _crease(self) -> None:
        self.out.copy_(_pushed_out_of_creases(self.positions, self.body(), margin=self.settings["margin"],
                                              final_depth=self.settings["final_depth"]))

    def _turn_graphs(self, width: int) -> dict:
        """The turn graphs with `width` slots (captured at first use; the capture's warm-ups
        leave the positions as they were).
        """
        if width in self.turn_graphs:
            return self.turn_graphs[width]
        shape = (1, width)
        n = self.x.shape[2]
        device, dtype = self.x.device, self.x.dtype
        g = {"order": torch.zeros(shape, dtype=torch.long, device=device),
             "valid": torch.zeros(shape, dtype=torch.bool, device=device),
             "inside": torch.zeros(shape, dtype=torch.long, device=device),
             "strands": torch.zeros((*shape, n, 3), dtype=dtype, device=device),
             "rest": torch.zeros((*shape, n, 3), dtype=dtype, device=device),
             "stuck": torch.zeros((), dtype=torch.long, device=device),
             "progress": _TurnProgress(device)}
        body, margin = self.body(), self.settings["margin"]

        def select():
            inside = _vertices_inside(self.positions, body, margin)
            order, valid = _stuck_slots(inside, width)
            g["order"].copy_(order)
            g["valid"].copy_(valid)
            g["inside"].copy_(inside.gather(1, order))
            g["strands"].copy_(_strand_rows(self.positions, order))
            g["rest"].copy_(_strand_rows(self.rigid, order))
            g["stuck"].copy_((inside > 0).sum())
            g["progress"].reset()

        def turn_rounds(count):
            def run():
                for _ in range(count):
                    _pinch_turn_round(g["strands"], g["rest"], g["valid"], body, margin=margin, axes=self.axes,
                                      weights=self.weights, progress=g["progress"])
            return run

        def keep():
            self.positions.copy_(_keep_better(self.positions, g["strands"], g["order"], g["valid"], g["inside"],
                                              body, margin))

        saved = self.positions.clone()
        for name, fn in (("select", select), ("keep", keep),
                         *((group, turn_rounds(group[1])) for group in set(self._turn_groups()))):
            g[name] = self._captured(fn)
        self.positions.copy_(saved)
        self.turn_graphs[width] = g
        return g


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


__all__ = ["KEEP_OUT_FINAL_DEPTH", "KEEP_OUT_MARGIN", "KEEP_OUT_PASSES", "KEEP_OUT_TRIGGER", "KEEP_OUT_TURN_PATIENCE",
           "KEEP_OUT_TURNS",
           "keep_out_of_body", "keep_out_of_body_in_frames", "pushed_out_of_body"]
