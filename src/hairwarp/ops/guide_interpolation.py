"""Torch bridge of the guide-to-follower interpolation; device code in
`hairwarp.kernels.guide_interpolation` (the formulas are there).

    rotations = guide_frame_rotations(guides_rest, guides_now, head_rotation)      # (B, K, N-1, 4)
    x = interpolate_followers(guides_rest, guides_now, rotations, followers_rest,
                              follower_guides, follower_weights, follower_ratios)  # (B, M, N, 3)
    lower = follower_distance_bound(guides_now, guide_signed_distance, x, ...)    # (B, M, N)

Every computation is float32 (a float64 input is computed in float32 and returned in float64)
and carries no gradient: the followers are a post-process of a method's guides.
"""

from __future__ import annotations

import torch
import warp as wp

from hairwarp import _warp
from hairwarp._validate import check_tensor
from hairwarp.kernels import guide_interpolation as kernels

INDEX_DTYPES = (torch.int32, torch.int64)
# A CPU launch of at least twice this many threads is split between two cores (`_run_shared`).
CPU_SPLIT_THREADS = 4096
# Kernels whose shared launch (`_run_shared`) has run once: loaded, and recorded on both threads.
_SHARED_READY: set = set()
# The body pass's query reach in rest lengths: an empty ball clears that many vertices after it
# without a query of their own (the signed distance is 1-Lipschitz). On a 100 000-strand groom
# draped on the default body, reach 1 / 4 made 2.00 / 1.66 million queries against 2.45 million
# without the carried bound; yet reach 4 was no faster on the 2-core CPU (1 628 ms against
# 1 627, median of 5) and slower on one H100 (10 000 strands 6.59 ms against 5.6: a warp waits
# for its longest walk).
QUERY_REACH_SEGMENTS = 1.0
# CUDA threads per block of the walk (`follow_guides_kernel`, a thread per strand): 10 000 strands
# are 40 blocks of Warp's default 256, on 40 of an H100's 132 multiprocessors. One H100,
# `bm_guides.py --walk-block-dims 32,64,128,256` (interpolation + body pass, median of three
# alternated rounds): 10 000 strands 4.93 / 4.90 / 4.91 / 5.18 ms, 100 000 strands 9.32 / 9.44 /
# 9.65 / 9.78 ms.
WALK_THREADS_PER_BLOCK = 32
# The walk caps each query at the distance to the strand's last closest face (`face_hint` of
# `follow_guides_kernel`): the same faces, a smaller ball for the tree's descent. One H100,
# interpolation + body pass from the graph: 10 000 strands 4.51 -> 4.10 ms, 100 000 strands
# 9.17 -> 8.64 ms (docs/guides.md, tenth session).
WALK_FACE_HINT = True
# The rounds cap a vertex's query at the distance to the face its last round's query found
# (`face_hint` of `follower_body_query_kernel`): the same faces, a ball of about a push's size.
# One H100, interpolation + body pass, median of three alternated rounds: 10 000 strands 2.36 ->
# 2.29 ms alone, 1.99 -> 2.01 ms beside ROUNDS_SKIP_SETTLED; 100 000 10.62 -> 10.68, 8.17 -> 8.07
# (`guides_rounds_hint_skip_session12_h100.json`): within the runs' spread. Kept: the same
# positions, for one point-triangle distance per vertex queried again.
ROUNDS_FACE_HINT = True
# The rounds walk again only the strands whose round found a vertex within the margin, and query
# only theirs (`every_strand` of `follower_walk_tiled_kernel`): the others' walk would return
# their positions up to rounding. Same run: 10 000 strands 2.36 -> 1.99 ms, 30 000 4.05 -> 3.30,
# 100 000 10.62 -> 8.17 (about one strand in six touches the body).
ROUNDS_SKIP_SETTLED = True
# How `follow_guides` orders its work (its docstring).
SCHEDULES = ("walk", "rounds")


def _quats(t: torch.Tensor):
    return _warp.as_warp(t, quat=True)


def _run(kernel, dim: int, device: torch.device, inputs, outputs, threads_per_block: int | None = None) -> None:
    if dim == 0:
        return
    with _warp.launch_scope(device):
        _warp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=_warp.warp_device(device),
                     threads_per_block=threads_per_block)


def _run_shared(kernel, dim: int, device: torch.device, inputs, outputs, threads_per_block: int | None = None) -> None:
    """`_run` of a kernel whose last input is its first thread's index: on the CPU the threads
    are split in two launches, one on the side thread (`hairwarp.runtime`; Warp's CPU kernels
    release Python's lock), so both cores work; one launch elsewhere.
    """
    from hairwarp.runtime import cpu_side_executor

    half = dim // 2
    if device.type != "cpu" or half < CPU_SPLIT_THREADS or torch.get_num_interop_threads() < 2:
        _run(kernel, dim, device, [*inputs, 0], outputs, threads_per_block)
        return
    pending = cpu_side_executor().submit(_run, kernel, dim - half, device, [*inputs, half], outputs)
    if kernel not in _SHARED_READY:
        # Warp checks and records a kernel's launch on a thread's first use of it; a hair-body
        # pass split this way (tried on 2026-11-26) failed there, in Warp's launch checks, then
        # crashed. This pass never did (5 fresh processes), but its first shared launch runs its
        # halves in turn all the same: one call's cost, against a crash.
        pending.result()
    _run(kernel, half, device, [*inputs, 0], outputs)
    pending.result()
    _SHARED_READY.add(kernel)


def rotation_quaternions(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (x, y, z, w), float32.

    Shepperd's method: each matrix's quaternion is read from whichever of w, x, y, z is largest
    (that component's square root is far from zero), so half turns come out exact.
    """
    r = rotation.double()
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = torch.stack([
        torch.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1], 1 + trace], -1),
        torch.stack([1 + m00 - m11 - m22, r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0],
                     r[..., 2, 1] - r[..., 1, 2]], -1),
        torch.stack([r[..., 0, 1] + r[..., 1, 0], 1 - m00 + m11 - m22, r[..., 1, 2] + r[..., 2, 1],
                     r[..., 0, 2] - r[..., 2, 0]], -1),
        torch.stack([r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1], 1 - m00 - m11 + m22,
                     r[..., 1, 0] - r[..., 0, 1]], -1),
    ], -2)  # (..., 4 branches, 4): each branch's quaternion times 4 * its leading component
    best = torch.stack([trace, m00, m11, m22], -1).argmax(-1)
    q = candidates.gather(-2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return (q / q.norm(dim=-1, keepdim=True)).to(torch.float32)


def _check_guides(guides_rest: torch.Tensor, guides_now: torch.Tensor) -> tuple[int, int, int]:
    check_tensor("guides_rest", guides_rest, shape=(None, None, 3), allow_empty=False)
    check_tensor("guides_now", guides_now, shape=(None,) + tuple(guides_rest.shape), device=guides_rest.device)
    if guides_rest.shape[1] < 3:
        raise ValueError(f"guides_rest: expected at least 3 vertices per strand, got {guides_rest.shape[1]}")
    return guides_now.shape[0], guides_rest.shape[0], guides_rest.shape[1]


# Segments on each side over which a guide's direction is read (`smoothed_direction`).
FRAME_WINDOW = 4


def guide_frame_rotations(guides_rest: torch.Tensor, guides_now: torch.Tensor,
                          head_rotation: torch.Tensor, window: int = FRAME_WINDOW, *, check: bool = True) -> torch.Tensor:
    """The rotation of each guide segment's parallel-transported frame from rest to now.

    Args:
        guides_rest: (K, N, 3) guide strands at rest [m].
        guides_now: (B, K, N, 3) the same guides in B frames [m] (a method's result).
        head_rotation: (B, 3, 3) the head's rotation in each frame (`PosedBody.head_transform`).
        window: segments on each side over which a segment's direction is read (0: its own).
        check: validate the arguments (False: a caller that built them itself; on a GPU each
            check of a tensor's values waits for the device).

    Returns:
        (B, K, N-1, 4) float32 unit quaternions (x, y, z, w), R_i = F_i F0_i^T per segment.
    """
    if check:
        _check_guides(guides_rest, guides_now)
        check_tensor("head_rotation", head_rotation, shape=(guides_now.shape[0], 3, 3), device=guides_rest.device)
        if isinstance(window, bool) or not isinstance(window, int) or window < 0:
            raise ValueError(f"window: expected an integer >= 0, got {window!r}")
    batch, k, n = guides_now.shape[0], guides_rest.shape[0], guides_rest.shape[1]
    device = guides_rest.device
    rest = guides_rest.detach().to(torch.float32).contiguous()
    now = guides_now.detach().to(torch.float32).contiguous()
    head = rotation_quaternions(head_rotation.detach()).to(device).contiguous()
    out = torch.empty(batch, k, n - 1, 4, dtype=torch.float32, device=device)
    rest_wp, now_wp, head_wp = _warp.as_warp(rest, vec3=True), _warp.as_warp(now, vec3=True), _quats(head)
    if device.type == "cuda" and (2 * 3 + 4) * 4 * n <= kernels.FRAMES_MAX_SHARED_BYTES:
        if batch * k:
            with _warp.launch_scope(device):
                _warp.launch(kernels.guide_frame_rotations_tiled_kernel(n, window), dim=batch * k,
                             inputs=[rest_wp, now_wp, head_wp, k], outputs=[_quats(out)],
                             device=_warp.warp_device(device), block_dim=kernels.FRAMES_BLOCK_DIM)
        return out
    _run(kernels.guide_frame_rotations_kernel, batch * k, device, [rest_wp, now_wp, head_wp, k, n, window],
         [_quats(out)])
    return out


def _check_followers(followers_rest, follower_guides, follower_weights, follower_ratios, num_guides: int,
                     num_vertices: int, device) -> int:
    check_tensor("followers_rest", followers_rest, shape=(None, num_vertices, 3), device=device)
    m = followers_rest.shape[0]
    check_tensor("follower_guides", follower_guides, shape=(m, None), dtypes=INDEX_DTYPES, device=device)
    k = follower_guides.shape[1]
    check_tensor("follower_weights", follower_weights, shape=(m, k), device=device)
    check_tensor("follower_ratios", follower_ratios, shape=(m, k), device=device)
    if m and (int(follower_guides.min()) < 0 or int(follower_guides.max()) >= num_guides):
        raise ValueError(f"follower_guides: expected guide indices in [0, {num_guides}), "
                         f"got [{int(follower_guides.min())}, {int(follower_guides.max())}]")
    return k


def _follower_arrays(follower_guides, follower_weights, follower_ratios) -> list:
    return [_warp.as_warp(follower_guides.to(torch.int32).contiguous()),
            _warp.as_warp(follower_weights.detach().to(torch.float32).contiguous()),
            _warp.as_warp(follower_ratios.detach().to(torch.float32).contiguous())]


def interpolate_followers(guides_rest: torch.Tensor, guides_now: torch.Tensor, rotations: torch.Tensor,
                          followers_rest: torch.Tensor, follower_guides: torch.Tensor,
                          follower_weights: torch.Tensor, follower_ratios: torch.Tensor, *,
                          check: bool = True) -> torch.Tensor:
    """Follower strands carried by their guides' frames (`hairwarp.kernels.guide_interpolation`),
    without the length projection or the body pass (`follow_guides` with neither).

    Args:
        guides_rest: (K, N, 3) guides at rest [m].
        guides_now: (B, K, N, 3) guides in B frames [m].
        rotations: (B, K, N-1, 4) `guide_frame_rotations` of those frames.
        followers_rest: (M, N, 3) follower strands at rest [m].
        follower_guides: (M, k) int guide indices of each follower.
        follower_weights: (M, k) blend weights (rows sum to 1; 0 skips a slot).
        follower_ratios: (M, k) follower rest length / guide rest length.
        check: as in `guide_frame_rotations`.

    Returns:
        (B, M, N, 3) follower positions [m], in the dtype of `guides_now`.
    """
    x, _ = follow_guides(guides_rest, guides_now, rotations, followers_rest, follower_guides, follower_weights,
                         follower_ratios, project=False, check=check)
    return x.to(guides_now.dtype)


def _no_body(device: torch.device) -> list:
    """Empty stand-ins for a body's kernel arrays (`BodyMesh._kernel_arrays`) and counts."""
    empty = torch.zeros(0, device=device)
    ids = wp.empty(0, dtype=wp.uint64, device=_warp.warp_device(device))
    return [ids, _warp.as_warp(torch.zeros(0, 3, device=device), vec3=True),
            _warp.as_warp(torch.zeros(0, dtype=torch.int32, device=device)),
            _warp.as_warp(torch.zeros(0, 3, device=device), vec3=True),
            _warp.as_warp(torch.zeros(0, 3, device=device), vec3=True), ids, 0,
            wp.empty(0, dtype=wp.vec4, device=_warp.warp_device(device)), 0, 0, 0], empty


def follow_guides(guides_rest: torch.Tensor, guides_now: torch.Tensor, rotations: torch.Tensor,
                  followers_rest: torch.Tensor, follower_guides: torch.Tensor, follower_weights: torch.Tensor,
                  follower_ratios: torch.Tensor, *, guide_slot: torch.Tensor | None = None,
                  project: bool = True, body=None, guide_signed_distance: torch.Tensor | None = None,
                  margin: float = 1.0e-3, passes: int = 3, reach_segments: float | None = None,
                  schedule: str = "walk", rest_lengths: torch.Tensor | None = None,
                  settle: float = 0.0, check: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Every strand of a groom from its guides: interpolated, projected onto its rest lengths,
    kept out of the body.

    The targets of all vertices come first (`follower_targets_kernel`, a thread per vertex); the
    body pass has two schedules (`hairwarp.kernels.guide_interpolation`):
    - "walk" (the default): a thread per strand (`follow_guides_kernel`) places, queries and
      pushes each vertex before the next. Fewest queries, fewest vertices left inside; on a GPU
      its time is its longest strand's chain of queries.
    - "rounds": `passes` rounds of [every vertex near the body queried at once; the walk again
      from the last positions, moving each vertex out of the tangent plane its query found, no
      query in it], the walk and the next round's queries only on the strands whose round found
      a vertex within the margin (`ROUNDS_SKIP_SETTLED`). On one H100 from the CUDA graph
      (`GuideSet.follow`), 10 000 strands: 1.9-2.3 ms against the walk's 4.1-4.4 ms, but 0.06 %
      of the followers' vertices left inside against 0.007 %; 100 000 strands: 8.0-8.4 ms
      against 8.5-8.9 ms, 0.083 % against 0.011 % (docs/guides.md, twelfth session).

    Args:
        guides_rest, guides_now, rotations, followers_rest, follower_guides, follower_weights,
            follower_ratios: as `interpolate_followers` (`followers_rest` is the whole groom).
        guide_slot: (M,) int, the guide index of each strand that is a guide (its row is copied
            from `guides_now`), -1 for the others; None: no strand is a guide.
        project: place each vertex at its rest length from its predecessor (follow-the-leader).
        body: the frames' `BodyMesh` (batch 1 or B) to keep the strands out of; None: no body pass
            (needs `project`).
        guide_signed_distance: (B, K, N) the guides' signed distances [m], with `body`.
        margin: vertices inside or nearer the surface than this [m] are pushed to it.
        passes: push-and-project rounds per vertex.
        reach_segments: each signed-distance query reaches this many rest lengths (plus the
            margin), >= 1; an empty ball clears as many vertices after it without a query. None:
            `QUERY_REACH_SEGMENTS`.
        schedule: "walk" or "rounds" (above).
        rest_lengths: (M, N-1) float32 the followers' rest segment lengths [m] if the caller keeps
            them (100 000 strands: 0.26 ms a call on a GPU to compute); None: computed.
        settle: "walk": a pushed vertex is not queried again where the length projection moved it
            less than this from where the push put it [m] (it is then at least margin - settle
            out); 0: always queried again (up to `passes`).
        check: as in `guide_frame_rotations`.

    Returns:
        ((B, M, N, 3) float32 positions [m], (B, M) int32 vertices the body pass moved per strand).
    """
    from hairwarp.ops.hair_body_contact import _ZERO_DISTANCE, _body_stride, _check_body

    batch, num_guides, n = guides_now.shape[0], guides_rest.shape[0], guides_rest.shape[1]
    device = guides_rest.device
    m, k = followers_rest.shape[0], follower_guides.shape[1]
    if check:
        _check_guides(guides_rest, guides_now)
        check_tensor("rotations", rotations, shape=(batch, num_guides, n - 1, 4), device=device)
        _check_followers(followers_rest, follower_guides, follower_weights, follower_ratios, num_guides, n, device)
        if guide_slot is not None:
            check_tensor("guide_slot", guide_slot, shape=(m,), dtypes=INDEX_DTYPES, device=device)
            if m and (int(guide_slot.min()) < -1 or int(guide_slot.max()) >= num_guides):
                raise ValueError(f"guide_slot: expected -1 or a guide index in [0, {num_guides})")
        if body is not None:
            if not project:
                raise ValueError("body: the body pass needs project=True (it keeps the rest lengths)")
            _check_body(body)
            check_tensor("guide_signed_distance", guide_signed_distance, shape=(batch, num_guides, n), device=device)
    if reach_segments is None:
        reach_segments = QUERY_REACH_SEGMENTS
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule: expected one of {SCHEDULES}, got {schedule!r}")
    if not settle >= 0:
        raise ValueError(f"settle: expected a number >= 0 [m], got {settle}")
    if not reach_segments >= 1:
        raise ValueError(f"reach_segments: expected a number >= 1, got {reach_segments}")
    if guide_slot is None:
        guide_slot = torch.full((m,), -1, dtype=torch.int32, device=device)
    rest = followers_rest.detach().to(torch.float32).contiguous()
    if rest_lengths is None:
        rest_lengths = (rest[:, 1:] - rest[:, :-1]).norm(dim=-1)
    elif check:
        check_tensor("rest_lengths", rest_lengths, shape=(m, n - 1), device=device)
    lengths = rest_lengths.detach().to(torch.float32).contiguous()
    if body is None:
        body_arrays, sd = _no_body(device)
    else:
        body_arrays = [*body._kernel_arrays(torch.float32), body.num_vertices, body.num_faces, _body_stride(body, batch)]
        sd = guide_signed_distance.detach().to(torch.float32).contiguous()
    out = torch.empty(batch, m, n, 3, dtype=torch.float32, device=device)
    targets = torch.empty_like(out)
    pushed = torch.zeros(batch, m, dtype=torch.int32, device=device)
    now = _warp.as_warp(guides_now.detach().to(torch.float32).contiguous(), vec3=True)
    link = _follower_arrays(follower_guides, follower_weights, follower_ratios)
    slot, lengths_wp, sd_wp = (_warp.as_warp(guide_slot.to(torch.int32).contiguous()), _warp.as_warp(lengths),
                               _warp.as_warp(sd))
    x, pushed_wp, targets_wp = _warp.as_warp(out, vec3=True), _warp.as_warp(pushed), _warp.as_warp(targets, vec3=True)
    walk_bound = schedule == "walk" and body is not None
    target_bound = torch.empty((batch, m, n) if walk_bound else (0,), dtype=torch.float32, device=device)
    _run_shared(kernels.follower_targets_kernel, batch * m * n, device,
                [_warp.as_warp(guides_rest.detach().to(torch.float32).contiguous(), vec3=True), now,
                 _quats(rotations.detach().to(torch.float32).contiguous()), _warp.as_warp(rest, vec3=True), *link,
                 slot, sd_wp, num_guides, m, n, k, int(walk_bound)], [targets_wp, x, _warp.as_warp(target_bound)])
    if not project:
        return targets, pushed
    if schedule == "walk":
        inputs = [targets_wp, _warp.as_warp(target_bound), slot, lengths_wp, *body_arrays, m, n, int(body is not None),
                  float(margin), int(passes), float(reach_segments), float(_ZERO_DISTANCE[torch.float32]),
                  float(settle), int(WALK_FACE_HINT)]
        _run_shared(kernels.follow_guides_kernel, batch * m, device, inputs, [x, pushed_wp], WALK_THREADS_PER_BLOCK)
        return out, pushed
    # Only `normal` (zero: no plane) and `clearance` (NEVER_QUERIED) are read before they are
    # written: the rest is set by a vertex's first query.
    cleared_at, surface, normal = torch.empty_like(out), torch.empty_like(out), torch.zeros_like(out)
    clearance = torch.full((batch, m, n), kernels.NEVER_QUERIED, dtype=torch.float32, device=device)
    closest_face = torch.empty((batch, m, n), dtype=torch.int32, device=device)
    strand_state = torch.empty((batch, m), dtype=torch.int32, device=device)  # set by the first walk
    planes = [_warp.as_warp(surface, vec3=True), _warp.as_warp(normal, vec3=True)]
    state_wp = _warp.as_warp(strand_state)
    walk = kernels.follower_walk_tiled_kernel(n)

    def follow_the_leader(source, every_strand: bool):
        if batch * m:
            with _warp.launch_scope(device):
                _warp.launch(walk, dim=batch * m,
                             inputs=[slot, lengths_wp, source, *planes, m, float(margin), int(every_strand)],
                             outputs=[x, pushed_wp, state_wp], device=_warp.warp_device(device),
                             block_dim=kernels.WALK_BLOCK_DIM)

    follow_the_leader(targets_wp, True)
    if body is None:
        return out, pushed
    inputs = [now, sd_wp, *link, slot, lengths_wp, *body_arrays, num_guides, m, n, k, float(margin),
              float(reach_segments), float(_ZERO_DISTANCE[torch.float32]), int(ROUNDS_FACE_HINT), x]
    found = [_warp.as_warp(cleared_at, vec3=True), _warp.as_warp(clearance), *planes, _warp.as_warp(closest_face),
             state_wp]
    for _ in range(passes):
        _run(kernels.follower_body_query_kernel, batch * m * n, device, inputs, found)
        follow_the_leader(x, not ROUNDS_SKIP_SETTLED)
    return out, pushed


def follower_distance_bound(guides_now: torch.Tensor, guide_signed_distance: torch.Tensor, followers: torch.Tensor,
                            follower_guides: torch.Tensor, follower_weights: torch.Tensor,
                            follower_ratios: torch.Tensor, *, check: bool = True) -> torch.Tensor:
    """A lower bound on each follower vertex's signed distance to the body [m].

    Args:
        guides_now: (B, K, N, 3) guides [m]; guide_signed_distance: (B, K, N) theirs [m].
        followers: (B, M, N, 3) follower positions [m].
        follower_guides, follower_weights, follower_ratios: as `interpolate_followers`.
        check: as in `guide_frame_rotations`.

    Returns:
        (B, M, N) float32: d(x) >= bound for every vertex (1-Lipschitz signed distance).
    """
    if check:
        check_tensor("guides_now", guides_now, shape=(None, None, None, 3), allow_empty=False)
    batch, num_guides, n = guides_now.shape[:3]
    device = guides_now.device
    if check:
        check_tensor("guide_signed_distance", guide_signed_distance, shape=(batch, num_guides, n), device=device)
        check_tensor("followers", followers, shape=(batch, None, n, 3), device=device)
        _check_followers(followers[0], follower_guides, follower_weights, follower_ratios, num_guides, n, device)
    m, k = followers.shape[1], follower_guides.shape[1]
    out = torch.empty(batch, m, n, dtype=torch.float32, device=device)
    inputs = [_warp.as_warp(guides_now.detach().to(torch.float32).contiguous(), vec3=True),
              _warp.as_warp(guide_signed_distance.detach().to(torch.float32).contiguous()),
              _warp.as_warp(followers.detach().to(torch.float32).contiguous(), vec3=True),
              *_follower_arrays(follower_guides, follower_weights, follower_ratios), num_guides, m, n, k]
    _run_shared(kernels.follower_distance_bound_kernel, batch * m * n, device, inputs, [_warp.as_warp(out)])
    return out


__all__ = ["FRAME_WINDOW", "follow_guides", "follower_distance_bound", "guide_frame_rotations",
           "interpolate_followers", "rotation_quaternions"]
