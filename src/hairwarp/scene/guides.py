"""Guide strands for a dense groom: which strands are simulated, and how the rest follow them.

A groom of 10 000 - 150 000 strands is simulated as K guide strands (1 024 by default, the
paper's strand count: its strands are guides standing for bundles, Section 3.4.1); every method
runs on the guides only, and the followers are interpolated from them afterwards, as production
hair systems do (guide and follow strands; Hsu et al. 2024 for the step from guides to a groom).

Choice of guides. Each strand is described by its root and the shape of its centreline: the
mean position of each quarter of the strand (by arc length) relative to its root, which averages
a curl's phase away and keeps where the strand goes. Guides are picked by farthest-point
sampling in that space, starting from the strand nearest the mean: every strand ends within the
smallest radius such a greedy cover reaches (within 2x of the best K-centre cover), so no part of
the scalp and no style (a fringe, a strand combed the other way) is left without a guide. (Over
16 384 strands, among 16 384 of them drawn at random: `select_guides`.)

Followers. Each strand follows its `neighbours` nearest guides in the same space (a guide follows
only itself), blended by inverse squared distance, each guide carrying the follower's rest
offset in its parallel-transported segment frames (`hairwarp.kernels.guide_interpolation`): a
rigid motion of the guides moves the followers rigidly and a curl keeps its shape. Then a walk
along each strand (`hairwarp.kernels.guide_interpolation.follow_guides_kernel`, a thread per
strand) places each vertex at its rest length from its predecessor (follow-the-leader), and one
inside the body or within `body_margin` of it is pushed out along the signed distance's gradient
and back onto its rest length, so the strand slides over the body. Only the vertices whose guides
do not prove them clear (the signed distance is 1-Lipschitz) are queried. `body_schedule =
"rounds"` takes the queries out of the walk (faster on a GPU up to tens of thousands of strands,
more vertices left inside: docs/guides.md); "auto", the default, picks by device and strand count.

Contact between guides. The energy's per-vertex constants (mass, stiffnesses, contact weights)
stand for a whole bundle: scaling all of them by the same bundle size leaves the minimiser
unchanged, so they are kept. The hair-hair barrier keeps `EnergyConfig.hair_diameter` as the
bundle's diameter rather than one grown to the guides' spacing: neighbouring guides rest a
spacing apart on the scalp (7-8 mm for 1 024 guides), so a radius of that size would push them
apart in the rest pose itself; the bundles keep apart because their guides do.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch

from hairwarp._validate import check_finite, check_tensor, finite_checks_enabled
from hairwarp.runtime import CapturedCall

# Quarters of a strand whose mean positions describe its shape in the guide choice.
SHAPE_SAMPLES = 4
# The guides of a larger groom are chosen among this many of its strands (`select_guides`).
MAX_GUIDE_CANDIDATES = 16384
# `GuideConfig(body_schedule="auto")` runs the rounds on CUDA up to this many strands x frames, the
# walk above. One H100, interpolation + body pass from the CUDA graph (docs/guides.md, twelfth
# session): 10 000 strands rounds 1.9-2.3 ms against the walk's 4.1-4.4; 30 000 rounds 3.3
# against 5.4; 100 000 rounds 8.0-8.4 against 8.5-8.9, but 0.083 % of the followers' vertices
# inside (down to 11.6 mm) against the walk's 0.011 %: there the walk meets the 10 ms goal with
# a seventh of the vertices inside. The switch between 30 000 and 100 000 is not measured.
ROUNDS_MAX_STRANDS = 30000
# Width [m] a strand is written with (USD `widths`) when it stands for a guide's bundle alone.
GUIDE_WIDTH = 1.0e-3


def strand_width(num_strands: int, num_guides: int) -> float:
    """The width [m] each of `num_strands` strands is written with when `num_guides` would cover the
    same scalp at GUIDE_WIDTH: the strands' total cross-section stays that of the guides'
    (1 mm for 1 024 guides alone, 0.32 mm for 10 000 strands, 0.1 mm for 100 000).
    """
    return GUIDE_WIDTH * (num_guides / max(num_strands, 1)) ** 0.5


@dataclass(frozen=True)
class GuideConfig:
    """How a groom is split into guides and followers.

    Attributes:
        num_guides: K guides (a groom of at most K strands is simulated whole); 1 024 by default,
            the paper's strand count.
        neighbours: guides blended per follower.
        shape_weight: weight of the strand shape against the root position in the guide choice
            and the followers' guides (both are lengths [m]).
        body_margin: the body pass pushes follower vertices to at least this signed distance [m]
            (the hair-body barrier's hard distance, 1 mm).
        body_passes: push-out and length projection rounds per vertex of the body pass (0: no
            body pass).
        body_schedule: how the body pass orders its queries, "walk" (vertex after vertex, a
            thread per strand), "rounds" (all queries of a round at once; faster on a GPU for a
            few strands, with more vertices left inside;
            `hairwarp.ops.guide_interpolation.follow_guides`, docs/guides.md) or "auto" (the
            default): the rounds on CUDA for at most `ROUNDS_MAX_STRANDS` (30 000) strands x
            frames, the walk elsewhere (`GuideSet.body_schedule`). On one H100 at 10 000 strands
            the rounds take 1.9-2.3 ms against the walk's 4.1-4.4 (both leave the followers
            less inside than their guides: 0.06 % / 0.007 % against 0.24 %); at 100 000 the walk
            takes 8.5-8.9 ms (goal 10) with a seventh of the rounds' vertices inside; on the CPU
            the rounds are 3x slower than the walk.
        body_settle: the walk does not query a pushed vertex again where the length projection
            moved it less than this from where the push put it [m]; 0: it is queried again, up
            to `body_passes` times (`follow_guides`' `settle`).
        cuda_graph: on CUDA, `GuideSet.follow` of one frame replays its launches from a CUDA
            graph from the second call on with the same shapes, settings and body (a per-frame
            loop that moves its body with `BodyMesh.update`): the launches' host work, ~1 ms a
            call, is then one replay. The graph keeps its buffers (~5 x the groom's positions:
            0.6 GB at 100 000 strands x 100 vertices); one graph is kept at a time.
    """

    num_guides: int = 1024
    neighbours: int = 3
    shape_weight: float = 1.0
    body_margin: float = 1.0e-3
    body_passes: int = 3
    body_schedule: str = "auto"
    body_settle: float = 0.0
    cuda_graph: bool = True

    def __post_init__(self):
        for name in ("num_guides", "neighbours", "body_passes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if name == "body_passes" else 1):
                raise ValueError(f"{name}: expected an integer >= {0 if name == 'body_passes' else 1}, got {value!r}")
        if not self.shape_weight >= 0:
            raise ValueError(f"shape_weight: expected a number >= 0, got {self.shape_weight}")
        if not self.body_settle >= 0:
            raise ValueError(f"body_settle: expected a number >= 0 [m], got {self.body_settle}")
        if not self.body_margin >= 0:
            raise ValueError(f"body_margin: expected a number >= 0 [m], got {self.body_margin}")
        from hairwarp.ops.guide_interpolation import SCHEDULES

        if self.body_schedule not in ("auto", *SCHEDULES):
            raise ValueError(f"body_schedule: expected one of {('auto', *SCHEDULES)}, got {self.body_schedule!r}")


def strand_features(strands: torch.Tensor, shape_weight: float = 1.0) -> torch.Tensor:
    """(M, 3 + 3 * SHAPE_SAMPLES) float32: the root, then each quarter's mean position minus the root.

    Args:
        strands: (M, N, 3) strands [m], vertices evenly spaced in arc length.
        shape_weight: factor on the shape part [dimensionless].
    """
    x = strands.to(torch.float32)
    root = x[:, 0]
    n = x.shape[1]
    bounds = torch.linspace(0, n, SHAPE_SAMPLES + 1).round().long().tolist()
    quarters = [x[:, a:max(b, a + 1)].mean(dim=1) - root for a, b in zip(bounds[:-1], bounds[1:])]
    return torch.cat([root, shape_weight * torch.cat(quarters, dim=1)], dim=1)


def select_guides(features: torch.Tensor, num_guides: int, max_candidates: int = MAX_GUIDE_CANDIDATES) -> torch.Tensor:
    """(K,) int64 strand indices picked by farthest-point sampling of `features` (M, D).

    Starts from the strand nearest the features' mean; deterministic. K >= M returns every strand.
    A groom of more than `max_candidates` strands picks among that many drawn at random (seeded,
    so still deterministic): each of the K picks reads every candidate once, and 16 384 dense
    strands cover a scalp as well as 100 000 for 1 024 guides, at a sixth of the cost.
    """
    m = features.shape[0]
    if num_guides >= m:
        return torch.arange(m)
    candidates = None
    if m > max(max_candidates, num_guides):
        generator = torch.Generator().manual_seed(0)
        candidates = torch.randperm(m, generator=generator)[:max(max_candidates, num_guides)].sort().values
    f = (features if candidates is None else features[candidates]).to(torch.float32).numpy()
    first = int(((f - f.mean(0)) ** 2).sum(1).argmin())
    chosen = np.empty(num_guides, dtype=np.int64)
    chosen[0] = first
    nearest = ((f - f[first]) ** 2).sum(1)
    work, distance = np.empty_like(f), np.empty_like(nearest)
    for k in range(1, num_guides):  # numpy with buffers: no allocation per pick
        pick = int(nearest.argmax())
        chosen[k] = pick
        np.subtract(f, f[pick], out=work)
        np.square(work, out=work)
        work.sum(1, out=distance)
        np.minimum(nearest, distance, out=nearest)
    chosen = torch.from_numpy(chosen)
    return chosen if candidates is None else candidates[chosen]


def nearest_guides(features: torch.Tensor, guide_features: torch.Tensor,
                   neighbours: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(indices (M, k) int64, distances (M, k)) of each strand's k nearest guides in feature space
    (a k-d tree over the guides).
    """
    from scipy.spatial import cKDTree

    k = min(neighbours, guide_features.shape[0])
    distance, index = cKDTree(guide_features.double().numpy()).query(features.double().numpy(), k=k)
    index, distance = np.asarray(index).reshape(len(features), k), np.asarray(distance).reshape(len(features), k)
    return torch.from_numpy(index.astype(np.int64)), torch.from_numpy(distance)


class _FiniteScan:
    """The NaN/Inf scan of `GuideSet.follow`'s CUDA inputs, on a side stream of high priority,
    made once per set and device (its stream, two events and a pinned flag: none is made per
    call).

    `start` marks the inputs as ready on the current stream before the pass is queued; `finite`,
    called once the pass is queued, sums every input on the side stream (it waits for the mark
    only, not for the pass) and reads whether the sum is finite. A NaN or Inf makes the sum NaN
    or infinite; a sum that overflows with every value finite only sends the caller to the exact
    scan (`check_finite`), which then passes. Queued before the pass, the scan's launches, its
    pinned flag and its event delayed the pass's first kernel by their host time; queued behind
    it, they run while the GPU works. (`isfinite(t).all()` per tensor took ~0.3 ms of host time
    a call at 10 000 strands on one H100: torch.profiler, `tools/profile_guides.py`.)
    """

    def __init__(self, device: torch.device):
        self.stream = torch.cuda.Stream(device=device, priority=-1)
        self.ready, self.done = torch.cuda.Event(), torch.cuda.Event()
        self.flag = torch.empty((), dtype=torch.bool, pin_memory=True)

    def start(self, device: torch.device) -> None:
        self.ready.record(torch.cuda.current_stream(device))

    def finite(self, tensors: list) -> bool:
        self.stream.wait_event(self.ready)
        with torch.cuda.stream(self.stream):
            total = torch.cat([t.reshape(-1).to(torch.float32) for t in tensors]).sum()
            self.flag.copy_(torch.isfinite(total), non_blocking=True)
            self.done.record(self.stream)
        self.done.synchronize()
        return bool(self.flag)


@dataclass(eq=False)
class GuideSet:
    """A groom split into guides and followers.

    Attributes:
        groom: the whole groom (`Hairstyle`, M strands x N vertices, rest pose) [m].
        guide_indices: (K,) int64 indices of the guides in the groom.
        follower_guides: (M, k) int64 the guides (0 .. K-1) each strand follows.
        follower_weights: (M, k) float32 blend weights (rows sum to 1).
        follower_ratios: (M, k) float32 strand rest length / guide rest length.
        bundle_sizes: (K,) int64 strands whose nearest guide each guide is (itself included).
        config: the `GuideConfig` used.
    """

    groom: object
    guide_indices: torch.Tensor
    follower_guides: torch.Tensor
    follower_weights: torch.Tensor
    follower_ratios: torch.Tensor
    bundle_sizes: torch.Tensor
    config: GuideConfig

    @classmethod
    def build(cls, groom, config: GuideConfig = GuideConfig()) -> GuideSet:
        """Choose K guides of a `Hairstyle` and each strand's guides and weights (see the module)."""
        strands = groom.strands
        m = strands.shape[0]
        if m == 0:
            raise ValueError("groom: expected at least one strand")
        features = strand_features(strands, config.shape_weight)
        guides = select_guides(features, config.num_guides)
        index, distance = nearest_guides(features, features[guides], config.neighbours)
        weights = 1.0 / (distance.double() ** 2 + 1e-12)
        exact = distance[:, 0] <= 1e-9  # the guides themselves (and exact copies of them)
        weights[exact] = 0.0
        weights[exact, 0] = 1.0
        weights = (weights / weights.sum(1, keepdim=True)).to(torch.float32)
        lengths = (strands[:, 1:] - strands[:, :-1]).double().norm(dim=-1).sum(1)
        ratios = (lengths[:, None] / lengths[guides][index].clamp_min(1e-12)).to(torch.float32)
        bundle = torch.bincount(index[:, 0], minlength=len(guides))
        return cls(groom=groom, guide_indices=guides, follower_guides=index, follower_weights=weights,
                   follower_ratios=ratios, bundle_sizes=bundle, config=config)

    @property
    def num_guides(self) -> int:
        return int(self.guide_indices.numel())

    @property
    def num_strands(self) -> int:
        return int(self.groom.strands.shape[0])

    def guide_hairstyle(self):
        """The guides as a `Hairstyle` (what the methods simulate)."""
        return self.groom.subset(self.guide_indices)

    def reach_lengths(self) -> torch.Tensor:
        """(K,) [m] the farthest any strand following a guide reaches from the guide's root.

        A strand reaches at most its own length from its own root; the body crop of the guides
        (`BodyMesh.crop_for_hair`) uses these in place of the guides' lengths so it keeps every
        triangle a follower can reach.
        """
        strands = self.groom.strands.to(torch.float32)
        lengths = (strands[:, 1:] - strands[:, :-1]).norm(dim=-1).sum(1)
        roots = strands[:, 0]
        reach = torch.zeros(self.num_guides)
        for j in range(self.follower_guides.shape[1]):
            g = self.follower_guides[:, j]
            far = lengths + (roots - roots[self.guide_indices][g]).norm(dim=-1)
            reach.scatter_reduce_(0, g, far, reduce="amax")
        return reach

    def _on(self, device: torch.device) -> dict:
        """The groom's tensors on `device`, copied there once (100 000 strands are 120 MB)."""
        key = str(device)
        cache = self.__dict__.setdefault("_device_cache", {})
        if key not in cache:
            rest = self.groom.strands.to(device=device, dtype=torch.float32).contiguous()
            index = self.guide_indices.to(device)
            slot = torch.full((self.num_strands,), -1, dtype=torch.int32)
            slot[self.guide_indices] = torch.arange(self.num_guides, dtype=torch.int32)
            cache[key] = {"rest": rest, "guide_indices": index, "guides_rest": rest[index].contiguous(),
                          "guide_slot": slot.to(device),
                          "rest_lengths": (rest[:, 1:] - rest[:, :-1]).norm(dim=-1).contiguous(),
                          "link": [self.follower_guides.to(device=device, dtype=torch.int32).contiguous(),
                                   self.follower_weights.to(device).contiguous(),
                                   self.follower_ratios.to(device).contiguous()]}
        return cache[key]

    def describe(self) -> str:
        b = self.bundle_sizes.double()
        return (f"{self.num_guides} guides of {self.num_strands} strands (bundles of {int(b.min())}-"
                f"{int(b.max())} strands, median {float(b.median()):g})")

    @torch.no_grad()
    def follow(self, guide_positions: torch.Tensor, head_rotation: torch.Tensor, body=None,
               guide_signed_distance: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """Every strand of the groom from the guides' positions in B frames.

        Args:
            guide_positions: (B, K, N, 3) the guides [m] (a method's result, or the rigid
                placement).
            head_rotation: (B, 3, 3) the head's rotation in each frame.
            body: the frames' `BodyMesh` (batch 1 or B) for the body pass; None skips it.
            guide_signed_distance: (B, K, N) the guides' signed distances [m] if known.

        Returns:
            ((B, M, N, 3) positions [m] in the dtype of `guide_positions`, the guides' rows
            exactly theirs; facts: "pushed", a (B, M) int32 tensor of the vertices the body pass
            moved per strand, on the device: read it only when needed, it waits for the GPU).
        """
        device = guide_positions.device
        on = self._on(device)
        guides = guide_positions.to(torch.float32)
        batch = guides.shape[0]
        check_tensor("guide_positions", guides, shape=(None, self.num_guides, on["rest"].shape[1], 3), finite=False)
        check_tensor("head_rotation", head_rotation, shape=(batch, 3, 3), finite=False)
        head = head_rotation.to(device)
        # The NaN/Inf scan of all inputs in one wait for the device instead of one per tensor.
        finite = {"guide_positions": guides, "head_rotation": head}
        use_body = body is not None and self.config.body_passes > 0
        if use_body:
            if guide_signed_distance is None:
                from hairwarp.ops import hair_body_signed_distance

                check_finite(**finite)
                finite = {}
                guide_signed_distance = hair_body_signed_distance(guides, body)
            check_tensor("guide_signed_distance", guide_signed_distance, shape=guides.shape[:3], device=device,
                         finite=False)
            finite["guide_signed_distance"] = guide_signed_distance
            inputs = (guides, head, guide_signed_distance.to(torch.float32))
        else:
            body, inputs = None, (guides, head)
        if device.type != "cuda":
            check_finite(**finite)
            x, pushed = self._launches(body, *inputs)
        else:
            # The scan is queued once the pass is, beside it (`_FiniteScan`): the host waits for
            # the scan only, not for the pass (on NaN or Inf the pass's result is dropped and the
            # exact scan names the tensor).
            scanned = [t for t in finite.values() if t.is_floating_point() and t.numel() > 0]
            scan = None
            if scanned and finite_checks_enabled():
                if "finite_scan" not in on:
                    on["finite_scan"] = _FiniteScan(device)
                scan = on["finite_scan"]
                scan.start(device)
            x, pushed = self._replayed(inputs, body) if self.config.cuda_graph else self._launches(body, *inputs)
            if scan is not None and not scan.finite(scanned):
                check_finite(**finite)
        return x.to(guide_positions.dtype), ({"pushed": pushed} if use_body else {})

    def body_schedule(self, device: torch.device, frames: int = 1) -> str:
        """The body pass's schedule ("walk" or "rounds") for `frames` frames on `device`:
        `GuideConfig.body_schedule`, with "auto" resolved.
        """
        schedule = self.config.body_schedule
        if schedule != "auto":
            return schedule
        few = self.num_strands * frames <= ROUNDS_MAX_STRANDS
        return "rounds" if torch.device(device).type == "cuda" and few else "walk"

    def _launches(self, body, guides: torch.Tensor, head: torch.Tensor,
                  guide_signed_distance: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`follow`'s device work on checked inputs: no host synchronisation, so a graph can hold it."""
        from hairwarp.ops.guide_interpolation import follow_guides, guide_frame_rotations

        on = self._on(guides.device)
        rotations = guide_frame_rotations(on["guides_rest"], guides, head, check=False)
        return follow_guides(on["guides_rest"], guides, rotations, on["rest"], *on["link"], guide_slot=on["guide_slot"],
                             body=body, guide_signed_distance=guide_signed_distance,
                             margin=self.config.body_margin, passes=self.config.body_passes,
                             schedule=self.body_schedule(guides.device, guides.shape[0]),
                             rest_lengths=on["rest_lengths"],
                             settle=self.config.body_settle, check=False)

    def _replayed(self, inputs: tuple, body) -> tuple[torch.Tensor, torch.Tensor]:
        """`_launches` from a CUDA graph: eager at the first call with a key (shapes, dtypes,
        settings, body), captured at the second, replayed after. The graph reads the body's
        buffers where they are, so it follows `BodyMesh.update`; another body object is another
        key. One frame only (a batch's buffers would be held for good), and one key at a time.
        """
        if inputs[0].shape[0] != 1:
            return self._launches(body, *inputs)
        key = (inputs[0].device, *[(t.shape, t.dtype) for t in inputs], self.config)
        graphs = self.__dict__.setdefault("_graphs", {})
        entry = graphs.get(key)
        if entry is None or (entry["body"]() if entry["body"] is not None else None) is not body:
            graphs.clear()  # the graph held before (and its buffers) goes
            graphs[key] = {"body": None if body is None else weakref.ref(body), "call": None}
            return self._launches(body, *inputs)
        if entry["call"] is None:
            with torch.cuda.device(inputs[0].device):
                entry["call"] = CapturedCall(lambda *t: self._launches(body, *t), *inputs, warmup=1)
        return entry["call"](*inputs)

    @torch.no_grad()
    def signed_distance(self, x: torch.Tensor, guide_positions: torch.Tensor, guide_signed_distance: torch.Tensor,
                        body, exact_below: float = 0.0) -> torch.Tensor:
        """Each strand vertex's signed distance to the body, queried only where it could be low.

        Args:
            x: (B, M, N, 3) the groom [m] (`follow`'s result).
            guide_positions: (B, K, N, 3) its guides [m]; guide_signed_distance: (B, K, N) theirs.
            body: the frames' `BodyMesh`.
            exact_below: [m] vertices whose bound (see `hairwarp.kernels.guide_interpolation`)
                is below this are queried exactly.

        Returns:
            (B, M, N) [m]: exact where the bound is below `exact_below`, else the bound itself (a
            lower bound, so the sign, and whether a vertex is inside, is exact everywhere).
        """
        from hairwarp.ops import hair_body_signed_distance
        from hairwarp.ops.guide_interpolation import follower_distance_bound

        device = x.device
        on = self._on(device)
        link = on["link"]
        out = follower_distance_bound(guide_positions.to(torch.float32), guide_signed_distance.to(torch.float32),
                                      x.to(torch.float32), *link)
        strand, vertex = (out < exact_below).any(dim=0).nonzero(as_tuple=True)
        if strand.numel():
            points = x[:, strand, vertex].unsqueeze(2).to(torch.float32)
            out[:, strand, vertex] = hair_body_signed_distance(points, body).squeeze(2)
        out[:, on["guide_indices"]] = guide_signed_distance.to(torch.float32)
        return out


__all__ = ["GUIDE_WIDTH", "ROUNDS_MAX_STRANDS", "GuideConfig", "GuideSet", "strand_width", "nearest_guides",
           "select_guides", "strand_features"]
