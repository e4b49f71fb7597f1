"""`hairwarp.energy.CapturedEnergy`: the total energy and its gradient for one shape, replayed
from a CUDA graph on the GPU (eager, same results, on the CPU), and the graph-safe energy it
captures (`total_energy(graph_safe=True)`: nothing read back to the host)."""

import math

import pytest
import torch

from hairwarp.energy import CapturedEnergy, total_energy
from hairwarp.ops.hair_hair_contact import HairHairCapacityError
from hairwarp.scene.scene import default_scene


def _small_inputs(device, batch=2):
    """A default-scene drape at 1/16 of the strands and 30 vertices, jittered off the rigid placement."""
    scene = default_scene("long_straight", "head_turn", strand_stride=4, num_vertices=30)
    idx = torch.linspace(0, scene.num_frames - 1, batch).round().long()
    frames = scene.frames(idx, device=device)
    g = torch.Generator().manual_seed(0)
    rigid = frames.rigid.positions
    jitter = (torch.randn(rigid.shape, generator=g, dtype=rigid.dtype) * 3e-3).to(device)
    jitter[:, :, :2] = 0
    from dataclasses import replace

    inputs = replace(frames.inputs, prev=(rigid + 0.5 * jitter).detach(), prev2=rigid.detach())
    return (rigid + jitter).detach(), inputs


def _eager(x, inputs, **kw):
    xe = x.detach().clone().requires_grad_(True)
    result = total_energy(xe, inputs, dynamic=True, **kw)
    result.total.sum().backward()
    return result, xe.grad


def test_graph_safe_energy_equals_eager_on_the_cpu():
    x, inputs = _small_inputs("cpu")
    eager, g_eager = _eager(x, inputs)
    safe, g_safe = _eager(x, inputs, graph_safe=True, hair_hair_capacity=10 * eager.hair_hair_pairs)
    assert eager.hair_hair_pairs > 0 and safe.hair_hair_pairs == eager.hair_hair_pairs
    torch.testing.assert_close(safe.total, eager.total, rtol=1e-6, atol=0)
    torch.testing.assert_close(g_safe, g_eager, rtol=1e-6, atol=1e-9)


def test_captured_energy_on_the_cpu_equals_total_energy_and_flags_overflow():
    x, inputs = _small_inputs("cpu")
    captured = CapturedEnergy(x, inputs, dynamic=True)
    assert not captured.captured  # no graph on the CPU: same object, eager
    eager, g_eager = _eager(x, inputs)
    energy, gradient = captured(x)
    torch.testing.assert_close(energy, eager.total.detach(), rtol=1e-6, atol=0)
    torch.testing.assert_close(gradient, g_eager, rtol=1e-6, atol=1e-9)
    assert captured.hair_hair_capacity >= 2 * eager.hair_hair_pairs
    captured.check()
    # Hair piled into a ball: far more pairs than the buffer holds; the call says so on check().
    piled = x.clone()
    piled[:, :, 2:] = x[:, :1, 2:2 + 1].mean(dim=1, keepdim=True) + 0.01 * (piled[:, :, 2:] - x[:, :, 2:])
    captured(piled)
    with pytest.raises(HairHairCapacityError, match="capacity"):
        captured.check()
    with pytest.raises(ValueError, match="x: expected"):
        captured(x[:1])


def _join_fraction_cases(captured, bp, x, inputs):
    """For two values written into `bp`: the captured call against the eager energy with the
    config holding that value."""
    from dataclasses import replace

    from hairwarp.config import EnergyConfig

    results = []
    for value in (0.3, 0.02):
        bp.fill_(value)
        eager, g_eager = _eager(x, inputs, config=replace(EnergyConfig(), barrier_join_fraction=value))
        energy, gradient = captured(x)
        torch.testing.assert_close(energy, eager.total.detach(), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(gradient, g_eager, rtol=1e-4, atol=1e-4)
        results.append(energy)
    assert not torch.allclose(results[0], results[1], rtol=1e-3)  # the value matters


def test_the_join_fraction_is_read_from_a_tensor_at_each_call():
    """b_p given as a one-element tensor (`total_energy(barrier_join_fraction=)`, the contact
    ops' `bp`) is read when the kernels run: a value written into it between calls is the one
    used, as with a float of that value; a bad tensor is refused naming bp."""
    from hairwarp.ops import hair_body_contact_energy, hair_hair_contact_energy

    x, inputs = _small_inputs("cpu")
    bp = torch.tensor([0.3])
    _join_fraction_cases(CapturedEnergy(x, inputs, dynamic=True, barrier_join_fraction=bp), bp, x, inputs)
    for dtype in (torch.float32, torch.float64):
        xd = x.to(dtype)
        bp64 = torch.tensor(0.2, dtype=torch.float64)
        torch.testing.assert_close(hair_body_contact_energy(xd, inputs.body, 1e-3, 1.5e-3, bp64),
                                   hair_body_contact_energy(xd, inputs.body, 1e-3, 1.5e-3, 0.2), rtol=0, atol=0)
        torch.testing.assert_close(hair_hair_contact_energy(xd, 5e-4, 7.5e-4, bp64)[0],
                                   hair_hair_contact_energy(xd, 5e-4, 7.5e-4, 0.2)[0], rtol=0, atol=0)
    for bad, match in ((torch.tensor([0.2, 0.3]), "one-element"), (torch.tensor([1]), "floating"),
                       (torch.tensor([1.5]), r"\(0, 1\)")):
        with pytest.raises(ValueError, match="bp: expected.*" + match):
            hair_body_contact_energy(x, inputs.body, 1e-3, 1.5e-3, bad)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_follows_the_join_fraction_tensor():
    x, inputs = _small_inputs("cuda")
    bp = torch.tensor([0.3], device="cuda")
    captured = CapturedEnergy(x, inputs, dynamic=True, barrier_join_fraction=bp)
    assert captured.captured
    _join_fraction_cases(captured, bp, x, inputs)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_energy_equals_eager():
    x, inputs = _small_inputs("cuda")
    captured = CapturedEnergy(x, inputs, dynamic=True)
    assert captured.captured
    for scale in (1.0, 0.5):  # a replay on new positions, not only the captured ones
        xs = inputs.rigid + scale * (x - inputs.rigid)
        eager, g_eager = _eager(xs, inputs)
        energy, gradient = captured(xs)
        torch.testing.assert_close(energy, eager.total.detach(), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(gradient, g_eager, rtol=1e-4, atol=1e-4)
    captured.check()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_follows_a_moved_body():
    """`BodyMesh.update` moves everything a query reads in place: a graph captured before it
    gives the moved body's energy and gradient (the eager call on the same body's)."""
    scene = default_scene("long_straight", "head_turn", strand_stride=4, num_vertices=30)
    x, inputs = _small_inputs("cuda")
    captured = CapturedEnergy(x, inputs, dynamic=True)
    before, _ = captured(x)
    posed = scene.frames([0, scene.num_frames - 1], device="cuda").posed.vertices  # the uncut body's vertices
    # Turned 0.15 rad about the vertical through its centre and raised 1 cm: new normals too.
    c, s = math.cos(0.15), math.sin(0.15)
    turn = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], device="cuda")
    centre = posed.mean(dim=1, keepdim=True)
    inputs.body.update((posed - centre) @ turn.T + centre + torch.tensor([0.0, 0.01, 0.0], device="cuda"))
    eager, g_eager = _eager(x, inputs)
    energy, gradient = captured(x)
    assert bool(((eager.total.detach() - before).abs() > 1e-3 * before.abs()).all())  # the move mattered
    torch.testing.assert_close(energy, eager.total.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gradient, g_eager, rtol=1e-4, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="side streams need a CUDA device; this machine has none")
@pytest.mark.parametrize("side, forks", [("hair_hair", True), ("hair_body", True), ("hair_hair", False)])
def test_contact_terms_side_by_side_equal_one_stream(monkeypatch, side, forks):
    """Whichever contact term runs on the side stream (or none), eager and replayed from a graph,
    the same energy and gradient as everything on one stream, each term in its place."""
    import hairwarp.energy as energy_module
    import hairwarp.runtime as runtime

    x, inputs = _small_inputs("cuda")
    monkeypatch.setattr(runtime, "STREAM_FORKS", False)
    one_stream, g_one = _eager(x, inputs)
    monkeypatch.setattr(runtime, "STREAM_FORKS", forks)
    monkeypatch.setattr(energy_module, "_CONTACT_SIDE", side)
    eager, g_eager = _eager(x, inputs)
    for name in ("hair_body_contact", "hair_hair_contact"):
        torch.testing.assert_close(eager.terms[name], one_stream.terms[name], rtol=1e-5, atol=0)
    torch.testing.assert_close(eager.total, one_stream.total, rtol=1e-5, atol=0)
    torch.testing.assert_close(g_eager, g_one, rtol=1e-4, atol=1e-4)
    energy, gradient = CapturedEnergy(x, inputs, dynamic=True)(x)
    torch.testing.assert_close(energy, one_stream.total.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gradient, g_one, rtol=1e-4, atol=1e-4)
