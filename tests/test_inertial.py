"""The inertial step (hairwarp.models.inertial), its training on physics clips, and the method "inertial"."""

import math
import os

import numpy as np
import pytest
import torch

from hairwarp.metrics import motion_fidelity
from hairwarp.models.checkpoint import load_checkpoint, save_checkpoint
from hairwarp.models.inertial import (KEEP_OUT_VELOCITIES, InertialConfig, InertialStep, body_held_chain_relaxation,
                                      body_hold_weights,
                                      chain_operator, hanging_chain_tension, limited_change, vertex_features)
from hairwarp.ops import BodyMesh, follow_the_leader, hair_body_signed_distance
from meshes import icosphere

# The toy clip of the training tests: 16 strands x 12 vertices of medium wavy hair, 0.8 s of random
# head moves (49 frames at 60 fps), simulated by the physics on this CPU once per module.
TOY = {"strand_stride": 64, "num_vertices": 12}


def _hanging(m=3, n=6, dtype=torch.float64):
    """m vertical strands of n vertices, 2 cm segments, roots on a row along x."""
    x = torch.zeros(m, n, 3, dtype=dtype)
    x[:, :, 0] = torch.arange(m, dtype=dtype)[:, None] * 0.05
    x[:, :, 1] = -0.02 * torch.arange(n, dtype=dtype)[None, :]
    return x


def _segment_lengths(x):
    return (x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1)


def test_a_still_equilibrium_is_its_own_rollout():
    rest = _hanging()
    frames = rest.expand(5, -1, -1, -1).clone()
    step = InertialStep().double()
    out = step.rollout(frames, frames)
    torch.testing.assert_close(out, frames, atol=1e-12, rtol=0)


def test_a_moving_head_keeps_rest_lengths_and_fixed_vertices():
    rest = _hanging()
    t = torch.arange(8, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.03 * t, 0 * t, 0 * t], dim=-1)[:, None, None, :]  # the head moves along x
    step = InertialStep().double()
    with torch.no_grad():
        out = step.rollout(rigid.clone(), rigid)
    torch.testing.assert_close(_segment_lengths(out), _segment_lengths(rigid), atol=1e-9, rtol=0)
    torch.testing.assert_close(out[:, :, :2], rigid[:, :, :2], atol=0, rtol=0)
    # The tips lag behind the moving roots: inertia, which the equilibrium (the rigid placement) has not.
    assert float((out[-1, :, -1, 0] - rigid[-1, :, -1, 0]).max()) < -1e-3


def test_a_chain_of_one_free_vertex_runs():
    """N = 3: the chain's operator is 1 x 1, still applied as the chain's."""
    rest = _hanging(2, 3)
    rigid = rest[None] + torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)
    rigid = torch.cat([rigid, rigid + torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)])
    step = InertialStep(InertialConfig(coupling="chain")).double()
    with torch.no_grad():
        out = step.rollout(rigid.clone(), rigid)
    assert out.shape == rigid.shape
    torch.testing.assert_close(_segment_lengths(out), _segment_lengths(rigid), atol=1e-12, rtol=0)


def test_coefficients_read_arc_length_for_any_vertex_count():
    step = InertialStep()
    for n in (4, 7, 100):
        rest = _hanging(2, n, torch.float32)
        with torch.no_grad():
            gate, retention = step.coefficients(rest)
        assert gate.shape == retention.shape == (2, n, 1)
        assert float(gate[:, :2].abs().max()) == 0.0 and float(retention[:, :2].abs().max()) == 0.0
        assert math.isclose(float(gate[0, -1]), InertialConfig().gate_init, rel_tol=1e-5)
        assert math.isclose(float(retention[0, -1]), InertialConfig().retention_init, rel_tol=1e-5)
    feats = vertex_features(_hanging(1, 5))
    torch.testing.assert_close(feats[0, :, 0], torch.linspace(0, 1, 5, dtype=torch.float64))
    torch.testing.assert_close(feats[0, :, 2], torch.full((5,), 0.08, dtype=torch.float64))


@pytest.mark.parametrize("coupling", ["vertex", "chain"])
def test_rollout_gradient_matches_finite_differences(coupling):
    rest = _hanging(2, 5)
    t = torch.arange(4, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.02 * t**2, 0.01 * t, 0 * t], dim=-1)[:, None, None, :]
    torch.manual_seed(0)
    step = InertialStep(InertialConfig(hidden_dim=4, coupling=coupling)).double()
    with torch.no_grad():
        step.net[-1].weight.normal_(0, 0.3)
    target = rigid + 0.01

    def loss_of(bias):
        step.net[-1].bias.data.copy_(bias)
        return (step.rollout(rigid.clone(), rigid) - target).square().sum()

    bias = step.net[-1].bias.detach().clone()
    step.net[-1].bias.grad = None
    step.net[-1].bias.data.copy_(bias)
    (step.rollout(rigid.clone(), rigid) - target).square().sum().backward()
    analytic = step.net[-1].bias.grad.clone()
    for i in range(len(bias)):
        e = torch.zeros_like(bias)
        e[i] = 1e-6
        with torch.no_grad():
            fd = (loss_of(bias + e) - loss_of(bias - e)) / 2e-6
        assert math.isclose(float(analytic[i]), float(fd), rel_tol=1e-5, abs_tol=1e-10)


@pytest.mark.parametrize("config", [
    InertialConfig(coupling="chain", damping="relative", equilibrium_speed=0.12, bending=3e4, tension_init=0.5),
    InertialConfig(coupling="vertex", damping="absolute"),
])
def test_a_rollout_in_pieces_is_the_whole_rollout(config):
    """`rollout(carry=RolloutCarry())` over a sequence cut in pieces of 1, 3 and 4 frames gives the
    whole sequence's rollout bit for bit (states, the rate-limited equilibrium, the head's motion
    across a cut, the coefficients of the first frame); a copied carry leaves the original's."""
    from hairwarp.models.inertial import RolloutCarry

    torch.manual_seed(0)
    step = InertialStep(config).double()
    rest = _hanging(3, 8)
    angle = torch.linspace(0.0, 0.6, 8, dtype=torch.float64)
    turn = torch.zeros(8, 3, 3, dtype=torch.float64)
    turn[:, 0, 0], turn[:, 0, 2], turn[:, 1, 1] = torch.cos(angle), torch.sin(angle), 1.0
    turn[:, 2, 0], turn[:, 2, 2] = -torch.sin(angle), torch.cos(angle)
    rigid = torch.einsum("tij,mnj->tmni", turn, rest)
    equilibrium = rigid + 0.01 * torch.randn_like(rigid) * torch.linspace(0, 1, 8, dtype=torch.float64)[:, None]
    equilibrium[:, :, :2] = rigid[:, :, :2]
    with torch.no_grad():
        whole = step.rollout(equilibrium, rigid)
        carry = RolloutCarry()
        pieces = []
        for a, b in ((0, 1), (1, 4), (4, 8)):
            if a == 1:
                spare = carry.copy()
                step.rollout(equilibrium[a:b], rigid[a:b], carry=spare)
                assert spare.prev is not carry.prev
            pieces.append(step.rollout(equilibrium[a:b], rigid[a:b], carry=carry))
    assert torch.equal(torch.cat(pieces), whole)
    assert float((whole - rigid).abs().max()) > 1e-3
    with pytest.raises(ValueError, match="rigid"):
        step.rollout(equilibrium[:2, :2], rigid[:2, :2], carry=carry)


def test_bad_inputs_name_the_argument():
    step = InertialStep()
    rigid = _hanging(2, 5, torch.float32)[None].expand(3, -1, -1, -1)
    with pytest.raises(ValueError, match="equilibrium"):
        step.rollout(rigid[:2], rigid)
    bad = rigid.clone()
    bad[1, 0, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="rigid"):
        step.rollout(rigid.clone(), bad)
    with pytest.raises(ValueError, match="gate_init"):
        InertialConfig(gate_init=1.0)
    with pytest.raises(ValueError, match="coupling"):
        InertialConfig(coupling="rope")
    with pytest.raises(ValueError, match="tension_init"):
        InertialConfig(tension_init=0.0)
    with pytest.raises(ValueError, match="rigid"):
        step.rollout(rigid[:, :, :2].contiguous(), rigid[:, :, :2].contiguous())


@pytest.mark.parametrize("coupling", ["vertex", "chain"])
def test_checkpoint_round_trip(tmp_path, coupling):
    step = InertialStep(InertialConfig(hidden_dim=8, gate_init=0.9, coupling=coupling))
    with torch.no_grad():
        step.net[0].weight.mul_(1.5)
    save_checkpoint(tmp_path / "step.pt", step)
    back = load_checkpoint(tmp_path / "step.pt")
    assert isinstance(back.model, InertialStep) and back.config == step.config
    rest = _hanging(2, 6, torch.float32)
    torch.testing.assert_close(back.model.coefficients(rest)[0], step.coefficients(rest)[0])


def test_keep_out_of_body_leaves_no_vertex_inside_and_keeps_rest_lengths():
    from hairwarp.methods.inertial import KEEP_OUT_MARGIN, keep_out_of_body

    v, f = icosphere(8, radius=0.1)
    body = BodyMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32))
    # Strands rooted above the sphere, hanging straight through it.
    m, n = 5, 16
    x = torch.zeros(1, m, n, 3)
    x[0, :, :, 0] = torch.linspace(-0.04, 0.04, m)[:, None]
    x[0, :, :, 1] = 0.14 - 0.02 * torch.arange(n)[None, :]
    rigid = x.clone()
    assert float(hair_body_signed_distance(x, body).min()) < -0.05
    out = keep_out_of_body(x, rigid, body)
    assert float(hair_body_signed_distance(out, body).min()) > -1e-5
    torch.testing.assert_close(_segment_lengths(out), _segment_lengths(rigid), atol=1e-5, rtol=0)
    torch.testing.assert_close(out[:, :, :2], rigid[:, :, :2])
    assert KEEP_OUT_MARGIN > 0
    # One round is not enough here (the projection takes later vertices back in): without the
    # turns, what is left inside less than the margin deep is pushed out without the projection
    # (a crease of the body), stretching only its own segments; deeper vertices stay.
    once = keep_out_of_body(x, rigid, body, passes=1, turns=0)
    d = hair_body_signed_distance(once, body)[..., 2:]
    assert not bool(((d < 0) & (d > -KEEP_OUT_MARGIN)).any())
    plain = keep_out_of_body(x, rigid, body, passes=1, turns=0, final_depth=0.0)
    d_plain = hair_body_signed_distance(plain, body)[..., 2:]
    shallow = (d_plain < 0) & (d_plain > -KEEP_OUT_MARGIN)
    assert bool(shallow.any())  # the round alone leaves some
    moved = (once - plain).norm(dim=-1)[..., 2:]
    assert bool((moved[~shallow] == 0).all()) and float(moved[shallow].max()) <= 2 * KEEP_OUT_MARGIN + 1e-6
    torch.testing.assert_close(once[:, :, :2], rigid[:, :, :2])


def test_keep_out_of_body_turns_strands_out_of_a_pinch_between_two_parts():
    """Two overlapping spheres (an arm against a torso) and strands hanging through the lens they
    share: pushed along the gradient a vertex leaves one sphere for the other, so pushes alone
    leave some inside; turning the segments about their predecessors frees them all, the rest
    lengths kept."""
    from hairwarp.methods.keep_out import keep_out_of_body

    v, f = icosphere(8, radius=0.1)
    v, f = torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32)
    body = BodyMesh(torch.cat([v + torch.tensor([-0.09, 0.0, 0.0]), v + torch.tensor([0.09, 0.0, 0.0])]),
                    torch.cat([f, f + len(v)]))
    m, n = 3, 16
    x = torch.zeros(1, m, n, 3)
    x[0, :, :, 2] = torch.tensor([-0.004, 0.0, 0.004])[:, None]
    x[0, :, :, 1] = 0.15 - 0.02 * torch.arange(n)[None, :]
    rigid = x.clone()
    pushed = keep_out_of_body(x, rigid, body, turns=0, final_depth=0.0)
    assert float(hair_body_signed_distance(pushed, body)[..., 2:].min()) < -0.005  # stuck in the lens
    turned = keep_out_of_body(x, rigid, body, final_depth=0.0)
    assert float(hair_body_signed_distance(turned, body)[..., 2:].min()) > 0
    torch.testing.assert_close(_segment_lengths(turned), _segment_lengths(rigid), atol=1e-5, rtol=0)
    torch.testing.assert_close(turned[:, :, :2], rigid[:, :, :2])


def test_constants_fitted_by_length_follow_the_anchors():
    """`fit_constants_by_length`: strands of each anchor's length get its G, beta and tension
    factor; a strand between two anchors gets constants between theirs; bad anchors are refused."""
    from hairwarp.models.inertial import fit_constants_by_length

    step = InertialStep(InertialConfig(coupling="chain"))
    anchors = [(0.18, 0.99, 0.98, 0.5), (0.3, 0.99, 0.95, 1.0), (0.55, 0.985, 0.9, 2.0)]
    error = fit_constants_by_length(step, anchors)
    assert error < 0.2
    lengths = [0.18, 0.3, 0.55, 0.42]
    rigid = torch.zeros(len(lengths), 40, 3)
    for i, length in enumerate(lengths):
        rigid[i, :, 1] = -torch.linspace(0.0, length, 40)
    raw = step.net(vertex_features(rigid)).detach()  # (M, N, 3): logit G, logit beta, log tension
    beta = torch.sigmoid(raw[:, 20, 1])
    gate = torch.sigmoid(raw[:, 20, 0])
    tension = torch.exp(raw[:, 20, 2])
    for i, (_, g, b, t) in enumerate(anchors):
        assert abs(float(beta[i]) - b) < 0.01 and abs(float(gate[i]) - g) < 0.003
        assert abs(float(tension[i]) / t - 1) < 0.15
    assert 0.9 < float(beta[3]) < 0.95 and 1.0 < float(tension[3]) < 2.0
    with pytest.raises(ValueError, match="anchors"):
        fit_constants_by_length(step, [])
    with pytest.raises(ValueError, match="anchors"):
        fit_constants_by_length(step, [(0.3, 1.0, 0.9, 1.0)])


def test_pinch_turns_stop_when_no_strand_is_freed_further():
    """`_TurnProgress`: the turns go on while a round turned some strand and the first vertices
    inside moved further along the strands within `KEEP_OUT_TURN_PATIENCE` rounds; once stopped
    they stay stopped, and a reset starts them again."""
    from hairwarp.methods.keep_out import KEEP_OUT_TURN_PATIENCE, _TurnProgress

    progress = _TurnProgress(torch.device("cpu"))
    progress.reset()
    go_on = []
    for turned, reach in [(3, 10), (3, 12), (2, 12), (2, 13), (2, 13), (2, 11), (2, 20), (1, 30)]:
        progress.update(torch.tensor(turned), torch.tensor(reach))
        go_on.append(bool(progress.go_on))
    assert KEEP_OUT_TURN_PATIENCE == 2
    # 10, 12 and 13 are new highs (12 again: one round without); 13 again and 11 are two rounds
    # without one: stopped, and a later high does not restart it
    assert go_on == [True, True, True, True, True, False, False, False]
    progress.reset()
    progress.update(torch.tensor(0), torch.tensor(5))
    assert not bool(progress.go_on)  # a round that turned nothing stops the turns


def test_pinch_turns_never_leave_a_strand_with_more_vertices_inside():
    """`_turn_out_of_pinches` on strands hanging in every direction through two overlapping spheres:
    a strand the turns do not free of some of its vertices inside keeps its place bit for bit, so
    no strand ends with more vertices inside than it had."""
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.methods.keep_out import KEEP_OUT_MARGIN, _turn_out_of_pinches

    v, f = icosphere(8, radius=0.1)
    v, f = torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32)
    body = BodyMesh(torch.cat([v + torch.tensor([-0.09, 0.0, 0.0]), v + torch.tensor([0.09, 0.0, 0.0])]),
                    torch.cat([f, f + len(v)]))
    g = torch.Generator().manual_seed(3)
    m, n = 48, 24
    roots = torch.tensor([0.0, 0.16, 0.0]) + 0.04 * (torch.rand(m, 3, generator=g) - 0.5)
    heading = torch.nn.functional.normalize(torch.randn(m, 3, generator=g) * torch.tensor([1.0, 0.3, 1.0])
                                            + torch.tensor([0.0, -1.0, 0.0]), dim=-1)
    bend = 0.02 * torch.randn(m, n, 3, generator=g).cumsum(1)
    x = (roots[:, None] + 0.012 * torch.arange(n)[None, :, None] * heading[:, None] + bend)[None]
    from hairwarp.ops import follow_the_leader

    rigid = x.clone()
    x = follow_the_leader(rigid, x, check=False)

    def inside(y):
        return (hair_body_signed_distance(y, body)[..., NUM_FIXED_VERTICES:] < 0).sum(-1)[0]

    before = inside(x)
    assert int((before > 0).sum()) >= 20  # most strands start inside
    turned = _turn_out_of_pinches(x, rigid, body, margin=KEEP_OUT_MARGIN, rounds=12)
    after = inside(turned)
    assert bool((after <= before).all())
    kept = after == before
    assert torch.equal(turned[0, kept], x[0, kept]) and int(kept.sum()) < m
    assert int((after < before).sum()) >= 5


def _keep_out_in_torch(x, rigid, body, *, margin, passes, trigger, turns, final_depth):
    """Oracle: the body pass as it was written before its rounds became one kernel launch each
    (`hair_body_keep_out_push`): plain torch over `hair_body_signed_distance_and_normal`, a host
    read per round. Returns (positions, the number of rounds that pushed)."""
    from hairwarp.methods.keep_out import _query_cap, _turn_out_of_pinches
    from hairwarp.ops import hair_body_signed_distance_and_normal

    for k in range(passes):
        distance, direction = hair_body_signed_distance_and_normal(x, body, max_distance=_query_cap(margin))
        near = distance < trigger * margin
        near[..., :2] = False
        if not bool(near.any()):
            return x, k
        push = torch.where(near, margin - distance, torch.zeros_like(distance))
        x = follow_the_leader(rigid, x + push[..., None] * direction, check=False)
    x = _turn_out_of_pinches(x, rigid, body, margin=margin, rounds=turns)
    distance, direction = hair_body_signed_distance_and_normal(x, body, max_distance=_query_cap(margin))
    shallow = (distance < 0.0) & (distance > -final_depth * margin)
    shallow[..., :2] = False
    push = torch.where(shallow, margin - distance, torch.zeros_like(distance))
    return x + push[..., None] * direction, passes


def _keep_out_scenes(device, dtype):
    """(name, hair, body) scenes with vertices deep inside, near the surface and far outside:
    one sphere (strands hanging through it or grazing its side, arcs along it within the trigger,
    a strand clear of it), and two overlapping spheres (strands in the lens they share: the pinch turns,
    and pieces of the crossing signed by the winding number)."""
    v, f = icosphere(8, radius=0.1)
    v, f = torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32)
    n = 16
    offsets = torch.tensor([-0.04, -0.01, 0.02, 0.0998, 0.1002, 0.1004, 0.1006, 0.13])
    sphere = torch.zeros(1, len(offsets), n, 3, dtype=dtype)
    sphere[0, :, :, 0] = offsets[:, None].to(dtype)
    sphere[0, :, :, 1] = 0.14 - 0.02 * torch.arange(n, dtype=dtype)[None, :]
    sphere[0, :, :, 2] = 0.003 * torch.arange(len(offsets), dtype=dtype)[:, None]
    # Arcs along the sphere 0.1, 0.3 and 0.7 mm off it (the faceted mesh lies up to ~0.3 mm
    # inside the sphere): most of their vertices within the trigger, outside.
    angle = torch.linspace(1.1 * math.pi, 1.9 * math.pi, n, dtype=torch.float64)
    ring = torch.sqrt((0.1 + torch.tensor([1e-4, 3e-4, 7e-4], dtype=torch.float64)) ** 2 - 0.03**2)[:, None]
    arcs = torch.stack([ring * torch.cos(angle), ring * torch.sin(angle), torch.full_like(ring * angle, 0.03)], -1)
    sphere = torch.cat([sphere, arcs[None].to(dtype)], 1)
    lens = torch.zeros(1, 3, n, 3, dtype=dtype)
    lens[0, :, :, 2] = torch.tensor([-0.004, 0.0, 0.004], dtype=dtype)[:, None]
    lens[0, :, :, 1] = 0.15 - 0.02 * torch.arange(n, dtype=dtype)[None, :]
    two = BodyMesh(torch.cat([v + torch.tensor([-0.09, 0.0, 0.0]), v + torch.tensor([0.09, 0.0, 0.0])]).to(device),
                   torch.cat([f, f + len(v)]).to(device))
    return [("sphere", sphere.to(device), BodyMesh(v.to(device), f.to(device))), ("two spheres", lens.to(device), two)]


# The body pass's settings the oracle is compared under: the default (the rounds stop early on
# the sphere, run out in the lens), one round (it runs out: the turns and the final push), two
# rounds with every depth pushed at the end, and a trigger at the whole margin.
_KEEP_OUT_CASES = [{}, dict(passes=1, turns=0), dict(passes=2, turns=2, final_depth=math.inf), dict(trigger=1.0)]
# Float32 positions of metres: the kernels and the oracle run the same float32 operations (a
# fused multiply-add on a GPU can round the push's last bit differently).
_KEEP_OUT_ATOL = 1e-6  # [m]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_keep_out_of_body_equals_the_plain_torch_rounds(device, dtype):
    """`keep_out_of_body` (a push kernel per round, `hair_body_keep_out_push`) against the same
    pass in plain torch: equal positions and equal numbers of rounds, in every setting; the
    scenes push in some rounds, stop early in some cases and run out in others."""
    from hairwarp.methods.keep_out import (KEEP_OUT_FINAL_DEPTH, KEEP_OUT_MARGIN, KEEP_OUT_PASSES, KEEP_OUT_TRIGGER,
                                           KEEP_OUT_TURNS, keep_out_of_body, pushed_out_of_body)

    defaults = dict(margin=KEEP_OUT_MARGIN, passes=KEEP_OUT_PASSES, trigger=KEEP_OUT_TRIGGER, turns=KEEP_OUT_TURNS,
                    final_depth=KEEP_OUT_FINAL_DEPTH)
    outcomes = set()
    for name, x, body in _keep_out_scenes(device, dtype):
        rigid = x.clone()
        for case in _KEEP_OUT_CASES:
            settings = {**defaults, **case}
            expected, expected_rounds = _keep_out_in_torch(x, rigid, body, **settings)
            out = keep_out_of_body(x, rigid, body, **case)
            _, rounds = pushed_out_of_body(x, rigid, body, margin=settings["margin"], passes=settings["passes"],
                                           trigger=settings["trigger"])
            assert rounds == expected_rounds, (name, case)
            torch.testing.assert_close(out, expected, rtol=0, atol=_KEEP_OUT_ATOL, msg=lambda m: f"{name} {case}: {m}")
            assert out.dtype == x.dtype and out.shape == x.shape
            outcomes.add("stopped early" if rounds < settings["passes"] else "ran out")
            assert rounds >= 1 and float((out - x).abs().max()) > 1e-3  # no comparison of nothing
    assert outcomes == {"stopped early", "ran out"}


def _pass_settings(case: dict) -> dict:
    from hairwarp.methods.keep_out import (KEEP_OUT_FINAL_DEPTH, KEEP_OUT_MARGIN, KEEP_OUT_PASSES, KEEP_OUT_TRIGGER,
                                           KEEP_OUT_TURNS)

    settings = {**dict(margin=KEEP_OUT_MARGIN, passes=KEEP_OUT_PASSES, trigger=KEEP_OUT_TRIGGER,
                       turns=KEEP_OUT_TURNS, final_depth=KEEP_OUT_FINAL_DEPTH), **case}
    return {k: (int(v) if k in ("passes", "turns") else float(v)) for k, v in settings.items()}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_replayed_keep_out_equals_the_eager_pass(dtype):
    """`_ReplayedPass`, the pass in fixed work for CUDA graphs (every round launched, the turns in
    fixed slots), called plainly on the CPU: the eager pass's positions bit for bit, in every
    setting, twice over the same buffers, also where a frame has more stuck strands than its
    slots (they grow)."""
    from hairwarp.methods.keep_out import _ReplayedPass, keep_out_of_body

    grew = 0
    for name, x, body in _keep_out_scenes("cpu", dtype):
        for case in _KEEP_OUT_CASES:
            eager = keep_out_of_body(x, x.clone(), body, **case)
            replayed = _ReplayedPass(x, x.clone(), body, _pass_settings(case))
            replayed.width = 1
            for _ in range(2):
                assert torch.equal(replayed(x, x.clone()), eager), (name, case)
            grew += replayed.width > 1
            assert float((eager - x).abs().max()) > 1e-3
    assert grew >= 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_keep_out_replayed_from_cuda_graphs_equals_the_eager_launches():
    """At batch 1 on CUDA the pass replays its graphs after its first eager calls on the same body:
    the eager launches' positions bit for bit, in every setting (the rounds stopping early and
    running out, the turns), on a body moved in place (`BodyMesh.update`) too."""
    from hairwarp.methods import keep_out

    for name, x, body in _keep_out_scenes("cuda", torch.float32):
        for case in _KEEP_OUT_CASES:
            keep_out.KEEP_OUT_GRAPHS = False
            try:
                eager = keep_out.keep_out_of_body(x, x.clone(), body, **case)
            finally:
                keep_out.KEEP_OUT_GRAPHS = True
            for k in range(keep_out.KEEP_OUT_EAGER_CALLS + 2):
                torch.testing.assert_close(keep_out.keep_out_of_body(x, x.clone(), body, **case), eager, rtol=0, atol=0,
                                           msg=lambda m: f"{name} {case}: {m}")
                replayed = [v for v in body.__dict__["_replayed_keep_out"].values() if isinstance(v, keep_out._ReplayedPass)]
                assert len(replayed) == (k >= keep_out.KEEP_OUT_EAGER_CALLS)
        vertices = body.vertices.clone() if hasattr(body, "vertices") else None
        if vertices is not None:
            body.update(vertices + torch.tensor([0.0, 0.002, 0.0], device="cuda"))
            keep_out.KEEP_OUT_GRAPHS = False
            try:
                eager = keep_out.keep_out_of_body(x, x.clone(), body)
            finally:
                keep_out.KEEP_OUT_GRAPHS = True
            for _ in range(keep_out.KEEP_OUT_EAGER_CALLS + 1):
                torch.testing.assert_close(keep_out.keep_out_of_body(x, x.clone(), body), eager, rtol=0, atol=0)


def test_keep_out_of_body_checks_its_arguments_once():
    from hairwarp.methods.keep_out import keep_out_of_body

    _, x, body = _keep_out_scenes("cpu", torch.float32)[0]
    with pytest.raises(ValueError, match="x: expected shape"):
        keep_out_of_body(x[0], x[0], body)
    with pytest.raises(ValueError, match="x: contains NaN"):
        keep_out_of_body(x + float("nan"), x, body)
    with pytest.raises(ValueError, match="rigid: expected shape"):
        keep_out_of_body(x, x[:, :2], body)
    with pytest.raises(ValueError, match="rigid: expected dtype"):
        keep_out_of_body(x, x.double(), body)
    with pytest.raises(ValueError, match="body: expected a BodyMesh"):
        keep_out_of_body(x, x, None)
    with pytest.raises(ValueError, match="margin"):
        keep_out_of_body(x, x, body, margin=-1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the CUDA path (pinned count reads) needs a CUDA device")
def test_keep_out_of_body_on_cuda_equals_the_cpu_on_a_side_stream():
    """The CUDA rounds (the count copied to pinned memory behind each push, read after the
    projection is queued) give the CPU's positions and rounds, also on a stream of their own.

    On one device the default stream and a side stream must agree to the bit, in both scenes.
    The CPU is compared on the sphere moved 1.3 mm off its mirror plane z = 0: a strand in that
    plane has two closest faces, one on each side, and the CPU's and the GPU's tree walks may pick
    either (pushed +2.2 mm or -2.2 mm in z, both right). The two spheres' pinch turns choose among
    near-equal turns (float32 against float64 on the CPU alone: 9.7 mm apart once moved off the
    mirror plane x = 0), so there each device is held to the plain torch rounds on its own
    device instead (`test_keep_out_of_body_equals_the_plain_torch_rounds`).
    """
    from hairwarp.methods.keep_out import keep_out_of_body, pushed_out_of_body

    off_plane = torch.tensor([0.0, 0.0, 0.0013])
    for (name, x, body), (_, x_cuda, body_cuda) in zip(_keep_out_scenes("cpu", torch.float32),
                                                        _keep_out_scenes("cuda", torch.float32)):
        for case in _KEEP_OUT_CASES:
            x_off, x_cuda_off = x + off_plane, x_cuda + off_plane.cuda()
            on_default = keep_out_of_body(x_cuda, x_cuda.clone(), body_cuda, **case)
            stream = torch.cuda.Stream()
            stream.wait_stream(torch.cuda.current_stream())  # the inputs, made on the default stream
            with torch.cuda.stream(stream):
                out = keep_out_of_body(x_cuda, x_cuda.clone(), body_cuda, **case)
                out_off = keep_out_of_body(x_cuda_off, x_cuda_off.clone(), body_cuda, **case)
            stream.synchronize()
            torch.testing.assert_close(out, on_default, rtol=0, atol=0, msg=lambda m: f"{name} {case}: {m}")
            if name != "sphere":
                continue
            expected = keep_out_of_body(x_off, x_off.clone(), body, **case)
            torch.testing.assert_close(out_off.cpu(), expected, rtol=0, atol=1e-5,
                                       msg=lambda m: f"{name} {case}: {m}")
            assert float((out_off.cpu() - x_off).abs().max()) > 1e-3  # the pass pushed
            assert (pushed_out_of_body(x_cuda_off, x_cuda_off.clone(), body_cuda)[1]
                    == pushed_out_of_body(x_off, x_off.clone(), body)[1])


def test_network_methods_keep_out_of_the_body_by_default():
    """`MethodOptions.keep_out`, on by default: the shipped static network leaves long straight
    hair grown on the body at rest partly inside it (64 strands); through the body pass no vertex
    is, the rest lengths and roots are kept, and with the option off the drape is the network's
    own. A motion's frames (the paper's dynamic network) get the same pass."""
    import hairwarp as hw

    scene = hw.build_scene(hairstyle="long_straight", pose="rest", grow="body", strand_stride=16)
    raw = hw.drape(scene, method="static", keep_out=False)
    kept = hw.drape(scene, method="static")
    assert raw.metrics["penetration_percent"] > 0.1
    assert kept.metrics["penetration_percent"] == 0.0
    assert kept.metrics["length_change_percent"] < 1e-3 and kept.info["keep_out_ms"] > 0
    assert "keep_out_ms" not in raw.info
    torch.testing.assert_close(kept.positions[:, :2], raw.positions[:, :2])
    motion = hw.default_scene("long_straight", "nod", duration=0.1, strand_stride=16, num_vertices=40)
    moved = hw.simulate(motion, method="dynamic")
    assert max(moved.metrics["per_frame"]["penetration_percent"]) == 0.0


def test_the_inertial_drape_is_the_static_drape_through_the_body_pass():
    """On one pose the step rests at its equilibrium: the static network's drape, kept out of the
    body as a motion's frames are (the raw network leaves this clean placement partly inside)."""
    import hairwarp as hw

    scene = hw.build_scene(hairstyle="long_straight", pose="rest", grow="body", strand_stride=16)
    inertial = hw.drape(scene, method="inertial")
    torch.testing.assert_close(inertial.positions, hw.drape(scene, method="static").positions)
    assert inertial.metrics["penetration_percent"] == 0.0
    assert hw.drape(scene, method="static", keep_out=False).metrics["penetration_percent"] > 0.1


@pytest.mark.parametrize("body_pass", ["shipped", "after"])
def test_the_inertial_method_rolls_out_chunk_by_chunk_as_one_sequence(body_pass, tmp_path):
    """`InertialMethod.simulate` runs a chunk of frames at a time (equilibrium, rollout going on
    from the chunk before, body pass): the same positions bit for bit as the whole motion at once.
    The shipped step (`keep_out_equilibrium`, `keep_out_state`): the equilibrium passed chunk by
    chunk, then rolled out at once with each frame's state passed on the motion's moving body. A
    step with neither: the whole equilibrium rolled out at once, then passed chunk by chunk."""
    from dataclasses import replace

    import hairwarp as hw
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import InertialMethod, _FrameBodyPass, _moving_body, load_inertial_step
    from hairwarp.methods.keep_out import keep_out_of_body_in_frames
    from hairwarp.scene.scene import FRAME_CHUNK

    scene = hw.default_scene("bob", "head_turn", duration=0.4, strand_stride=32)
    frames = scene.frames()
    assert frames.num_frames > FRAME_CHUNK  # two chunks at least
    step = load_inertial_step(None, frames.rigid.positions.device)
    assert step.config.keep_out_state and step.config.keep_out_equilibrium
    checkpoint = None
    if body_pass == "after":
        step = InertialStep(replace(step.config, keep_out_state=False, keep_out_equilibrium=False))
        checkpoint = str(tmp_path / "after.pt")
        save_checkpoint(checkpoint, step)
    method = InertialMethod(MethodOptions(checkpoint=checkpoint))
    out = method.simulate(frames)
    rigid = frames.rigid.positions
    with torch.no_grad():
        target = method.equilibrium.simulate(frames).positions.to(rigid.dtype)
        # The shipped step's settle (`InertialConfig.settle_steps`; its own test replays it).
        assert step.config.settle_steps > 0
        settle, _ = method._settled_offset(frames, step.config, step.config.settle_steps)
        target = target + torch.einsum("tij,mnj->tmni", frames.posed.head_transform[:, :3, :3].to(rigid.dtype), settle)
        if body_pass == "after":
            whole = keep_out_of_body_in_frames(step.rollout(target, rigid), frames)
        else:
            whole = step.rollout(keep_out_of_body_in_frames(target, frames), rigid,
                                 project=_FrameBodyPass(frames, _moving_body(frames)))
    assert torch.equal(out.positions, whole)
    assert len(out.info["chunks"]) >= 2 and out.info["step_ms"] > 0 and out.time_ms > out.info["step_ms"]


def test_random_head_moves_are_seeded_and_bounded():
    from hairwarp.scene.motion import random_head_moves

    a, b, c = random_head_moves(3), random_head_moves(3), random_head_moves(4)
    assert a.num_frames == 91 and a.name == "head_moves3"
    torch.testing.assert_close(a.poses, b.poses)
    assert not torch.equal(a.poses, c.poses)
    assert float(a.poses.abs().max()) < math.radians(75)
    speed = np.abs(np.diff(a.poses.numpy(), axis=0)).max() * a.fps
    assert speed > 1.0  # quick moves, not a still pose


# --------------------------------------------------------------------------- training on the physics
@pytest.fixture(scope="module")
def toy_run(tmp_path_factory):
    """A trainer on the one-clip toy (the clip also its held-out curve), trained 60 steps, saved."""
    from hairwarp.training.inertial import ClipSpec, InertialTrainer, InertialTrainingConfig

    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("inertial_run")
    clip = ClipSpec("medium_wavy", "head_moves", 2, 0.0, 0.8)
    config = InertialTrainingConfig(clips=[clip], held_out=[clip], steps=60, eval_every=30, learning_rate=2e-2,
                                    **TOY)
    trainer = InertialTrainer(config, out=out, progress=False)
    untrained = trainer.evaluate()
    trainer.train()
    return out, trainer, untrained


def test_a_rollout_trained_step_swings_where_the_static_network_cannot(toy_run):
    _, trainer, untrained = toy_run
    clip = trainer.held_out_clips[0]
    with torch.no_grad():
        x = trainer.model.rollout(clip["equilibrium"], clip["rigid"])
    ours = motion_fidelity(x, clip["physics"], clip["rigid"])
    static = motion_fidelity(clip["equilibrium"], clip["physics"], clip["rigid"])
    assert ours["swing_correlation"] > static["swing_correlation"] + 0.3, (ours, static)
    assert ours["swing_correlation"] > 0.6
    key = clip["spec"].key
    assert trainer.evaluate()[key]["swing_correlation"] >= untrained[key]["swing_correlation"] - 1e-6


def test_the_learning_curve_holds_the_motion_metrics_and_resume_continues(toy_run):
    from hairwarp.training.inertial import InertialTrainer, read_log

    out, trainer, _ = toy_run
    log = read_log(out)
    assert [r["step"] for r in log] == list(range(1, 61))
    points = [r for r in log if "held_out" in r]
    assert [r["step"] for r in points] == [30, 60]
    metrics = next(iter(points[-1]["held_out"].values()))
    for name in ("mean_distance_mm", "swing_correlation", "swing_amplitude_ratio", "equilibrium_swing_correlation"):
        assert name in metrics
    clips = os.listdir(os.path.join(out, "clips"))
    stamp = {c: os.path.getmtime(os.path.join(out, "clips", c)) for c in clips}

    resumed = InertialTrainer(out=out, resume=out, progress=False)
    assert resumed.step_count == 60
    torch.testing.assert_close(resumed.model.net[0].weight, trainer.model.net[0].weight)
    resumed.config.steps = 65
    resumed.train()
    log = read_log(out)
    assert [r["step"] for r in log][-5:] == [61, 62, 63, 64, 65]
    assert {c: os.path.getmtime(os.path.join(out, "clips", c)) for c in clips} == stamp  # not simulated again
    with pytest.raises(ValueError, match="resume"):
        InertialTrainer(resume=os.path.join(out, "nothing_here"))


def test_the_method_runs_a_motion_and_refuses_another_frame_rate(toy_run, tmp_path):
    import hairwarp as hw
    from hairwarp.methods import MethodOptions, make
    from hairwarp.scene.motion import resample_motion

    out, trainer, _ = toy_run
    scene = hw.default_scene("bob", "nod", strand_stride=64, num_vertices=12)
    scene = type(scene)(body=scene.body, scalp=scene.scalp, hairstyle=scene.hairstyle,
                        motion=scene.motion.replace(poses=scene.motion.poses[:20], trans=scene.motion.trans[:20]))
    ckpt = os.path.join(out, "checkpoint.pt")
    result = hw.simulate(scene, method="inertial", checkpoint=ckpt)
    assert result.positions.shape == (20, scene.hairstyle.num_strands, 12, 3)
    assert result.metrics["penetration_percent"] == 0.0
    assert result.metrics["length_change_percent"] < 0.01
    shipped = hw.simulate(scene, method="inertial")  # the step shipped in hairwarp/assets
    assert shipped.positions.shape == result.positions.shape and shipped.metrics["penetration_percent"] == 0.0
    slow = type(scene)(body=scene.body, scalp=scene.scalp, hairstyle=scene.hairstyle,
                       motion=resample_motion(scene.motion, 30.0))
    with pytest.raises(ValueError, match="resample"):
        make("inertial", MethodOptions(checkpoint=ckpt)).simulate(slow.frames())
    with pytest.raises(ValueError, match="no such file"):
        make("inertial", MethodOptions(checkpoint=str(tmp_path / "missing.pt"))).simulate(scene.frames())
    other = tmp_path / "static.pt"
    from hairwarp.models import StaticConfig, StaticNetwork

    save_checkpoint(other, StaticNetwork(StaticConfig(latent_dim=8, model_dim=16, num_heads=2, ffn_dim=16,
                                                      num_vertices=12)))
    with pytest.raises(ValueError, match="not an inertial step"):
        make("inertial", MethodOptions(checkpoint=str(other))).simulate(scene.frames())


def test_the_chain_operator_is_the_inverse_of_the_tension_laplacian():
    """(I + D + L_w)^-1 against a float64 matrix written entry by entry; w = 0 is the per-vertex gate."""
    torch.manual_seed(1)
    gate_logit, tension = torch.randn(2, 5, dtype=torch.float64), torch.rand(2, 5, dtype=torch.float64) * 30
    a = chain_operator(gate_logit, tension)
    for m in range(2):
        k = torch.zeros(5, 5, dtype=torch.float64)
        for i in range(5):
            k[i, i] += 1.0 + math.exp(-float(gate_logit[m, i])) + float(tension[m, i])  # the segment above
            if i + 1 < 5:  # the segment below (vertex i + 1's above) couples i and i + 1
                w = float(tension[m, i + 1])
                k[i, i] += w
                k[i, i + 1] -= w
                k[i + 1, i] -= w
        torch.testing.assert_close(a[m] @ k, torch.eye(5, dtype=torch.float64), atol=1e-10, rtol=0)
    torch.testing.assert_close(chain_operator(gate_logit, torch.zeros_like(tension)),
                               torch.diag_embed(torch.sigmoid(gate_logit)), atol=1e-12, rtol=0)
    # a hanging strand's tension: h^2 g (L - s) / l^2 over each segment
    w = hanging_chain_tension(_hanging(1, 6), 60.0)
    below = torch.tensor([0.08, 0.06, 0.04, 0.02], dtype=torch.float64)
    torch.testing.assert_close(w[0], 9.81 * below / (3600 * 0.02**2))


def test_a_chain_swings_through_its_equilibrium_after_the_head_stops():
    """The head moves 10 cm along x in a sixth of a second and stops: the chain's tip first trails,
    then swings past the rigid placement (its equilibrium) and back; the untrained step's pull
    stays stable, with the rest lengths kept."""
    rest = _hanging(1, 40)
    rest[..., 1] *= 0.25  # 5 mm segments: a 0.2 m strand
    t = torch.arange(60, dtype=torch.float64)
    head = torch.clamp(t * 0.01, max=0.1)
    rigid = rest[None] + torch.stack([head, 0 * t, 0 * t], dim=-1)[:, None, None, :]
    step = InertialStep(InertialConfig(coupling="chain")).double()
    with torch.no_grad():
        out = step.rollout(rigid.clone(), rigid)
    lag = (out[:, 0, -1, 0] - rigid[:, 0, -1, 0]).numpy()
    assert lag[:10].min() < -0.01  # trails while the head moves
    assert lag[10:].max() > 0.01  # swings past after it stops
    assert np.abs(lag).max() < 0.1  # and stays bounded
    torch.testing.assert_close(_segment_lengths(out), _segment_lengths(rigid), atol=1e-9, rtol=0)


def test_a_capped_projection_gain_keeps_the_rollout_and_bounds_its_gradient():
    """Training's `projection_max_gain`: the same positions; uncapped in effect (a cap no gain
    reaches) the exact gradient; capped low, another one (its bound: tests/test_strand_projection.py)."""
    rest = _hanging(2, 6)
    t = torch.arange(5, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.03 * t**2, 0.01 * t, 0 * t], dim=-1)[:, None, None, :]
    step = InertialStep(InertialConfig(coupling="chain")).double()
    grads, outs = {}, {}
    for cap in (None, 1e9, 0.05):
        step.projection_max_gain = cap
        equilibrium = rigid.clone().requires_grad_(True)
        x = step.rollout(equilibrium, rigid)
        x.square().sum().backward()
        grads[cap], outs[cap] = equilibrium.grad, x.detach()
    torch.testing.assert_close(outs[1e9], outs[None], atol=0, rtol=0)
    torch.testing.assert_close(outs[0.05], outs[None], atol=0, rtol=0)
    torch.testing.assert_close(grads[1e9], grads[None], atol=1e-12, rtol=1e-9)
    assert not torch.allclose(grads[0.05], grads[None])  # the cap binds: another gradient


def test_the_step_at_rest_keeps_a_still_hairstyle_still():
    rest = _hanging(2, 8, torch.float32)
    rigid = rest.expand(4, -1, -1, -1).clone()
    x = follow_the_leader(rigid, rigid + 0.001)
    step = InertialStep()
    out = step.rollout(x, rigid)
    torch.testing.assert_close(out, x, atol=1e-6, rtol=0)


def test_relative_damping_carries_hair_at_a_steady_speed_without_drag():
    rest = _hanging(2, 6)
    t = torch.arange(240, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.01 * t, 0 * t, 0 * t], dim=-1)[:, None, None, :]  # 0.6 m/s along x
    lag = {}
    for damping in ("relative", "absolute"):
        step = InertialStep(InertialConfig(damping=damping)).double()
        with torch.no_grad():
            out = step.rollout(rigid.clone(), rigid)
        lag[damping] = float((out[-1, :, -1] - rigid[-1, :, -1]).norm(dim=-1).max())
    assert lag["relative"] < 1e-4 < 1e-3 < lag["absolute"], lag


def test_the_optimum_equilibrium_is_each_frames_static_drape():
    """`equilibrium="optimum"` gives each clip frame its static optimum (the physics' drape of the
    frame): no higher in static energy than the rigid placement, and not the static network's."""
    from hairwarp.energy import total_energy
    from hairwarp.training.inertial import ClipSpec, clip_scene, clip_trajectories

    torch.set_num_threads(1)
    scene = clip_scene(ClipSpec("bob", "head_moves", 5, 0.0, 0.05), **TOY)
    optimum = clip_trajectories(scene, "optimum")
    static = clip_trajectories(scene, "static")
    assert optimum["equilibrium"].shape == optimum["rigid"].shape == static["equilibrium"].shape
    assert torch.equal(optimum["physics"], static["physics"])  # the same clip either way
    frames = scene.frames()
    with torch.no_grad():
        e_opt = total_energy(optimum["equilibrium"], frames.inputs).total
        e_rigid = total_energy(optimum["rigid"], frames.inputs).total
    assert e_opt.shape == (optimum["rigid"].shape[0],)
    assert bool((e_opt <= e_rigid).all()), (e_opt, e_rigid)
    assert float((optimum["equilibrium"] - static["equilibrium"]).norm(dim=-1).max()) > 1e-4


def test_limited_change_caps_each_strands_mean_and_keeps_small_ones():
    change = torch.zeros(3, 6, 3, dtype=torch.float64)
    change[0, 2:, 0] = 0.004  # mean 4 mm: scaled to the limit
    change[1, 2:, 1] = 0.0005  # 0.5 mm: kept
    limited = limited_change(change, 0.001)
    sizes = limited[:, 2:].norm(dim=-1).mean(dim=-1)
    assert math.isclose(float(sizes[0]), 0.001, rel_tol=1e-12)
    torch.testing.assert_close(limited[1:], change[1:], rtol=0, atol=0)
    torch.testing.assert_close(limited[0] / 0.25, change[0], rtol=1e-12, atol=0)  # direction and shape kept


def _flipping_equilibrium(frames=30, flip=range(8, 12)):
    """4 hanging strands, the head still; their equilibrium swings 0.1 m sideways at the tip for the
    frames of `flip` (a static network's drape jumping to the other side of a shoulder and back)."""
    rest = _hanging(4, 8)
    rigid = rest.expand(frames, -1, -1, -1).clone()
    tilt = torch.zeros_like(rest)
    tilt[:, :, 0] = 0.1 * torch.linspace(0, 1, 8, dtype=rest.dtype)
    jumped = torch.zeros(frames, 1, 1, 1, dtype=rest.dtype)
    jumped[list(flip)] = 1.0
    return follow_the_leader(rigid, rigid + jumped * tilt), rigid


def test_a_limited_equilibrium_speed_stops_a_jumping_equilibrium_from_flinging_the_strand():
    equilibrium, rigid = _flipping_equilibrium()
    swing = {}
    for speed in (None, 1e6, 0.06):
        step = InertialStep(InertialConfig(coupling="chain", equilibrium_speed=speed)).double()
        with torch.no_grad():
            out = step.rollout(equilibrium, rigid)
        swing[speed] = out
    # A limit no jump reaches is no limit.
    torch.testing.assert_close(swing[1e6], swing[None], rtol=0, atol=1e-12)
    tip = {k: float((v[:, :, -1] - rigid[:, :, -1]).norm(dim=-1).max()) for k, v in swing.items()}
    # Unlimited, the step follows the jump (0.1 m at the tip); at 0.06 m/s (1 mm a frame for the
    # strand's mean) the four jumped frames move the target a few millimetres.
    assert tip[None] > 0.03, tip
    assert tip[0.06] < 0.25 * tip[None], tip
    assert tip[0.06] < 0.01, tip


def test_rollout_gradient_through_a_limited_equilibrium_matches_finite_differences():
    equilibrium, rigid = _flipping_equilibrium(frames=12, flip=range(4, 7))
    step = InertialStep(InertialConfig(coupling="chain", equilibrium_speed=0.06)).double()
    target = rigid + 0.01
    equilibrium = equilibrium.clone().requires_grad_(True)
    (step.rollout(equilibrium, rigid) - target).square().sum().backward()
    analytic = equilibrium.grad.clone()
    for index in [(5, 1, 7, 0), (4, 2, 4, 1), (6, 3, 6, 0)]:  # frames where the limit is active
        e = torch.zeros_like(equilibrium)
        e[index] = 1e-6
        with torch.no_grad():
            fd = ((step.rollout(equilibrium + e, rigid) - target).square().sum()
                  - (step.rollout(equilibrium - e, rigid) - target).square().sum()) / 2e-6
        assert math.isclose(float(analytic[index]), float(fd), rel_tol=1e-5, abs_tol=1e-10), index


def test_a_projection_in_the_rollout_acts_on_the_state_the_next_frames_read():
    """`rollout(project=...)`: each frame's result passes through the projection before it
    becomes the state. A floor under swinging strands: every frame stays above it, and the
    frames after a clamp start from the clamped state, so they differ from clamping a free
    rollout afterwards; the identity is no projection."""
    rest = _hanging(3, 8)
    t = torch.arange(40, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.05 * torch.sin(t / 4), 0.03 * torch.sin(t / 3), 0 * t], -1)[:, None, None, :]
    step = InertialStep(InertialConfig(coupling="chain", damping="relative", retention_init=0.98)).double()
    floor = -0.12

    def clamp(_, x):
        return torch.cat([x[..., :1], x[..., 1:2].clamp_min(floor), x[..., 2:]], dim=-1)

    with torch.no_grad():
        free = step.rollout(rigid.clone(), rigid)
        same = step.rollout(rigid.clone(), rigid, project=lambda _, x: x)
        floored = step.rollout(rigid.clone(), rigid, project=clamp)
    torch.testing.assert_close(same, free, rtol=0, atol=0)
    assert float(free[..., 1].min()) < floor - 0.001  # the free strands swing below the floor
    assert float(floored[..., 1].min()) >= floor
    assert float((floored - clamp(None, free)).abs().max()) > 1e-3  # the state, not the output, was clamped


def test_the_velocity_a_pushed_frame_hands_on_is_the_one_the_config_names():
    """`InertialConfig.keep_out_velocity`: with a floor as the pass, "pushed" reads the next
    velocity from the pushed states, "raw" from the step's own move, "tangential" from the
    step's own move less what ran against the push; each frame's x(t-2) checked against that
    rule in float64 numpy, frame by frame; without a push all three are one rollout."""
    rest = _hanging(3, 8)
    t = torch.arange(30, dtype=torch.float64)
    rigid = rest[None] + torch.stack([0.05 * torch.sin(t / 4), 0.03 * torch.sin(t / 3), 0 * t], -1)[:, None, None, :]
    floor = -0.12

    def clamp(_, x):
        return torch.cat([x[..., :1], x[..., 1:2].clamp_min(floor), x[..., 2:]], dim=-1)

    runs = {}
    for mode in KEEP_OUT_VELOCITIES:
        step = InertialStep(InertialConfig(coupling="chain", damping="relative", retention_init=0.98,
                                           keep_out_velocity=mode)).double()
        calls = []

        def record(t, x, calls=calls):
            calls.append(x.clone())
            return clamp(t, x)

        with torch.no_grad():
            runs[mode] = step.rollout(rigid.clone(), rigid, project=record)
            free = step.rollout(rigid.clone(), rigid, project=lambda _, x: x)
            if mode == "pushed":
                reference = free
            torch.testing.assert_close(free, reference, rtol=0, atol=0)
            # Replay frame by frame from the recorded raw results: x(t-2) by the rule, in numpy.
            out = runs[mode].numpy()
            raw = torch.stack(calls).numpy()
            prev = prev2 = rigid[0].numpy()
            for k in range(1, rigid.shape[0]):
                velocity, push = raw[k - 1] - prev, out[k - 1] - raw[k - 1]
                if mode == "pushed":
                    before = prev
                else:
                    length = np.linalg.norm(push, axis=-1, keepdims=True)
                    normal = np.where(length > 0, push / np.maximum(length, 1e-300), 0.0)
                    into = np.minimum((velocity * normal).sum(-1, keepdims=True), 0.0)
                    kept = velocity if mode == "raw" else velocity - into * normal
                    before = out[k - 1] - kept
                prev2, prev = before, out[k - 1]
                # the rollout's head velocity: how the rigid placement moved a frame before
                head = (rigid[k - 1] - rigid[k - 2])[None] if k > 1 else torch.zeros_like(rigid[:1])
                expected = step.step(rigid[k:k + 1].clone(), rigid[k:k + 1], torch.from_numpy(prev)[None],
                                     torch.from_numpy(prev2)[None], head, step.coefficients(rigid))[0]
                np.testing.assert_allclose(raw[k], expected.numpy(), rtol=0, atol=1e-12)
    assert float(runs["pushed"][..., 1].min()) >= floor
    for mode in ("raw", "tangential"):
        assert float((runs[mode] - runs["pushed"]).abs().max()) > 1e-4
    with pytest.raises(ValueError, match="keep_out_velocity"):
        InertialConfig(keep_out_velocity="elastic")


def test_the_method_keeps_the_state_out_of_the_body_when_its_step_asks(tmp_path):
    """`InertialConfig.keep_out_state`: the method's body pass inside the rollout; every frame is
    out of the body, at its rest lengths, and the result differs from the pass after the rollout."""
    import hairwarp as hw

    scene = hw.default_scene("long_straight", "nod", duration=0.25, strand_stride=64, num_vertices=24)
    paths = {}
    for keep_out_state in (False, True):
        step = InertialStep(InertialConfig(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95,
                                           tension_init=0.5, equilibrium_speed=0.12, keep_out_state=keep_out_state))
        paths[keep_out_state] = str(tmp_path / f"step_{keep_out_state}.pt")
        save_checkpoint(paths[keep_out_state], step)
    after = hw.simulate(scene, method="inertial", checkpoint=paths[False])
    inside = hw.simulate(scene, method="inertial", checkpoint=paths[True])
    assert max(inside.metrics["per_frame"]["penetration_percent"]) == 0.0
    assert inside.metrics["length_change_percent"] < 0.01
    assert float((inside.positions - after.positions).abs().max()) > 1e-4
    with pytest.raises(ValueError, match="keep_out_state"):
        InertialConfig(keep_out_state=1)


def test_the_state_pushed_on_the_moving_body_is_the_state_pushed_on_each_frames_own_body():
    """The method's state pass moves one body through the motion (`Scene.moving_body`) where each
    frame had a body of its own built: the same rollout to 1e-5 m, out of the body."""
    import hairwarp as hw
    from hairwarp.methods.inertial import _FrameBodyPass, _moving_body
    from hairwarp.methods.keep_out import keep_out_of_body

    scene = hw.default_scene("long_straight", "nod", duration=0.25, strand_stride=64, num_vertices=24)
    frames = scene.frames()
    rigid = frames.rigid.positions
    step = InertialStep(InertialConfig(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95,
                                       tension_init=0.5))
    # An equilibrium sagging 3 cm into the shoulders: the pass has work in every frame.
    sag = torch.zeros_like(rigid)
    sag[..., 2:, 1] = -0.03 * torch.linspace(0.0, 1.0, rigid.shape[2] - 2)
    with torch.no_grad():
        own = step.rollout(rigid + sag, rigid, project=lambda t, x: keep_out_of_body(
            x[None], rigid[t:t + 1], frames.select([t]).body_mesh)[0])
        moved = step.rollout(rigid + sag, rigid, project=_FrameBodyPass(frames, _moving_body(frames)))
        free = step.rollout(rigid + sag, rigid)
    torch.testing.assert_close(moved, own, rtol=0, atol=1e-5)
    assert float((free - own).abs().max()) > 1e-3  # the pass did move the state
    assert float(hair_body_signed_distance(moved[:, :, 2:], frames.body_mesh).min()) > -1e-4


def test_the_step_pulled_to_the_kept_out_equilibrium_starts_at_the_static_drape(tmp_path):
    """`InertialConfig.keep_out_equilibrium`: the rollout is pulled to the static network's drape
    through the body pass; at rest on the first frame the method returns what `drape` (the step at
    rest) returns for that frame, and the option is checked as a bool."""
    import hairwarp as hw
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import InertialMethod

    scene = hw.default_scene("long_straight", "nod", duration=0.25, strand_stride=64, num_vertices=24)
    frames = scene.frames()
    step = InertialStep(InertialConfig(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95,
                                       tension_init=0.5, equilibrium_speed=0.12, keep_out_state=True,
                                       keep_out_equilibrium=True))
    path = str(tmp_path / "step.pt")
    save_checkpoint(path, step)
    method = InertialMethod(MethodOptions(checkpoint=path))
    motion = method.simulate(frames).positions
    rest = method.drape(frames.select([0])).positions
    torch.testing.assert_close(motion[:1], rest, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="keep_out_equilibrium"):
        InertialConfig(keep_out_equilibrium="yes")


def test_the_settle_starts_the_motion_on_the_physics_steps_and_moves_every_equilibrium_with_the_head(tmp_path):
    """`InertialConfig.settle_steps`: the physics' steps from the first frame's equilibrium (the
    pose held, `settle_with_pose_held`) give S_0; every frame's equilibrium is moved by
    R_t R_0^T (S_0 - E_0), R_t the rotation of M_head, and the rollout starts at rest on S_0.
    Replayed by hand from the static network's drape and the solver."""
    import hairwarp as hw
    from hairwarp.methods import MethodOptions
    from hairwarp.methods.inertial import InertialMethod, keep_out_of_body
    from hairwarp.methods.optimizers import scene_energy_config
    from hairwarp.solvers.physics import PhysicsConfig, settle_with_pose_held, settling_solver

    scene = hw.default_scene("long_straight", "nod", duration=0.25, strand_stride=64, num_vertices=24)
    frames = scene.frames()
    config = InertialConfig(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95,
                            tension_init=0.5, equilibrium_speed=0.12, settle_steps=3, settle_momentum=0.8)
    step = InertialStep(config)
    path = str(tmp_path / "step.pt")
    save_checkpoint(path, step)
    method = InertialMethod(MethodOptions(checkpoint=path))
    result = method.simulate(frames)
    assert result.info["settle_ms"] > 0

    equilibrium = method.equilibrium.simulate(frames).positions.to(frames.rigid.positions.dtype)
    first = frames.select([0])
    inputs = first.inputs
    solver = settling_solver(inputs.rest_lengths, first.rigid.positions, inputs.scalp_normals, inputs.body,
                             scene_energy_config(method.options, first), PhysicsConfig())
    # The first frame's drape on its own (the network's frames in one batch agree to 1e-7 m, which
    # the settle's stopping rule may amplify to a different iteration count).
    start = method.equilibrium.drape(first).positions.to(equilibrium.dtype)
    settle_with_pose_held(solver, start, 3, PhysicsConfig().settle_tolerance, 0.8)
    settled = solver.prev.to(equilibrium.dtype)
    assert float((settled - start).norm(dim=-1).max()) > 1e-3  # the settle moved the hair
    rotations = frames.posed.head_transform[:, :3, :3].to(equilibrium.dtype)
    local = (settled - start)[0] @ rotations[0]
    moved = equilibrium + torch.einsum("tij,mnj->tmni", rotations, local)
    torch.testing.assert_close(moved[0], settled[0], rtol=0, atol=1e-6)
    with torch.no_grad():
        expected = keep_out_of_body(step.rollout(moved, frames.rigid.positions), frames.rigid.positions,
                                    frames.body_mesh)
    torch.testing.assert_close(result.positions, expected, rtol=0, atol=1e-5)
    # `MethodOptions.settle` overrides the step's count: 0, the rollout on the network's drapes.
    unsettled = InertialMethod(MethodOptions(checkpoint=path, settle=0)).simulate(frames)
    assert "settle_ms" not in unsettled.info
    with torch.no_grad():
        plain = keep_out_of_body(step.rollout(equilibrium, frames.rigid.positions), frames.rigid.positions,
                                 frames.body_mesh)
    torch.testing.assert_close(unsettled.positions, plain, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="settle"):
        InertialMethod(MethodOptions(checkpoint=path, settle=-1)).simulate(frames)
    for bad in ({"settle_steps": -1}, {"settle_steps": 2.5}, {"settle_momentum": 0.0}, {"settle_momentum": 1.5}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            InertialConfig(**bad)


def test_the_chain_operators_bending_is_the_clamped_second_difference_penalty():
    """`chain_operator(..., bending=b)` against a float64 matrix with b sum (d[c-1] - 2 d[c] +
    d[c+1])^2 written term by term (the two fixed vertices' offsets 0); a kick at one vertex
    relaxes smoother with it; b = 0 is the chain without bending."""
    torch.manual_seed(2)
    n = 6
    gate_logit, tension = torch.randn(1, n, dtype=torch.float64), torch.rand(1, n, dtype=torch.float64) * 30
    b = 7.0
    k = torch.linalg.inv(chain_operator(gate_logit, tension))[0]
    for c in range(1, n + 1):  # centre c of the strand; free vertex j is strand vertex j + 2
        terms = {c - 1: 1.0, c: -2.0, c + 1: 1.0}
        free = {v - 2: coef for v, coef in terms.items() if v >= 2}
        for i, a in free.items():
            for j, a2 in free.items():
                k[i, j] += b * a * a2
    torch.testing.assert_close(chain_operator(gate_logit, tension, b)[0] @ k, torch.eye(n, dtype=torch.float64),
                               atol=1e-9, rtol=0)
    torch.testing.assert_close(chain_operator(gate_logit, tension, 0.0), chain_operator(gate_logit, tension))
    kick = torch.zeros(n, dtype=torch.float64)
    kick[3] = 1.0

    def roughness(x):
        full = torch.cat([torch.zeros(2, dtype=x.dtype), x])
        return float((full[:-2] - 2 * full[1:-1] + full[2:]).square().sum())

    assert roughness(chain_operator(gate_logit, tension, 1e3)[0] @ kick) < 0.1 * roughness(
        chain_operator(gate_logit, tension)[0] @ kick)
    with pytest.raises(ValueError, match="bending"):
        InertialConfig(bending=-1.0)


def test_the_shipped_step_swings_on_after_the_head_stops_and_comes_to_rest():
    """The shipped constants (a weak pull to the equilibrium, light damping, bending) are stable:
    hair carried sideways that stops swings through its equilibrium and settles. Three 40 cm
    strands of 80 vertices, carried at 0.5 m/s for 20 frames, then held for 580 (60 fps)."""
    from hairwarp.methods.inertial import load_inertial_step

    step = load_inertial_step(None, torch.device("cpu")).double()
    rest = torch.zeros(3, 80, 3, dtype=torch.float64)
    rest[:, :, 0] = torch.arange(3, dtype=torch.float64)[:, None] * 0.05
    rest[:, :, 1] = -0.005 * torch.arange(80, dtype=torch.float64)[None, :]
    t = torch.arange(600, dtype=torch.float64).clamp(max=20)
    rigid = rest[None] + torch.stack([0.5 / 60 * t, 0 * t, 0 * t], dim=-1)[:, None, None, :]
    with torch.no_grad():
        out = step.rollout(rigid.clone(), rigid)
    assert bool(torch.isfinite(out).all())
    after = (out[20:, :, -1, 0] - rigid[20:, :, -1, 0])  # the tips' sideways offset once the head stops
    largest = float(after.abs().max())
    assert 0.01 < largest < 0.4, largest  # it swings, within the strand's length
    crossings = ((after[1:] * after[:-1]) < 0).sum(0)
    assert bool((crossings >= 2).all()), crossings  # through the equilibrium and back: secondary motion
    assert float(after[-60:].abs().max()) < 0.02 * largest  # and at rest within the last second


def _held_system(seed=0, m=4, n=9, batch=2):
    """A chain's C^-1 (M, n, n), offsets (B, M, n, 3), holds (B, M, n) with strand 1 of frame 0 free,
    and unit normals (B, M, n, 3), in float64."""
    gen = torch.Generator().manual_seed(seed)
    operator = chain_operator(torch.randn(m, n, generator=gen) + 3.0, torch.rand(m, n, generator=gen) * 5.0,
                              bending=100.0)
    offset = torch.randn(batch, m, n, 3, generator=gen, dtype=torch.float64) * 0.01
    weight = (torch.rand(batch, m, n, generator=gen) < 0.4).double() * 1000.0 * torch.rand(batch, m, n, generator=gen)
    weight[0, 1] = 0.0
    normal = torch.nn.functional.normalize(torch.randn(batch, m, n, 3, generator=gen, dtype=torch.float64), dim=-1)
    return operator, offset, weight, normal


def test_the_body_held_chain_solves_the_held_3n_system():
    """`body_held_chain_relaxation` (Woodbury's identity over C^-1) against the dense float64
    solve of (C (x) I_3 + sum_i kappa_i n_i n_i^T) u = d per strand; a strand with no held
    vertex is the free chain's C^-1 d."""
    operator, offset, weight, normal = _held_system()
    u = body_held_chain_relaxation(operator, offset, weight, normal)
    chain = torch.linalg.inv(operator)
    n = chain.shape[-1]
    for b in range(offset.shape[0]):
        for m in range(offset.shape[1]):
            system = torch.einsum("ij,ab->iajb", chain[m], torch.eye(3, dtype=torch.float64)).reshape(3 * n, 3 * n)
            for i in range(n):
                system[3 * i:3 * i + 3, 3 * i:3 * i + 3] += weight[b, m, i] * torch.outer(normal[b, m, i], normal[b, m, i])
            expected = torch.linalg.solve(system, offset[b, m].reshape(-1)).reshape(n, 3)
            torch.testing.assert_close(u[b, m], expected, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(u[0, 1], (operator @ offset)[0, 1], rtol=0, atol=0)
    assert float((u - operator @ offset).abs().max()) > 1e-4  # the hold changed the held strands


def test_a_stiff_hold_stops_the_chain_along_the_normal_and_leaves_the_tangent_free():
    operator, offset, _, normal = _held_system(seed=1, batch=1)
    weight = torch.zeros(offset.shape[:-1], dtype=torch.float64)
    weight[..., 3:6] = 1e7
    u = body_held_chain_relaxation(operator, offset, weight, normal)
    along = (u * normal).sum(-1)
    free = operator @ offset
    assert float(along[..., 3:6].abs().max()) < 1e-5 * float(free.abs().max())
    tangent = u - along[..., None] * normal
    assert float(tangent[..., 3:6, :].norm(dim=-1).min()) > 1e-5  # the held vertices still slide along the body


def test_the_body_held_chain_gradient_matches_finite_differences():
    operator, offset, weight, normal = _held_system(seed=2, m=2, n=5, batch=1)
    # C^-1 is symmetric (the Cholesky's gradient reads its lower triangle): perturbed symmetrically.
    torch.autograd.gradcheck(lambda d, p: body_held_chain_relaxation((p + p.transpose(-1, -2)) / 2, d, weight, normal),
                             (offset.requires_grad_(), operator.requires_grad_()))


def test_the_body_hold_is_checked_and_needs_the_equilibriums_distances():
    with pytest.raises(ValueError, match="body_hold"):
        InertialConfig(body_hold=-1.0)
    with pytest.raises(ValueError, match="coupling"):
        InertialConfig(body_hold=100.0)
    with pytest.raises(ValueError, match="body_hold_distance"):
        InertialConfig(coupling="chain", body_hold=100.0, body_hold_distance=0.0)
    step = InertialStep(InertialConfig(coupling="chain", body_hold=100.0))
    rigid = _hanging(2, 5, torch.float32)[None].expand(3, -1, -1, -1).contiguous()
    with pytest.raises(ValueError, match="hold"):
        step.rollout(rigid.clone(), rigid)
    with pytest.raises(ValueError, match=r"hold\[1\]"):
        step.rollout(rigid.clone(), rigid, hold=(torch.zeros(rigid.shape[:3]), torch.zeros(3, 2, 4, 3)))
    distance = torch.tensor([[0.001, 0.05, -0.01, 0.019, 0.02]])
    torch.testing.assert_close(body_hold_weights(distance, step.config), torch.tensor([[100.0, 100.0, 0.0]]))


def test_a_hold_far_from_every_vertex_is_the_free_chain():
    """A held step whose equilibrium lies farther than its distance from the body rolls out as the
    same step without the hold, to the last bit; where it lies on the body, the rollout differs."""
    rigid = _hanging(3, 8, torch.float64)
    frames = rigid[None].repeat(6, 1, 1, 1)
    frames[:, :, :, 0] += 0.01 * torch.linspace(0, 1, 6, dtype=torch.float64)[:, None, None]  # the head moves
    config = dict(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95)
    free = InertialStep(InertialConfig(**config)).double().rollout(frames.clone(), frames)
    held = InertialStep(InertialConfig(**config, body_hold=1000.0)).double()
    normal = torch.zeros_like(frames)
    normal[..., 0] = 1.0  # along the head's motion: the swing is held
    far = held.rollout(frames.clone(), frames, hold=(torch.full(frames.shape[:3], 0.05, dtype=torch.float64), normal))
    torch.testing.assert_close(far, free, rtol=0, atol=0)
    near = held.rollout(frames.clone(), frames, hold=(torch.zeros(frames.shape[:3], dtype=torch.float64), normal))
    assert float((near - free).abs().max()) > 1e-6


def test_the_method_holds_the_chain_where_the_equilibrium_lies_on_the_body(tmp_path):
    """The method hands the rollout the equilibrium's distances and normals: a held step runs a
    motion out of the body at its rest lengths, and moves the hair that lies on the body."""
    import hairwarp as hw

    scene = hw.default_scene("long_straight", "nod", duration=0.25, strand_stride=64, num_vertices=24)
    paths = {}
    for hold in (0.0, 1000.0):
        step = InertialStep(InertialConfig(coupling="chain", damping="relative", gate_init=0.99, retention_init=0.95,
                                           tension_init=0.5, equilibrium_speed=0.12, body_hold=hold))
        paths[hold] = str(tmp_path / f"step_{hold:g}.pt")
        save_checkpoint(paths[hold], step)
    free = hw.simulate(scene, method="inertial", checkpoint=paths[0.0])
    held = hw.simulate(scene, method="inertial", checkpoint=paths[1000.0])
    assert max(held.metrics["per_frame"]["penetration_percent"]) == 0.0
    assert held.metrics["length_change_percent"] < 0.01
    assert float((held.positions - free.positions).abs().max()) > 1e-4


def _curly_rest(strands=4):
    """Rest strands of the procedural long curly hair (100 vertices, 6 turns), float64."""
    import hairwarp as hw

    scene = hw.default_scene("long_curly", strand_stride=128)  # 8 strands: a head proxy needs 6 roots
    return scene.frames([0], dtype=torch.float64).rigid.positions[0, :strands]


def test_dynamic_follow_the_leader_keeps_a_curled_strand_still():
    """T23: the shipped constants (chain, G 0.995, beta 0.97, bending 3e4) on long curly hair
    held still, every free vertex kicked 1 mm: with the projected positions' own velocity the
    kick grows (more than 10x in 2 s: follow-the-leader's corrections on a curl feed the swing);
    with `projection_damping` 0.9 it dies out. Straight hair settles either way."""
    import dataclasses

    base = InertialConfig(coupling="chain", gate_init=0.995, retention_init=0.97, damping="relative",
                          tension_init=0.5, bending=3e4)

    def tip_offset_at_2s(config, rest):
        rigid = rest[None].expand(121, -1, -1, -1).clone()
        kick = rest + 0.001 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(0), dtype=rest.dtype)
        kick[:, :2] = rest[:, :2]
        with torch.no_grad():
            out = InertialStep(config).double().rollout(rigid.clone(), rigid, initial=(kick, rest))
        return float((out[-1, :, -1] - rest[:, -1]).norm(dim=-1).mean())

    curly, straight = _curly_rest(), _hanging(4, 100) * 0.25
    damped = dataclasses.replace(base, projection_damping=0.9)
    assert tip_offset_at_2s(base, curly) > 0.01
    assert tip_offset_at_2s(damped, curly) < 0.0005
    assert tip_offset_at_2s(base, straight) < 0.0005 and tip_offset_at_2s(damped, straight) < 0.0005
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="projection_damping"):
            InertialConfig(projection_damping=bad)


def test_the_projection_damping_gives_back_the_led_vertexs_correction():
    """Two frames of `rollout` against the steps written out: the second step reads the velocity
    x(0) - x(-1) - s c(0) shifted one vertex rootward, c = x - p the projection's correction."""
    import dataclasses

    torch.manual_seed(3)
    config = InertialConfig(coupling="chain", gate_init=0.99, retention_init=0.95, damping="relative",
                            projection_damping=0.7)
    step = InertialStep(config).double()
    rest = _curly_rest(2)[:, :30]
    rigid = torch.stack([rest, rest + torch.tensor([0.01, 0.02, 0.0], dtype=torch.float64)])
    equilibrium = rigid + 0.003 * torch.randn_like(rigid)
    with torch.no_grad():
        out = step.rollout(equilibrium, rigid)
        coefficients = step.coefficients(rigid)
        head = torch.zeros_like(rigid)  # the head at rest before the first frame: no head velocity in either step
        x0, p0 = step.step(equilibrium[:1], rigid[:1], equilibrium[:1], equilibrium[:1], head[:1], coefficients,
                           return_target=True)
        led = (x0 - p0)[:, :, 1:]
        before = equilibrium[:1] + 0.7 * torch.cat([led, torch.zeros_like(led[:, :, :1])], dim=2)
        x1 = step.step(equilibrium[1:], rigid[1:], x0, before, head[1:], coefficients)
    torch.testing.assert_close(out, torch.cat([x0, x1]), atol=0, rtol=0)
    undamped = InertialStep(dataclasses.replace(config, projection_damping=0.0)).double()
    undamped.load_state_dict(step.state_dict())
    with torch.no_grad():
        assert float((undamped.rollout(equilibrium, rigid)[1] - out[1]).abs().max()) > 1e-6


def _helix(n=200, radius=0.02, pitch=0.01, turn_segments=20):
    """One helix of n vertices about the vertical axis (radius, rise per turn [m]), float64."""
    angle = 2 * math.pi * torch.arange(n, dtype=torch.float64) / turn_segments
    return torch.stack([radius * torch.cos(angle), -pitch * angle / (2 * math.pi), radius * torch.sin(angle)], dim=-1)


def test_strand_curliness_is_one_less_chord_over_arc_along_the_strand():
    """`strand_curliness` against a float64 loop written from its definition (each vertex's chord
    to the first vertex a window of arc farther, over that arc; vertices with less than half a
    window left not counted); a straight strand reads 0, a helix its chord deficit (a window of
    whole turns: 1 - rise / arc), and a rigid motion changes nothing."""
    from hairwarp.models.inertial import strand_curliness

    def reference(strand, window):
        p = strand.numpy()
        seg = np.linalg.norm(p[1:] - p[:-1], axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        values = []
        for i in range(len(p)):
            j = next((k for k in range(i, len(p)) if s[k] >= s[i] + window), len(p) - 1)
            arc = s[j] - s[i]
            if arc > 0.5 * window:
                values.append(1.0 - np.linalg.norm(p[j] - p[i]) / arc)
        return np.mean(values) if values else 0.0

    helix = _helix()
    seg = float((helix[1] - helix[0]).norm())
    turn_arc = 20.5 * seg  # a turn and a half segment: every window ends 21 segments on, clear of rounding
    straight = _hanging(1, 200)[0]
    torch.manual_seed(3)
    wavy = straight + 0.003 * torch.sin(torch.arange(200, dtype=torch.float64) / 4)[:, None] * torch.tensor(
        [1.0, 0.0, 0.0], dtype=torch.float64)
    strands = torch.stack([helix, straight, wavy])
    for window in (turn_arc, 0.12, 0.5):
        got = strand_curliness(strands, window=window)
        want = [reference(s, window) for s in strands]
        np.testing.assert_allclose(got.numpy(), want, atol=1e-12)
    got = strand_curliness(strands, window=turn_arc)
    assert float(got[1]) == 0.0
    # Away from the tip every window spans 21 segments: one less the chord of 21 / 20 of a turn
    # over their arc (the shorter windows at the tip move the mean a little).
    chord = math.hypot(0.01 * 21 / 20, 2 * 0.02 * math.sin(math.pi / 20))
    assert abs(float(got[0]) - (1.0 - chord / (21 * seg))) < 0.02
    turn = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.4, 0.2], [0.4, 0.0, -0.1], [-0.2, 0.1, 0.0]],
                                                dtype=torch.float64))
    moved = strands @ turn.T + torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    torch.testing.assert_close(strand_curliness(moved, window=turn_arc), got, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="window"):
        strand_curliness(strands, window=0.0)


def test_curl_bending_softens_curled_strands_only():
    """`InertialConfig.curl_bending`: the procedural long curls keep that share of `bending`,
    long straight and medium wavy hair all of it; the chain operator with one bending per strand
    is the operator of each strand's own; 1 (the default) is the step of before bit for bit."""
    import dataclasses

    import hairwarp as hw
    from hairwarp.models.inertial import strand_bending

    base = InertialConfig(coupling="chain", gate_init=0.995, retention_init=0.97, damping="relative",
                          tension_init=0.5, bending=3e4)
    soft = dataclasses.replace(base, curl_bending=0.1)
    curly = _curly_rest(8)
    straight = hw.default_scene("long_straight", strand_stride=128).frames([0], dtype=torch.float64).rigid.positions[0]
    wavy = hw.default_scene("medium_wavy", strand_stride=128).frames([0], dtype=torch.float64).rigid.positions[0]
    torch.testing.assert_close(strand_bending(curly, soft), torch.full((8,), 3e3, dtype=torch.float64))
    for rest in (straight, wavy):
        torch.testing.assert_close(strand_bending(rest, soft), torch.full((len(rest),), 3e4, dtype=torch.float64))
    torch.testing.assert_close(strand_bending(curly, base), torch.full((8,), 3e4, dtype=torch.float64))

    torch.manual_seed(4)
    gate_logit, tension = torch.randn(3, 6, dtype=torch.float64), torch.rand(3, 6, dtype=torch.float64) * 30
    each = torch.tensor([0.0, 50.0, 3e3], dtype=torch.float64)
    together = chain_operator(gate_logit, tension, each)
    for i in range(3):
        torch.testing.assert_close(together[i], chain_operator(gate_logit[i:i + 1], tension[i:i + 1], float(each[i]))[0])

    step, softened = InertialStep(base).double(), InertialStep(soft).double()
    softened.load_state_dict(step.state_dict())
    rigid = curly[None].expand(3, -1, -1, -1).clone()
    moved = rigid + torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64) * torch.arange(3, dtype=torch.float64)[:, None,
                                                                                                              None, None]
    with torch.no_grad():
        plain = step.rollout(moved, moved)
        same = InertialStep(dataclasses.replace(base, curl_bending=1.0)).double()
        same.load_state_dict(step.state_dict())
        assert torch.equal(same.rollout(moved, moved), plain)
        assert not torch.allclose(softened.rollout(moved, moved), plain)
    for bad in (-0.1, 1.5, math.nan, True):
        with pytest.raises(ValueError, match="curl_bending"):
            InertialConfig(curl_bending=bad)


def test_curl_gate_pulls_curled_strands_only():
    """`InertialConfig.curl_gate`: the procedural long curls' free vertices take that G (their
    chain operator is the one made with it), long straight hair keeps the MLP's; None is the step
    of before."""
    import dataclasses

    import hairwarp as hw

    base = InertialConfig(coupling="vertex", gate_init=0.995, retention_init=0.97)
    curly = _curly_rest(8)
    straight = hw.default_scene("long_straight", strand_stride=128).frames([0], dtype=torch.float64).rigid.positions[0]
    step = InertialStep(base).double()
    pulled = InertialStep(dataclasses.replace(base, curl_gate=0.99)).double()
    pulled.load_state_dict(step.state_dict())
    gate, _ = pulled.coefficients(curly)
    torch.testing.assert_close(gate[:, 2:, 0], torch.full_like(gate[:, 2:, 0], 0.99))
    assert torch.equal(gate[:, :2], torch.zeros_like(gate[:, :2]))
    assert torch.equal(pulled.coefficients(straight)[0], step.coefficients(straight)[0])
    chain = dataclasses.replace(base, coupling="chain", tension_init=0.5, bending=3e4)
    plain, curled = InertialStep(chain).double(), InertialStep(dataclasses.replace(chain, curl_gate=0.99)).double()
    curled.load_state_dict(plain.state_dict())
    tension = hanging_chain_tension(curly, 60.0) * 0.5
    logit = torch.full_like(tension, math.log(0.99 / 0.01))
    torch.testing.assert_close(curled.coefficients(curly)[0], chain_operator(logit, tension, 3e4))
    assert torch.equal(curled.coefficients(straight)[0], plain.coefficients(straight)[0])
    for bad in (0.0, 1.0, -0.5, math.inf, True):
        with pytest.raises(ValueError, match="curl_gate"):
            InertialConfig(curl_gate=bad)
