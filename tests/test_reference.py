"""The implicit-Euler physics reference (Eq. 16 + Eq. 5 minimised per frame)."""

from dataclasses import replace

import pytest
import torch

from hairwarp.energy import total_energy
from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape
from hairwarp.solvers.reference import reference_solver_config, simulate_reference


@pytest.fixture(scope="module")
def whiplash():
    scene = comparison_scene("whiplash", strand_stride=32, num_vertices=10)
    return scene, [scene.frames([i]) for i in range(4)]


def test_first_step_from_rest_dissipates():
    """Still body, hair at rest (x_-1 = x_-2 = x_0): the first implicit-Euler step minimises
    inertia + static energy from x_0, where inertia is zero, so the static energy cannot rise."""
    scene = comparison_scene("medium_rest", strand_stride=32, num_vertices=10)
    frames = scene.frames([0])
    config = scene.energy_config()
    start = optimize_drape(frames.rigid.positions, frames.inputs, config,
                           DirectOptimizationConfig(max_iterations=30)).positions
    result = simulate_reference(lambda t: frames.inputs, 2, config, initial=start)
    assert result.positions.shape == (2, *start.shape)
    with torch.no_grad():
        e0 = float(total_energy(start, frames.inputs, config).total.sum())
        e1 = float(total_energy(result.positions[1], frames.inputs, config).total.sum())
    assert e1 <= e0
    assert float((result.positions[1] - start).norm(dim=-1).max()) > 0  # it did move (not converged at 30 it.)


@pytest.mark.slow
def test_reference_follows_the_motion(whiplash):
    scene, frames = whiplash
    config = scene.energy_config()
    result = simulate_reference(lambda t: frames[t].inputs, len(frames), config)
    x = result.positions
    assert x.shape == (4, 1, *frames[0].rigid.positions.shape[1:])
    assert torch.isfinite(x).all()
    assert result.stop_reasons[0] == "initial" and len(result.iterations) == 4
    assert not any(r.startswith("diverged") for r in result.stop_reasons)
    for t in range(4):  # the fixed vertices ride with the head
        assert torch.allclose(x[t][:, :, :2], frames[t].rigid.positions[:, :, :2])
    # Each step's solution has no more incremental potential (Eq. 6) than its start, the
    # inertial prediction 2 x_{t-1} - x_{t-2} (fixed vertices from the rigid placement).
    for t in range(2, 4):
        inputs = replace(frames[t].inputs, prev=x[t - 1], prev2=x[t - 2])
        guess = torch.cat([frames[t].rigid.positions[:, :, :2], (2 * x[t - 1] - x[t - 2])[:, :, 2:]], dim=2)
        with torch.no_grad():
            e_guess = float(total_energy(guess, inputs, config, dynamic=True).total.sum())
            e_step = float(total_energy(x[t], inputs, config, dynamic=True).total.sum())
        assert e_step <= e_guess
    # The head turns: the hair moves.
    assert float((x[3] - x[0]).norm(dim=-1).max()) > 1e-3


def test_reference_solver_is_tight():
    solver = reference_solver_config()
    assert solver.method == "lbfgs" and solver.min_decrease <= 1e-9


def test_bad_frame_count(whiplash):
    _, frames = whiplash
    with pytest.raises(ValueError, match="num_frames"):
        simulate_reference(lambda t: frames[t].inputs, 0)
