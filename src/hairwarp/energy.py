"""The total hair energy: Eq. 5 (static) and Eq. 6 without the functional regularization
(that term belongs to the networks, `hairwarp.models`).

Composition, in as few kernel launches as the physics allows:
    1. every strand term (Eq. 7-11, 15, 16) in one fused pass over the vertices
       (`hairwarp.ops.strand_energies`);
    2. hair-body contact (Eq. 12, d = signed distance to the body) in one pass over the
       vertices (`hairwarp.ops.hair_body_contact_energy`);
    3. hair-hair contact (Eq. 12, d = segment-segment distance): broad phase into a pair
       buffer, then one pass over the pairs (`hairwarp.ops.hair_hair_contact_energy`).
Each returns its energy per batch item with a hand-written gradient; autograd adds them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from hairwarp.config import ALL_TERMS, EnergyConfig
from hairwarp.runtime import StreamFork

# Which contact term runs on a side stream beside the other on CUDA (see `total_energy`).
_CONTACT_SIDE = "hair_hair"
# Whether the side stream's term starts before the strand terms on CUDA (on the CPU's side
# thread it always does: the strand terms then run beside it).
_SIDE_FIRST_ON_CUDA = False
# Whether the side stream's blocks go first when both streams wait for room on the GPU.
_SIDE_HIGH_PRIORITY = True


@dataclass
class EnergyInputs:
    """What the energy compares hair positions against, for one frame of a batch.

    Attributes:
        rest_lengths: (M, N-1) rest segment lengths of P_init [m] (Eq. 7).
        rigid: (B, M, N, 3) rigidly placed hair P_rigid [m] (Eq. 9); None drops Eq. 9.
        scalp_normals: (B, M, 3) or (M, 3) posed outward scalp normals at the roots (Eq. 15);
            None drops Eq. 15.
        body: a `hairwarp.ops.BodyMesh` of the posed body (B meshes or one); None drops the
            hair-body contact.
        prev: (B, M, N, 3) positions at t-1 [m] (Eq. 16; no gradient flows into them).
        prev2: (B, M, N, 3) positions at t-2 [m] (Eq. 16).
    """

    rest_lengths: torch.Tensor
    rigid: torch.Tensor | None = None
    scalp_normals: torch.Tensor | None = None
    body: object | None = None
    prev: torch.Tensor | None = None
    prev2: torch.Tensor | None = None


@dataclass
class EnergyResult:
    """The total energy per batch item and its parts.

    Attributes:
        total: (B,) differentiable w.r.t. the hair positions.
        terms: name -> (B,) weighted value of each term (detached), names from
            `hairwarp.config.ALL_TERMS`; terms switched off are absent.
        hair_hair_info: the hair-hair `HairHairContactInfo` (pair count on the device until read),
            or the count itself (the plain-torch reference), if computed.
    """

    total: torch.Tensor
    terms: dict[str, torch.Tensor] = field(default_factory=dict)
    hair_hair_info: object | None = None

    @property
    def hair_hair_pairs(self) -> int | None:
        """Number of hair-hair contact pairs found (all batch items), if computed (reads the device)."""
        info = self.hair_hair_info
        return info if info is None or isinstance(info, int) else info.pair_count


def _as_batched(x: torch.Tensor) -> torch.Tensor:
    if x.dim() == 3:
        return x.unsqueeze(0)
    if x.dim() != 4 or x.shape[-1] != 3:
        from hairwarp._validate import check_tensor

        check_tensor("x", x, shape=(None, None, None, 3))
    return x


def total_energy(
    x: torch.Tensor,
    inputs: EnergyInputs,
    config: EnergyConfig | None = None,
    *,
    dynamic: bool = False,
    terms: tuple[str, ...] | None = None,
    graph_safe: bool = False,
    hair_hair_capacity: int | None = None,
    hair_hair_cache=None,
    hair_hair_list=None,
    hair_body_cache=None,
    barrier_join_fraction: torch.Tensor | None = None,
) -> EnergyResult:
    """The total energy of hair positions `x`: Eq. 5, or Eq. 6 (without L_func_reg) when `dynamic`.

    Args:
        x: (B, M, N, 3) or (M, N, 3) hair positions [m], float32 or float64. Vertices 0 and 1
            of each strand are fixed: they get zero gradient.
        inputs: rest lengths, rigid placement, scalp normals, body, previous states.
        config: weights and constants (defaults: `EnergyConfig()`).
        dynamic: add the inertia term of Eq. 16 (needs `inputs.prev` and `inputs.prev2`).
        terms: restrict to a subset of `hairwarp.config.ALL_TERMS` (ablations).
        graph_safe: read nothing back to the host (a CUDA graph can capture the call): the
            hair-hair pairs beyond the pair buffer's capacity are dropped instead of regrown,
            and `result.hair_hair_info.check()` says so afterwards (see `CapturedEnergy`).
        hair_hair_capacity: pair-buffer capacity [pairs] for the whole batch; None:
            `config.hair_hair_capacity_per_segment` per segment.
        hair_hair_cache: a `hairwarp.ops.hair_hair_contact.HairHairPairCache` that keeps the
            hair-hair pair list across calls (CPU only, not with `graph_safe`): the same
            energy, cheaper for an optimizer's evaluations of slowly moving hair.
        hair_hair_list: a built `hairwarp.ops.hair_hair_contact.HairHairPairList` (device
            buffers, graph-safe): hair-hair contact over its stored pairs, exact while its
            `stale` flag stays 0 (the caller rebuilds it); the physics' steps on CUDA.
        hair_body_cache: a `hairwarp.ops.hair_body_contact.HairBodyDistanceCache` kept across
            calls against a body that does not move (the caller resets it when it does; device
            tensors, graph-safe): the hair-body queries it proves misses are skipped.
        barrier_join_fraction: a one-element tensor on `x`'s device in place of
            `config.barrier_join_fraction`: the contact kernels read it at launch, so a graph
            captured with it follows the value it holds (training's annealed b_p); None: the
            config's.

    Returns:
        EnergyResult with `total` of shape (B,) ((1,) for an unbatched `x`).
    """
    from hairwarp import ops

    config = config or EnergyConfig()
    xb = _as_batched(x)
    if hair_hair_cache is not None and graph_safe:
        raise ValueError("hair_hair_cache: not with graph_safe=True (a captured call keeps no host state)")
    wanted = set(ALL_TERMS if terms is None else terms)
    unknown = wanted - set(ALL_TERMS)
    if unknown:
        raise ValueError(f"terms: unknown term(s) {sorted(unknown)}; expected names from {ALL_TERMS}")
    if not dynamic:
        wanted.discard("inertia")
    elif inputs.prev is None or inputs.prev2 is None:
        raise ValueError("inputs.prev, inputs.prev2: the dynamic energy (Eq. 6) needs the two previous states")

    with_hair_body = "hair_body_contact" in wanted and inputs.body is not None and config.hair_body_weight != 0.0
    with_hair_hair = "hair_hair_contact" in wanted and config.hair_hair_weight != 0.0
    bp = config.barrier_join_fraction if barrier_join_fraction is None else barrier_join_fraction
    if hair_hair_capacity is None:
        segments = xb.shape[1] * (xb.shape[2] - 1)
        hair_hair_capacity = config.hair_hair_capacity_per_segment * segments * xb.shape[0]

    def hair_hair_term():
        return ops.hair_hair_contact_energy(
            xb,
            config.hair_diameter,
            config.hair_hair_dhat,
            bp,
            weight=config.hair_hair_weight,
            variant=config.barrier_variant,
            capacity=hair_hair_capacity,
            on_overflow="defer" if graph_safe else "grow",
            pair_cache=hair_hair_cache,
            pair_list=hair_hair_list,
        )

    def hair_body_term():
        return ops.hair_body_contact_energy(
            xb,
            inputs.body,
            config.hair_body_xi,
            config.hair_body_dhat,
            bp,
            weight=config.hair_body_weight,
            variant=config.barrier_variant,
            distance_cache=hair_body_cache,
        )

    # The two contact terms run side by side: on CUDA at batch 1 hair-body's deep queries are a
    # few thousand long BVH walks that leave most of the GPU idle (docs/contact.md 7-9); on the
    # CPU each term is one core's work (docs/contact.md 10). `_CONTACT_SIDE` names the term on
    # the side stream (or thread): "hair_hair" puts hair-hair, the longer chain, on a
    # high-priority stream. On the CPU it starts first, the strand terms and the other contact
    # term following on this thread; on CUDA after the strand terms (`_SIDE_FIRST_ON_CUDA`).
    both = with_hair_body and with_hair_hair
    hb_fork = StreamFork(xb.device, "hair_body", enabled=both and _CONTACT_SIDE == "hair_body",
                         high_priority=_SIDE_HIGH_PRIORITY, cpu_thread=True)
    hh_fork = StreamFork(xb.device, "hair_hair", enabled=both and _CONTACT_SIDE == "hair_hair",
                         high_priority=_SIDE_HIGH_PRIORITY, cpu_thread=True)
    pending = {}  # term -> its future
    here = []  # the terms computed on this stream and thread, after the strand terms
    for with_term, fork, term in ((with_hair_hair, hh_fork, hair_hair_term), (with_hair_body, hb_fork, hair_body_term)):
        if with_term and (fork.threaded or (fork.active and _SIDE_FIRST_ON_CUDA)):
            pending[term] = fork.call(term)
        elif with_term:
            here.append((fork, term))

    strand_terms = tuple(t for t in ("stretch", "bending", "auxiliary", "smoothness", "gravity",
                                     "root_alignment", "inertia") if t in wanted)
    total, parts = ops.strand_energies(
        xb,
        inputs.rest_lengths,
        config,
        rigid=inputs.rigid,
        scalp_normals=inputs.scalp_normals,
        prev=inputs.prev if dynamic else None,
        prev2=inputs.prev2 if dynamic else None,
        terms=strand_terms,
    )
    result = EnergyResult(total=total, terms=dict(parts))
    for fork, term in here:
        pending[term] = fork.call(term)

    if with_hair_hair:
        e_hh, info = pending[hair_hair_term].result()
        hh_fork.join(e_hh, info.device_count)
        result.total = result.total + e_hh
        result.terms["hair_hair_contact"] = e_hh.detach()
        result.hair_hair_info = info
    if with_hair_body:
        e_hb = pending[hair_body_term].result()
        hb_fork.join(e_hb)
        result.total = result.total + e_hb
        result.terms["hair_body_contact"] = e_hb.detach()

    if x.dim() == 3:
        result.total = result.total.reshape(1)
    return result


def static_energy(x: torch.Tensor, inputs: EnergyInputs, config: EnergyConfig | None = None, **kw) -> EnergyResult:
    """Eq. 5: the static total energy of a drape (see `total_energy`)."""
    return total_energy(x, inputs, config, dynamic=False, **kw)


def dynamic_energy(x: torch.Tensor, inputs: EnergyInputs, config: EnergyConfig | None = None, **kw) -> EnergyResult:
    """Eq. 6 without L_func_reg: the static energy plus inertia (Eq. 16) (see `total_energy`)."""
    return total_energy(x, inputs, config, dynamic=True, **kw)


class CapturedEnergy:
    """`total_energy` and its gradient for one hair shape, captured in a CUDA graph and replayed.

    On CUDA a forward+backward of the total energy is a few dozen kernel launches and torch ops
    whose host cost dominates at small batch; a replay launches them at once. The capture is
    possible because nothing in the graph-safe energy reads the device (`graph_safe=True`): the
    hair-hair pair buffer has a fixed capacity, set from an eager warm-up call (twice its pair
    count, at least one pair per segment: a drape has about one), and `check()` raises `HairHairCapacityError` if a
    later call found more pairs than that (the energy then missed some). On the CPU (or with
    `use_graph=False`) the same object evaluates eagerly with the same results.

    Args:
        x: (B, M, N, 3) example hair positions [m]: shape, dtype and device of every call.
        inputs, config, dynamic, terms, barrier_join_fraction: as `total_energy` (held by
            reference: the graph reads the body, rest lengths, previous states and the join
            fraction's tensor as they are at replay time).
        use_graph: capture on CUDA (default); False evaluates eagerly everywhere.

    Call: `energy, gradient = captured(x)`: (B,) energies [J] and (B, M, N, 3) d energy / d x
    (zero on the fixed vertices 0, 1), both new tensors.
    """

    def __init__(self, x: torch.Tensor, inputs: EnergyInputs, config: EnergyConfig | None = None, *,
                 dynamic: bool = False, terms: tuple[str, ...] | None = None, use_graph: bool = True,
                 barrier_join_fraction: torch.Tensor | None = None):
        from hairwarp._validate import check_tensor

        check_tensor("x", x, shape=(None, None, None, 3), allow_empty=False)
        self.inputs, self.config, self.dynamic, self.terms = inputs, config or EnergyConfig(), dynamic, terms
        self.barrier_join_fraction = barrier_join_fraction
        self.shape, self.dtype, self.device = tuple(x.shape), x.dtype, x.device
        # Eager warm-up: checks the inputs, compiles the kernels, and sizes the pair buffer.
        probe = self._evaluate(x, graph_safe=False, capacity=None)
        segments = x.shape[0] * x.shape[1] * (x.shape[2] - 1)
        found = 0 if probe[2] is None else probe[2].pair_count
        self.hair_hair_capacity = max(2 * found, segments, 1)
        self._info = None
        self._graph = None
        if use_graph and x.device.type == "cuda":
            from hairwarp.runtime import CapturedCall

            def step(x_static):
                energy, gradient, info = self._evaluate(x_static, graph_safe=True, capacity=self.hair_hair_capacity)
                self._graph_info = info
                return energy, gradient

            self._graph = CapturedCall(step, x)
            self._info = self._graph_info

    @property
    def captured(self) -> bool:
        """Whether calls replay a CUDA graph."""
        return self._graph is not None

    def _evaluate(self, x: torch.Tensor, graph_safe: bool, capacity: int | None):
        xg = x.detach().requires_grad_(True)
        with torch.enable_grad():
            result = total_energy(xg, self.inputs, self.config, dynamic=self.dynamic, terms=self.terms,
                                  graph_safe=graph_safe, hair_hair_capacity=capacity,
                                  barrier_join_fraction=self.barrier_join_fraction)
            (gradient,) = torch.autograd.grad(result.total.sum(), xg)
        return result.total.detach(), gradient, result.hair_hair_info

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if tuple(x.shape) != self.shape or x.dtype != self.dtype or x.device != self.device:
            raise ValueError(f"x: expected {self.shape} {self.dtype} on {self.device} (the captured shape), "
                             f"got {tuple(x.shape)} {x.dtype} on {x.device}")
        if self._graph is not None:
            return self._graph(x)
        energy, gradient, self._info = self._evaluate(x, graph_safe=True, capacity=self.hair_hair_capacity)
        return energy, gradient

    def overflowed(self) -> bool:
        """Whether the last call found more hair-hair pairs than the buffer holds (reads the device)."""
        return self._info is not None and self._info.overflow

    def check(self) -> None:
        """Raise `HairHairCapacityError` if the last call found more hair-hair pairs than the
        buffer holds (reads the device once).

        Raises:
            HairHairCapacityError: the last energy missed pairs; build a new `CapturedEnergy`.
        """
        if self._info is not None:
            self._info.check()
