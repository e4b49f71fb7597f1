"""The body pass: hair pushed out of the body with its rest lengths kept.

The inertial step shows every frame through it, and the network methods on request
(`MethodOptions.keep_out`): a network's drape may leave vertices inside the body, which no
rigid placement with none inside should ever get back.
"""

from __future__ import annotations

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
# Distances queried exactly up to this [m]; farther vertices are left alone.
_KEEP_OUT_QUERY = 1.0e-2


def keep_out_of_body(x: torch.Tensor, rigid: torch.Tensor, body, *, margin: float = KEEP_OUT_MARGIN,
                     passes: int = KEEP_OUT_PASSES, trigger: float = KEEP_OUT_TRIGGER,
                     final_depth: float = KEEP_OUT_FINAL_DEPTH) -> torch.Tensor:
    """Hair pushed out of the body with its rest lengths kept (up to a crease: see below).

    Each round pushes every moving vertex (index >= 2) that lies inside the body or nearer its
    surface than `trigger` x `margin` along the signed distance's gradient to `margin`, then
    projects the strands back onto the rigid placement's segment lengths (follow-the-leader),
    which can move later vertices in again: hence a few rounds. Should every round find some, the
    vertices still inside after the last and less than `final_depth` x `margin` deep are pushed
    out without the projection (each by `margin` plus its depth, which stretches its two segments
    by as much); deeper ones stay.

    Args:
        x: (B, M, N, 3) hair positions [m].
        rigid: (B, M, N, 3) the rigid placement of the same frames (its rest lengths) [m].
        body: the frames' `BodyMesh` (batch 1 or B).
        margin: [m] >= 0.
        passes: at most this many rounds (>= 1); the pass stops at a round that moves nothing.
        trigger: the share of `margin` below which a round pushes a vertex, in (0, 1].
        final_depth: vertices left inside less than this many margins deep are pushed out
            without the projection (0: none; inf: every one).

    Returns:
        (B, M, N, 3) positions [m] (no autograd).
    """
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.ops import follow_the_leader, hair_body_signed_distance_and_normal

    for _ in range(passes):
        distance, direction = hair_body_signed_distance_and_normal(x, body, max_distance=_KEEP_OUT_QUERY)
        near = distance < trigger * margin
        near[..., :NUM_FIXED_VERTICES] = False
        if not bool(near.any()):
            return x
        push = torch.where(near, margin - distance, torch.zeros_like(distance))
        x = follow_the_leader(rigid, x + push[..., None] * direction, check=False)
    # The rounds ran out: a segment across a crease of the body can take its end back inside at
    # every projection (one vertex in 10^5 of long straight hair on the shoulders, 0.3 mm deep).
    # Those shallow vertices alone are pushed out without the projection, each by the margin plus
    # its depth (its two segments stretch by as much). Deeper ones stay: pushed without the
    # projection they stretched whole strands (whiplash at full size: a frame's segments 1.5 %
    # longer on average, eighteenth session).
    distance, direction = hair_body_signed_distance_and_normal(x, body, max_distance=_KEEP_OUT_QUERY)
    shallow = (distance < 0.0) & (distance > -final_depth * margin)
    shallow[..., :NUM_FIXED_VERTICES] = False
    push = torch.where(shallow, margin - distance, torch.zeros_like(distance))
    return x + push[..., None] * direction


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


__all__ = ["KEEP_OUT_FINAL_DEPTH", "KEEP_OUT_MARGIN", "KEEP_OUT_PASSES", "KEEP_OUT_TRIGGER", "keep_out_of_body",
           "keep_out_of_body_in_frames"]
