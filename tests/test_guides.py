"""Guide strands and their followers (`hairwarp.scene.guides`, `hairwarp.ops.guide_interpolation`):
the kernels against float64 references, the interpolation's invariants, the body pass, the guide
choice, and a 1 000-strand groom end to end through the commands."""

import os
import struct

import numpy as np
import pytest
import torch

from hairwarp.ops import BodyMesh, hair_body_signed_distance
from hairwarp.ops.guide_interpolation import (
    follow_guides,
    follower_distance_bound,
    guide_frame_rotations,
    interpolate_followers,
    rotation_quaternions,
)
from hairwarp.scene.guides import GuideConfig, GuideSet, select_guides, strand_features
from hairwarp.scene.hairstyles import Hairstyle
from hairwarp.scene.rotations import axis_angle_to_matrix
from meshes import icosphere
from references import guides as ref
from test_body_sign import box


def quaternion_matrices(q: torch.Tensor) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3, 3) float64 rotation matrices."""
    x, y, z, w = np.moveaxis(q.double().numpy(), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def wavy_strands(count: int, n: int, rng, length: float = 0.3, amplitude: float = 0.01) -> np.ndarray:
    """(count, n, 3) strands hanging down from roots spread in x, each with its own wave."""
    s = np.linspace(0.0, 1.0, n)
    out = np.zeros((count, n, 3))
    for k in range(count):
        phase, freq = rng.uniform(0, 2 * np.pi), rng.uniform(5, 9)
        out[k, :, 0] = 0.01 * k + amplitude * np.sin(freq * s + phase)
        out[k, :, 1] = -length * s
        out[k, :, 2] = amplitude * np.cos(freq * s + phase) + 0.002 * k
    return out


def bend(strands: np.ndarray, angle: float, axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Each segment turned by an angle growing along the strand (to `angle` at the tip): a bend
    that keeps every segment's length, as the physics does."""
    n = strands.shape[1]
    axis = np.asarray(axis) / np.linalg.norm(axis)
    edges = np.diff(strands, axis=1)
    for i in range(n - 1):
        r = axis_angle_to_matrix(torch.tensor(axis * angle * (i / (n - 2)))).numpy()
        edges[:, i] = edges[:, i] @ r.T
    return np.concatenate([strands[:, :1], strands[:, :1] + np.cumsum(edges, axis=1)], axis=1)


def random_rotation(rng) -> np.ndarray:
    return axis_angle_to_matrix(torch.tensor(rng.normal(size=3) * 0.6)).numpy()


# ------------------------------------------------------------------ kernels against the references


def test_frame_rotations_and_followers_match_the_float64_reference(rng):
    k, n, m = 5, 12, 7
    rest = wavy_strands(k, n, rng)
    head = random_rotation(rng)
    now = bend(rest, 0.9) @ head.T + np.array([0.1, -0.2, 0.05])
    now += 0.002 * rng.normal(size=now.shape)
    rotations = guide_frame_rotations(torch.tensor(rest, dtype=torch.float32), torch.tensor(now[None], dtype=torch.float32),
                                      torch.tensor(head[None]))
    expected = ref.guide_frame_rotations(rest, now, head)
    np.testing.assert_allclose(quaternion_matrices(rotations[0]), expected, atol=2e-5)

    followers = wavy_strands(m, n, rng) + rng.normal(size=(m, 1, 3)) * 0.01
    link = rng.integers(0, k, size=(m, 3))
    weights = rng.uniform(0.1, 1.0, size=(m, 3))
    weights[0, 1:] = 0.0  # a follower of one guide
    weights /= weights.sum(1, keepdims=True)
    ratios = rng.uniform(0.6, 1.4, size=(m, 3))
    got = interpolate_followers(torch.tensor(rest, dtype=torch.float32), torch.tensor(now[None], dtype=torch.float32),
                                rotations, torch.tensor(followers, dtype=torch.float32), torch.tensor(link),
                                torch.tensor(weights, dtype=torch.float32), torch.tensor(ratios, dtype=torch.float32))
    want = ref.interpolate_followers(rest, now, expected, followers, link, weights, ratios)
    np.testing.assert_allclose(got[0].double().numpy(), want, atol=2e-6)


def test_frames_a_block_per_guide_equal_the_one_thread_kernel(rng):
    """The CUDA frames kernel (a block per guide, the strands in shared memory), run on the CPU,
    gives the one-thread kernel's rotations bit for bit, for any window."""
    from hairwarp import _warp
    from hairwarp.kernels import guide_interpolation as kernels
    from hairwarp.ops.guide_interpolation import rotation_quaternions

    rest = torch.tensor(wavy_strands(5, 16, rng), dtype=torch.float32)
    now = torch.tensor(np.stack([bend(rest.double().numpy(), 0.8), bend(rest.double().numpy(), -0.5)]),
                       dtype=torch.float32)
    head = torch.tensor(np.stack([random_rotation(rng), random_rotation(rng)]), dtype=torch.float32)
    for window in (0, 4):
        expected = guide_frame_rotations(rest, now, head, window=window)
        got = torch.empty_like(expected)
        _warp.launch(kernels.guide_frame_rotations_tiled_kernel(16, window), dim=10, device="cpu",
                     inputs=[_warp.as_warp(rest, vec3=True), _warp.as_warp(now.contiguous(), vec3=True),
                             _warp.as_warp(rotation_quaternions(head).contiguous(), quat=True), 5],
                     outputs=[_warp.as_warp(got, quat=True)], block_dim=kernels.FRAMES_BLOCK_DIM)
        assert torch.equal(got, expected)


def test_head_rotation_quaternions_are_the_matrices(rng):
    half_turns = [axis_angle_to_matrix(torch.tensor(np.pi * np.asarray(a) / np.linalg.norm(a))).numpy()
                  for a in ([1.0, -1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 2.0, -3.0])]
    matrices = np.stack([random_rotation(rng) for _ in range(6)] + [np.eye(3)] + half_turns)
    q = rotation_quaternions(torch.tensor(matrices))
    np.testing.assert_allclose(quaternion_matrices(q), matrices, atol=1e-6)


def test_distance_bound_is_below_the_signed_distance(rng):
    v, f = icosphere(6, radius=0.1, center=(0.0, -0.15, 0.05))
    body = BodyMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32))
    k, n, m = 4, 16, 9
    guides = torch.tensor(wavy_strands(k, n, rng)[None], dtype=torch.float32)
    followers = guides[:, torch.tensor(rng.integers(0, k, m))] + torch.tensor(rng.normal(size=(1, m, 1, 3)) * 0.01,
                                                                              dtype=torch.float32)
    link = torch.tensor(rng.integers(0, k, size=(m, 2)))
    weights = torch.full((m, 2), 0.5)
    ratios = torch.tensor(rng.uniform(0.8, 1.2, size=(m, 2)), dtype=torch.float32)
    bound = follower_distance_bound(guides, hair_body_signed_distance(guides, body), followers, link, weights, ratios)
    exact = hair_body_signed_distance(followers, body)
    assert bool((exact < 0).any()) and bool((exact > 0.05).any())  # the case spans inside and far outside
    assert bool((bound <= exact + 1e-6).all())
    assert float((exact - bound).min()) < 0.01  # and is not vacuous


def test_bad_inputs_name_the_argument():
    rest = torch.zeros(3, 5, 3)
    with pytest.raises(ValueError, match="guides_now"):
        guide_frame_rotations(rest, torch.zeros(1, 4, 5, 3), torch.eye(3)[None])
    with pytest.raises(ValueError, match="head_rotation"):
        guide_frame_rotations(rest, torch.zeros(2, 3, 5, 3), torch.eye(3)[None])
    rot = torch.zeros(1, 3, 4, 4)
    with pytest.raises(ValueError, match="follower_guides"):
        interpolate_followers(rest, rest[None], rot, torch.zeros(2, 5, 3), torch.tensor([[0], [3]]),
                              torch.ones(2, 1), torch.ones(2, 1))
    with pytest.raises(ValueError, match="guides_rest"):
        guide_frame_rotations(torch.full((3, 5, 3), float("nan")), torch.zeros(1, 3, 5, 3), torch.eye(3)[None])
    with pytest.raises(ValueError, match="num_guides"):
        GuideConfig(num_guides=0)
    with pytest.raises(ValueError, match="reach_segments"):
        follow_guides(rest, rest[None], rot, torch.zeros(2, 5, 3), torch.tensor([[0], [1]]), torch.ones(2, 1),
                      torch.ones(2, 1), reach_segments=0.5)
    with pytest.raises(ValueError, match="schedule"):
        follow_guides(rest, rest[None], rot, torch.zeros(2, 5, 3), torch.tensor([[0], [1]]), torch.ones(2, 1),
                      torch.ones(2, 1), schedule="parallel")
    with pytest.raises(ValueError, match="rest_lengths"):
        follow_guides(rest, rest[None], rot, torch.zeros(2, 5, 3), torch.tensor([[0], [1]]), torch.ones(2, 1),
                      torch.ones(2, 1), rest_lengths=torch.ones(2, 5))
    with pytest.raises(ValueError, match="body_schedule"):
        GuideConfig(body_schedule="parallel")


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_follow_names_the_input_that_holds_a_nan(rng, device):
    """`GuideSet.follow` scans its inputs for NaN/Inf in one read-back and names the culprit (on
    CUDA read after the pass is queued, replayed from its graph from the third clean call on)."""
    from hairwarp._validate import check_finite

    groom = _hanging_groom(rng)
    v, f = icosphere(8, radius=0.05, center=(0.03, 0.0, 0.0))
    body = BodyMesh(torch.tensor(v, dtype=torch.float32, device=device),
                    torch.tensor(f, dtype=torch.int32, device=device))
    guides = GuideSet.build(groom, GuideConfig(num_guides=8))
    positions = groom.strands[guides.guide_indices][None].float().to(device)
    sd = hair_body_signed_distance(positions, body)
    head = torch.eye(3, device=device)[None]
    for _ in range(3):  # eager, captured, replayed
        guides.follow(positions, head, body, guide_signed_distance=sd)
    bad = positions.clone()
    bad[0, 3, 5, 1] = float("nan")
    for kwargs, name in ((dict(guide_positions=bad, head_rotation=head), "guide_positions"),
                         (dict(guide_positions=positions, head_rotation=head * float("inf")), "head_rotation"),
                         (dict(guide_positions=bad, head_rotation=head, body=body), "guide_positions"),
                         (dict(guide_positions=positions, head_rotation=head, body=body,
                               guide_signed_distance=sd.index_fill(2, torch.tensor([4], device=device), float("nan"))),
                          "guide_signed_distance")):
        with pytest.raises(ValueError, match=name):
            guides.follow(**kwargs)
    x, facts = guides.follow(positions, head, body, guide_signed_distance=sd)
    assert bool(torch.isfinite(x).all()) and int(facts["pushed"].sum()) > 0
    check_finite(a=positions, b=torch.zeros(0), c=torch.arange(3))  # clean, empty and integer tensors pass
    with pytest.raises(ValueError, match="^b: contains NaN or Inf"):
        check_finite(a=positions, b=bad)


# ------------------------------------------------------------------ what followers do


def _run(rest, now, head, followers, link, weights, ratios):
    t = lambda a, dtype=torch.float32: torch.tensor(np.asarray(a), dtype=dtype)  # noqa: E731
    rotations = guide_frame_rotations(t(rest), t(now[None]), t(head[None], torch.float64))
    return interpolate_followers(t(rest), t(now[None]), rotations, t(followers), torch.tensor(link), t(weights),
                                 t(ratios))[0].double().numpy()


def test_a_follower_sitting_on_its_guide_reproduces_it(rng):
    rest = wavy_strands(3, 20, rng)
    now = bend(rest, 1.2) + 0.003 * rng.normal(size=rest.shape)
    got = _run(rest, now, np.eye(3), rest[1:2], [[1]], [[1.0]], [[1.0]])
    np.testing.assert_allclose(got[0], now[1], atol=2e-6)


def test_followers_of_guides_moved_rigidly_move_rigidly(rng):
    rest = wavy_strands(2, 20, rng)
    followers = 0.5 * (rest[0] + rest[1])[None] + rng.normal(size=(1, 20, 3)) * 0.002  # between the two
    offset = np.array([0.03, -0.05, 0.02])
    got = _run(rest, rest + offset, np.eye(3), followers, [[0, 1]], [[0.5, 0.5]], [[1.1, 0.9]])
    np.testing.assert_allclose(got, followers + offset, atol=2e-6)  # translated together: translated
    head = random_rotation(rng)
    got = _run(rest, rest @ head.T + offset, head, followers, [[0, 1]], [[0.3, 0.7]], [[1.0, 1.0]])
    np.testing.assert_allclose(got, followers @ head.T + offset, atol=5e-6)  # turned with the head: turned


def turning_angles(strand: np.ndarray) -> np.ndarray:
    d = np.diff(strand, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip((d[1:] * d[:-1]).sum(1), -1.0, 1.0))


def test_followers_of_a_curly_guide_keep_their_curl():
    n = 100
    s = np.linspace(0.0, 1.0, n)
    helix = lambda r, x0, phase: np.stack([x0 + r * np.cos(40 * s + phase), -0.4 * s,  # noqa: E731
                                           r * np.sin(40 * s + phase)], -1)
    rest = np.stack([helix(0.012, 0.0, 0.0)])
    followers = np.stack([helix(0.010, 0.004, 0.7), helix(0.015, -0.003, 2.0)])
    now = bend(rest, 1.0, axis=(1.0, 0.0, 0.3))  # the guide swings and bends
    got = _run(rest, now, np.eye(3), followers, [[0], [0]], [[1.0], [1.0]], [[1.0], [1.0]])
    for before, after in zip(followers, got):
        k0, k1 = turning_angles(before), turning_angles(after)
        assert np.abs(k1 - k0).mean() / k0.mean() < 0.10
        assert np.abs(after[-1] - before[-1]).max() > 0.05  # the follower did move with its guide


# ------------------------------------------------------------------ the body pass and the guide choice


def _hanging_groom(rng, count=40, n=24):
    """Straight strands hanging from roots over a ring, some passing through a ball below."""
    angle = rng.uniform(0, 2 * np.pi, count)
    radius = rng.uniform(0.0, 0.06, count)
    roots = np.stack([radius * np.cos(angle), np.full(count, 0.2), radius * np.sin(angle)], -1)
    strands = roots[:, None] + np.linspace(0, 1, n)[None, :, None] * np.array([0.0, -0.3, 0.0])
    return Hairstyle(strands=torch.tensor(strands, dtype=torch.float32), root_uv=torch.zeros(count, 2),
                     root_normals=torch.tensor([[0.0, 1.0, 0.0]]).expand(count, 3).clone(),
                     root_index=torch.arange(count), filtered=torch.zeros(0, dtype=torch.int64))


def _sphere_or_box(shape: str) -> BodyMesh:
    """A body the hanging groom's followers pass through: a sphere or a box."""
    if shape == "sphere":
        v, f = icosphere(8, radius=0.05, center=(0.03, 0.0, 0.0))
    else:
        v, f = box([-0.02, -0.04, -0.03], [0.06, 0.03, 0.05])
    return BodyMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32))


@pytest.mark.parametrize("shape, reach, schedule, settle", [
    ("sphere", 1.0, "walk", 0.0), ("box", 1.0, "walk", 0.0), ("sphere", 4.0, "walk", 0.0), ("box", 4.0, "walk", 0.0),
    ("sphere", 1.0, "walk", 5e-4), ("box", 1.0, "walk", 5e-4), ("sphere", 1.0, "rounds", 0.0),
    ("box", 1.0, "rounds", 0.0)])
def test_body_pass_leaves_no_follower_inside_and_keeps_rest_lengths(rng, shape, reach, schedule, settle, monkeypatch):
    """Whatever the queries' reach (an empty ball clears the vertices after it without a query),
    their schedule (vertex after vertex, or in rounds) and whether the walk skips a pushed
    vertex's confirming query (`body_settle`)."""
    import hairwarp.ops.guide_interpolation as ops_guides

    monkeypatch.setattr(ops_guides, "QUERY_REACH_SEGMENTS", reach)
    groom = _hanging_groom(rng)
    body = _sphere_or_box(shape)
    guides = GuideSet.build(groom, GuideConfig(num_guides=8, body_passes=8, body_schedule=schedule, body_settle=settle))
    guide_positions = groom.strands[guides.guide_indices][None]
    before, _ = guides.follow(guide_positions, torch.eye(3)[None])
    assert bool((hair_body_signed_distance(before, body)[:, :, 2:] < 0).any())  # the case has followers inside
    after, facts = guides.follow(guide_positions, torch.eye(3)[None], body)
    followers = torch.ones(groom.num_strands, dtype=torch.bool)
    followers[guides.guide_indices] = False
    sd = hair_body_signed_distance(after, body)[0, followers, 2:]
    assert float(sd.min()) >= -1e-5, float(sd.min())
    rest = (groom.strands[:, 1:] - groom.strands[:, :-1]).norm(dim=-1)
    lengths = (after[0, :, 1:] - after[0, :, :-1]).norm(dim=-1)
    torch.testing.assert_close(lengths[followers], rest[followers], atol=1e-5, rtol=1e-4)
    assert int(facts["pushed"].sum()) > 0
    torch.testing.assert_close(after[0, guides.guide_indices], guide_positions[0])  # the guides stay the method's


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_the_walks_face_hint_changes_no_position(rng, shape, monkeypatch):
    """Capping a query at the strand's last closest face finds the same closest faces: the same
    positions and pushes as the full-reach queries."""
    import hairwarp.ops.guide_interpolation as ops_guides

    groom = _hanging_groom(rng)
    body = _sphere_or_box(shape)
    guides = GuideSet.build(groom, GuideConfig(num_guides=8))
    now = torch.tensor(bend(groom.strands[guides.guide_indices].double().numpy(), 0.3), dtype=torch.float32)[None]
    results = {}
    for hint in (False, True):
        monkeypatch.setattr(ops_guides, "WALK_FACE_HINT", hint)
        results[hint] = guides.follow(now, torch.eye(3)[None], body)
    assert int(results[False][1]["pushed"].sum()) > 0
    torch.testing.assert_close(results[True][0], results[False][0], atol=1e-6, rtol=0)
    assert torch.equal(results[True][1]["pushed"], results[False][1]["pushed"])


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_the_rounds_face_hint_and_skipped_settled_strands_change_no_position(rng, shape, monkeypatch):
    """The rounds' query capped at the vertex's last closest face finds the same faces (the same
    positions and pushes); walking again only the strands whose round found a vertex within the
    margin leaves the others where a walk would put them, to float32 rounding (their pushes are
    those of the last walk that ran on them, so they are not compared)."""
    import hairwarp.ops.guide_interpolation as ops_guides

    groom = _hanging_groom(rng)
    body = _sphere_or_box(shape)
    guides = GuideSet.build(groom, GuideConfig(num_guides=8, body_schedule="rounds", body_passes=4))
    now = torch.tensor(bend(groom.strands[guides.guide_indices].double().numpy(), 0.3), dtype=torch.float32)[None]
    results = {}
    for hint, skip in ((False, False), (True, False), (False, True), (True, True)):
        monkeypatch.setattr(ops_guides, "ROUNDS_FACE_HINT", hint)
        monkeypatch.setattr(ops_guides, "ROUNDS_SKIP_SETTLED", skip)
        results[hint, skip] = guides.follow(now, torch.eye(3)[None], body)
    x, facts = results[False, False]
    assert int(facts["pushed"].sum()) > 0
    for key, (y, other) in results.items():
        torch.testing.assert_close(y, x, atol=1e-6, rtol=0, msg=f"face hint, skip settled: {key}")
    assert torch.equal(results[True, False][1]["pushed"], facts["pushed"])
    assert torch.equal(results[True, True][1]["pushed"], results[False, True][1]["pushed"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_frames_and_both_schedules_match_the_cpu(rng):
    """The CUDA kernels (the frames a block per guide, the rounds' walk a block per strand) give
    the CPU's frames, and each schedule the CPU's positions, to float32 rounding."""
    from hairwarp.ops.guide_interpolation import follow_guides

    groom = _hanging_groom(rng, count=64)
    v, f = icosphere(8, radius=0.05, center=(0.03, 0.0, 0.0))
    guides = GuideSet.build(groom, GuideConfig(num_guides=8))
    now = torch.tensor(bend(groom.strands[guides.guide_indices].double().numpy(), 0.4), dtype=torch.float32)[None]
    head = torch.eye(3)[None]
    results = {}
    for device in ("cpu", "cuda"):
        body = BodyMesh(torch.tensor(v, dtype=torch.float32, device=device), torch.tensor(f, dtype=torch.int32,
                                                                                        device=device))
        on = guides._on(torch.device(device))
        rotations = guide_frame_rotations(on["guides_rest"], now.to(device), head.to(device))
        sd = hair_body_signed_distance(now.to(device), body)
        results[device] = [rotations.cpu()]
        for schedule in ("walk", "rounds"):
            x, pushed = follow_guides(on["guides_rest"], now.to(device), rotations, on["rest"], *on["link"],
                                      guide_slot=on["guide_slot"], body=body, guide_signed_distance=sd,
                                      schedule=schedule)
            results[device] += [x.cpu(), pushed.cpu()]
    cpu, cuda = results["cpu"], results["cuda"]
    torch.testing.assert_close(cuda[0], cpu[0], atol=2e-6, rtol=0)
    for i in (1, 3):
        assert int(cpu[i + 1].sum()) > 0
        torch.testing.assert_close(cuda[i], cpu[i], atol=2e-5, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("schedule", ["walk", "rounds"])
def test_cuda_follow_replayed_from_its_graph_equals_the_eager_launches(rng, schedule):
    """Calls 1 (eager), 2 (captured) and 3-4 (replayed) with new guide positions each, the body
    moved by `BodyMesh.update` in between, against the same calls with `cuda_graph=False`; a new
    body object is a new key, run eagerly."""
    groom = _hanging_groom(rng, count=64)
    v, f = icosphere(8, radius=0.05, center=(0.03, 0.0, 0.0))
    device = torch.device("cuda")
    vertices = torch.tensor(v, dtype=torch.float32, device=device)
    results = {}
    for graph in (True, False):
        body = BodyMesh(vertices.clone(), torch.tensor(f, dtype=torch.int32, device=device))
        guides = GuideSet.build(groom, GuideConfig(num_guides=8, body_passes=8, body_schedule=schedule, cuda_graph=graph))
        base = groom.strands[guides.guide_indices][None].to(device)
        out = []
        for call in range(4):
            body.update(vertices + torch.tensor([0.004 * call, 0.0, 0.0], device=device))
            moved = base + 0.002 * call * torch.sin(torch.arange(base.shape[2], device=device))[None, None, :, None]
            x, facts = guides.follow(moved, torch.eye(3, device=device)[None], body)
            out.append((x.cpu(), facts["pushed"].cpu()))
        if graph:
            (entry,) = guides._graphs.values()
            assert entry["call"] is not None  # captured at call 2, replayed at calls 3 and 4
        other = BodyMesh(vertices.clone() + 0.01, torch.tensor(f, dtype=torch.int32, device=device))
        x, facts = guides.follow(base, torch.eye(3, device=device)[None], other)
        out.append((x.cpu(), facts["pushed"].cpu()))
        if graph:
            (entry,) = guides._graphs.values()
            assert entry["call"] is None  # the new body: a new key, eager
            for _ in range(2):  # a batch of frames never gets a graph (its buffers would stay held)
                guides.follow(base.expand(2, -1, -1, -1), torch.eye(3, device=device)[None].expand(2, 3, 3), other)
            assert all(e["call"] is None for e in guides._graphs.values())
        results[graph] = out
    for (x_graph, p_graph), (x_eager, p_eager) in zip(results[True], results[False]):
        torch.testing.assert_close(x_graph, x_eager, atol=1e-6, rtol=0)
        assert torch.equal(p_graph, p_eager)
    assert int(results[True][3][1].sum()) > 0


_SPLIT_SCRIPT = """
import numpy as np, torch
import hairwarp.ops.guide_interpolation as ops_guides
from hairwarp.ops import BodyMesh
from hairwarp.scene.guides import GuideConfig, GuideSet
from meshes import icosphere
from test_guides import _hanging_groom

groom = _hanging_groom(np.random.default_rng(3), count=64)
v, f = icosphere(8, radius=0.05, center=(0.03, 0.0, 0.0))
body = BodyMesh(torch.tensor(v, dtype=torch.float32), torch.tensor(f, dtype=torch.int32))
guides = GuideSet.build(groom, GuideConfig(num_guides=8, body_passes=8))
positions = groom.strands[guides.guide_indices][None]
ops_guides.CPU_SPLIT_THREADS = 4  # every launch of this groom split: the first ones of the process
split, facts = guides.follow(positions, torch.eye(3)[None], body)
assert ops_guides._SHARED_READY, "no launch was split"
ops_guides.CPU_SPLIT_THREADS = 10**9
whole, _ = guides.follow(positions, torch.eye(3)[None], body)
assert torch.equal(split, whole) and int(facts["pushed"].sum()) > 0
print("same")
"""


def test_the_passes_split_between_two_cores_match_one_launch_from_a_fresh_process():
    """On the CPU a large follower pass runs as two launches, one on the side thread: the same
    positions as one launch, bit for bit, from the first split launches of a fresh process on."""
    import subprocess
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, "-c", _SPLIT_SCRIPT], cwd=here, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and done.stdout.strip().endswith("same"), done.stderr[-2000:]


def test_guide_choice_covers_both_styles_and_is_deterministic(rng):
    n = 20
    left = wavy_strands(30, n, rng) + np.array([0.0, 0.0, 0.0])
    right = left.copy()
    left[:, :, 0] -= np.linspace(0, 0.2, n)[None]  # combed to -x
    right[:, :, 0] += np.linspace(0, 0.2, n)[None]  # combed to +x, roots shared
    strands = torch.tensor(np.concatenate([left, right]), dtype=torch.float32)
    features = strand_features(strands)
    chosen = select_guides(features, 2)
    assert sorted(int(c) // 30 for c in chosen) == [0, 1]  # one guide per style
    chosen8 = select_guides(features, 8)
    assert torch.equal(chosen8, select_guides(features, 8))
    assert len(set(chosen8.tolist())) == 8
    # Farthest-point sampling: no strand is farther from its nearest guide than the last pick was.
    d = torch.cdist(features, features[chosen8]).min(1).values
    radius = torch.cdist(features[chosen8[-1:]], features[chosen8[:-1]]).min()
    assert float(d.max()) <= float(radius) + 1e-6


# ------------------------------------------------------------------ a groom end to end


def _write_groom(path, count: int, seed: int = 0) -> None:
    """A `.data` groom of `count` strands around the default scalp, written with struct (centimetres)."""
    import hairwarp as hw

    base = hw.default_scene("medium_wavy", strand_stride=4, num_vertices=30).hairstyle.strands.double().numpy()
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(base), count)
    strands = base[pick] + rng.normal(size=(count, 1, 3)) * 0.003 + rng.normal(size=(count, 30, 3)) * 0.0005
    out = bytearray(struct.pack("<i", count))
    for s in strands * 100.0:
        out += struct.pack("<i", len(s)) + s.astype("<f4").tobytes()
    with open(path, "wb") as f:
        f.write(bytes(out))


def test_a_thousand_strand_groom_through_50_guides_drapes_simulates_and_exports(tmp_path):
    from hairwarp.cli import main
    from hairwarp.io.hair_data import read_hair_data
    from hairwarp.io.usd import read_usd_curves

    groom = str(tmp_path / "groom.data")
    _write_groom(groom, 1000)
    common = ["--hairstyle", groom, "--guides", "50", "--num-vertices", "20", "--no-progress"]
    assert main(["drape", *common, "--method", "lbfgs", "--max-iterations", "5", "--out", str(tmp_path / "d")]) == 0
    assert len(read_hair_data(str(tmp_path / "d" / "drape.data"))) == 1000
    assert main(["simulate", *common, "--method", "rigid", "--pose", "nod", "--frames", "3",
                 "--out", str(tmp_path / "s")]) == 0
    curves = read_usd_curves(str(tmp_path / "s" / "simulate.usdc"))
    assert len(curves["strands"]) == 1000
    assert main(["export", str(tmp_path / "s" / "simulate.usdc"), str(tmp_path / "last.data")]) == 0
    assert len(read_hair_data(str(tmp_path / "last.data"))) == 1000
    for name in ("d/drape.png", "s/simulate.png", "s/simulate.gif", "d/drape_metrics.json"):
        assert os.path.getsize(tmp_path / name) > 1000

    import hairwarp as hw

    scene = hw.build_scene(groom, guides=50, num_vertices=20)
    result = hw.drape(scene, method="rigid")
    assert result.positions.shape == (1000, 20, 3) and result.guide_positions.shape == (50, 20, 3)
    assert set(result.metrics["guides"]) >= {"penetration_percent", "length_change_percent"}
    assert result.metrics["length_change_percent"] < 0.5  # the followers keep their rest lengths


def test_guide_counts_out_of_range_are_one_clear_line(tmp_path, capsys):
    import hairwarp as hw
    from test_cli import TINY, _bad

    with pytest.raises(ValueError, match="^guides: expected at most the groom's 16 strands, got 17$"):
        hw.build_scene("bob", strand_stride=64, num_vertices=12, grow="head", guides=17)
    with pytest.raises(ValueError, match="^guides: expected an integer >= 1"):
        hw.build_scene("bob", strand_stride=64, num_vertices=12, grow="head", guides=0)
    _bad(["drape", *TINY, "--guides", "0", "--out", str(tmp_path)], capsys, needle="--guides")
    _bad(["drape", *TINY, "--guides", "100000", "--out", str(tmp_path)], capsys, needle="--guides")
