"""Plain-torch hair-hair contact energy (HairFormer Eq. 12-14, d = segment-segment distance).

The same energy as `hairwarp.ops.hair_hair_contact_energy`, with the same pair rules (segments
of different strands of one batch item; segments with index < `skip_root_segments` left out;
no gradient to the fixed vertices 0 and 1), written with torch operations only, differentiable
by autograd. Method:

1. Candidate pairs, without gradient, by one of two searches:
   - "bruteforce": every pair of segments of one batch item, O(S^2) memory: small inputs.
   - "grid": segment midpoints sorted into cubic voxels of width R = max segment length +
     xi + dhat (keyed by batch item and voxel coordinates); each segment is compared with the
     segments of the 27 voxels around its own (found by `searchsorted` on the sorted keys).
     Two segments closer than xi + dhat have midpoints closer than R, so they sit in the same
     or adjacent voxels: no pair is missed.
   Both keep the pairs whose exact distance is < xi + dhat.
2. Per pair, the closest parameters (s, t) are found without gradient (the same candidate
   enumeration as the kernel: four endpoint-to-segment projections and the clamped interior
   solution, the smallest wins), then d = |p(s) - q(t)| is evaluated with autograd: by the
   envelope theorem this is the exact gradient of the distance (where d > 0).
3. energy = weight * sum of `torch_reference.barrier.barrier(d)` per batch item.
"""

from __future__ import annotations

import torch

from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.torch_reference.barrier import barrier

# Above this many segments per batch item "auto" switches from brute force to the voxel grid.
BRUTEFORCE_MAX_SEGMENTS = 2048


def _dot(a, b):
    return (a * b).sum(-1)


def _point_segment_parameter(r, e):
    ee = _dot(e, e)
    safe = torch.where(ee > 0, ee, torch.ones_like(ee))
    return torch.where(ee > 0, (_dot(r, e) / safe).clamp(0.0, 1.0), torch.zeros_like(ee))


@torch.no_grad()
def edge_edge_parameters(p0, p1, q0, q1):
    """Closest parameters (s, t) of segments p0-p1, q0-q1 (..., 3): the kernel's enumeration."""
    ep, eq, r = p1 - p0, q1 - q0, p0 - q0
    aa, ee, bb, cc, ff = _dot(ep, ep), _dot(eq, eq), _dot(ep, eq), _dot(ep, r), _dot(eq, r)
    zero, one = torch.zeros_like(aa), torch.ones_like(aa)
    cand_s = [zero, one, _point_segment_parameter(-r, ep), _point_segment_parameter(eq - r, ep)]
    cand_t = [_point_segment_parameter(r, eq), _point_segment_parameter(r + ep, eq), zero, one]
    n = torch.cross(ep, eq, dim=-1)
    nn = _dot(n, n)
    ok = (aa > 0) & (ee > 0) & (nn > 0)
    s = (_dot(torch.cross(-r, eq, dim=-1), n) / torch.where(ok, nn, one)).clamp(0.0, 1.0)
    t = ((bb * s + ff) / torch.where(ok, ee, one)).clamp(0.0, 1.0)
    s = ((bb * t - cc) / torch.where(ok, aa, one)).clamp(0.0, 1.0)
    cand_s.append(torch.where(ok, s, zero))
    cand_t.append(torch.where(ok, t, zero))
    s_all = torch.stack(cand_s, -1)
    t_all = torch.stack(cand_t, -1)
    v = r[..., None, :] + s_all[..., None] * ep[..., None, :] - t_all[..., None] * eq[..., None, :]
    best = _dot(v, v).argmin(-1, keepdim=True)
    return s_all.gather(-1, best)[..., 0], t_all.gather(-1, best)[..., 0]


def edge_edge_distance(p0, p1, q0, q1):
    """Segment-segment distance (...,), differentiable (envelope theorem; d > 0 assumed)."""
    s, t = edge_edge_parameters(p0, p1, q0, q1)
    v = (p0 - q0) + s[..., None] * (p1 - p0) - t[..., None] * (q1 - q0)
    dist2 = _dot(v, v)
    # sqrt'(0) is infinite: the reference only promises gradients where d > 0.
    return torch.sqrt(torch.clamp(dist2, min=torch.finfo(dist2.dtype).tiny))


def _segments(x4):
    """Flat segment endpoints (S, 3) x2, strand ids, batch ids and index along the strand."""
    b, m, n, _ = x4.shape
    p0 = x4[:, :, :-1].reshape(-1, 3)
    p1 = x4[:, :, 1:].reshape(-1, 3)
    seg = torch.arange(b * m * (n - 1), device=x4.device)
    strand = seg // (n - 1)
    return p0, p1, strand, strand // m, seg % (n - 1)


@torch.no_grad()
def _filter(i, j, x4, cutoff, skip_root_segments):
    """Keep candidate pairs (i < j) of different strands, both past the root, closer than cutoff."""
    p0, p1, strand, batch, index = _segments(x4)
    keep = (i < j) & (strand[i] != strand[j]) & (batch[i] == batch[j])
    keep &= (index[i] >= skip_root_segments) & (index[j] >= skip_root_segments)
    i, j = i[keep], j[keep]
    d = edge_edge_distance(p0[i], p1[i], p0[j], p1[j])
    close = d < cutoff
    return torch.stack([i[close], j[close]], dim=1)


@torch.no_grad()
def pairs_bruteforce(x4, cutoff, skip_root_segments=2):
    """All segment pairs closer than `cutoff` [m], by comparing every pair: (P, 2) flat ids, sorted."""
    b, m, n, _ = x4.shape
    per_item = m * (n - 1)
    if b == 0 or per_item == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=x4.device)
    ii, jj = torch.triu_indices(per_item, per_item, offset=1, device=x4.device)
    offsets = torch.arange(b, device=x4.device)[:, None] * per_item
    i = (ii[None] + offsets).reshape(-1)
    j = (jj[None] + offsets).reshape(-1)
    # Cheap necessary condition first: midpoints within cutoff + max segment length.
    p0, p1, _, _, _ = _segments(x4)
    mid = 0.5 * (p0 + p1)
    radius = cutoff + float((p1 - p0).norm(dim=1).max())
    near = (mid[i] - mid[j]).norm(dim=1) <= radius
    return _sorted(_filter(i[near], j[near], x4, cutoff, skip_root_segments), b * per_item)


@torch.no_grad()
def pairs_grid(x4, cutoff, skip_root_segments=2):
    """Segment pairs closer than `cutoff` [m] by a voxel grid of midpoints: (P, 2) flat ids, sorted."""
    b, m, n, _ = x4.shape
    p0, p1, _, batch, _ = _segments(x4)
    count = p0.shape[0]
    if count == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=x4.device)
    mid = 0.5 * (p0 + p1)
    radius = cutoff + float((p1 - p0).norm(dim=1).max())
    cell = torch.floor((mid - mid.min(0).values) / radius).long() + 1  # >= 1: neighbours stay >= 0
    dims = cell.max(0).values + 2
    key = ((batch * dims[0] + cell[:, 0]) * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    sorted_key, order = torch.sort(key)
    found = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nb = cell + torch.tensor([dx, dy, dz], device=x4.device)
                nkey = ((batch * dims[0] + nb[:, 0]) * dims[1] + nb[:, 1]) * dims[2] + nb[:, 2]
                start = torch.searchsorted(sorted_key, nkey, right=False)
                end = torch.searchsorted(sorted_key, nkey, right=True)
                counts = end - start
                total = int(counts.sum())
                if total == 0:
                    continue
                i = torch.repeat_interleave(torch.arange(count, device=x4.device), counts)
                first = torch.repeat_interleave(start, counts)
                rank = torch.arange(total, device=x4.device) - torch.repeat_interleave(
                    torch.cumsum(counts, 0) - counts, counts
                )
                j = order[first + rank]
                near = (mid[i] - mid[j]).norm(dim=1) <= radius
                found.append(_filter(i[near], j[near], x4, cutoff, skip_root_segments))
    if not found:
        return torch.zeros(0, 2, dtype=torch.long, device=x4.device)
    return _sorted(torch.cat(found), count)


def _sorted(pairs, num_segments):
    key = pairs[:, 0] * max(num_segments, 1) + pairs[:, 1]
    return pairs[torch.argsort(key)]


def hair_hair_contact_energy(
    x: torch.Tensor,
    xi: float,
    dhat: float,
    bp: float,
    weight: float = 1.0,
    variant: str = "quadratic",
    *,
    skip_root_segments: int = 2,
    method: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hair-hair contact energy in plain torch, differentiable w.r.t. `x` by autograd.

    Args:
        x: hair positions [m], (M, N, 3) or (B, M, N, 3), float32 or float64.
        xi: hard barrier [m].
        dhat: soft barrier width [m].
        bp: barrier join fraction in (0, 1).
        weight: lambda_hh (energy = weight * sum over pairs of B(d)).
        variant: "quadratic", "monotone" or "paper".
        skip_root_segments: segments with index below this along each strand take no part.
        method: "bruteforce", "grid", or "auto" (brute force up to `BRUTEFORCE_MAX_SEGMENTS`
            segments per batch item).

    Returns:
        (energy, pairs): energy (B,) or () for unbatched input; pairs (P, 2) flat segment ids.
    """
    x4 = x if x.dim() == 4 else x.unsqueeze(0)
    b, m, n, _ = x4.shape
    if method == "auto":
        method = "bruteforce" if m * max(n - 1, 0) <= BRUTEFORCE_MAX_SEGMENTS else "grid"
    search = {"bruteforce": pairs_bruteforce, "grid": pairs_grid}[method]
    pairs = search(x4.detach(), xi + dhat, skip_root_segments)
    # The fixed vertices 0 and 1 take no gradient (Section 3.4).
    k = NUM_FIXED_VERTICES
    x_eff = torch.cat([x4[:, :, :k].detach(), x4[:, :, k:]], dim=2)
    p0, p1, _, batch, _ = _segments(x_eff)
    i, j = pairs[:, 0], pairs[:, 1]
    d = edge_edge_distance(p0[i], p1[i], p0[j], p1[j])
    per_pair = weight * barrier(d, xi, dhat, bp, variant)
    energy = torch.zeros(b, dtype=x.dtype, device=x.device).index_add(0, batch[i], per_pair)
    return (energy if x.dim() == 4 else energy[0]), pairs
