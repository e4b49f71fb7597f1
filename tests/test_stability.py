"""Stability study: pinned behaviour of the barrier, precision, units, degenerate inputs, divergence."""

import math

import pytest
import torch

from hairwarp.config import EnergyConfig
from hairwarp.energy import total_energy
from hairwarp.evaluation import stability as S
from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape


@pytest.fixture(scope="module")
def tiny():
    scene = comparison_scene("table1", strand_stride=32, num_vertices=10)
    return scene, scene.frames([0])


def test_paper_barrier_traps_deep_vertices_the_others_do_not():
    cfg = EnergyConfig()
    trap = -(cfg.hair_body_xi + cfg.hair_body_dhat)
    depths = torch.tensor([-0.5e-3, -1e-3, -2e-3, -5e-3, -2e-2], dtype=torch.float64)
    paper = S.barrier_trap_1d(depths, "paper", cfg)
    for variant in ("monotone", "quadratic"):
        final = S.barrier_trap_1d(depths, variant, cfg)
        assert bool((final > 0).all()), variant  # every start pushed out
    assert float(paper[0]) > 0  # shallower than the paper barrier's peak (-0.73 mm): escapes
    assert torch.allclose(paper[1:], torch.full((4,), trap, dtype=torch.float64), atol=1e-6)


def test_float32_barrier_near_xi():
    gaps = torch.tensor([1e-5, 1e-7, 1e-10], dtype=torch.float64)
    default = S.barrier_precision(gaps)
    assert float(default["grad_rel_err"].max()) < 1e-4  # the polynomial piece below xi + 15 um
    log_down_to_xi = S.barrier_precision(gaps, bp=1e-7)
    assert float(log_down_to_xi["grad_rel_err"][:2].max()) < 1e-3
    # Documented boundary: float32 rounds d by ~6e-11 m near 1 mm; 0.1 nm above xi the log
    # barrier's gradient is off by tens of percent (still finite).
    assert float(log_down_to_xi["grad_rel_err"][2]) > 0.1
    assert bool(torch.isfinite(log_down_to_xi["grad32"]).all())


def test_centimetres_give_the_same_energy_and_drape(tiny):
    scene, _ = tiny
    frames = scene.frames([0], dtype=torch.float64)
    config = EnergyConfig()
    cm = S.centimetre_config(config)
    inputs_cm = S.scaled_inputs(frames, scene.scene.body.faces)
    x = frames.rigid.positions
    y = x + 1e-3 * torch.randn_like(x)  # off the rigid placement, so every term is non-zero
    for z in (x, y):
        with torch.no_grad():
            e_m = total_energy(z, frames.inputs, config)
            e_cm = total_energy(z * 100, inputs_cm, cm)
        assert float(e_m.terms["hair_body_contact"]) > 0
        # Bending (Eq. 8) is left out: its epsilon is a length in the norm guard but a
        # dimensionless margin in clamp(theta, -1 + eps, 1 - eps), so no rescaling keeps both
        # (0.25 % apart on this scene, 1e-7 J of a 59 J total).
        no_bend_m = float(e_m.total - e_m.terms["bending"])
        assert float(e_cm.total - e_cm.terms["bending"]) == pytest.approx(no_bend_m, rel=1e-9)
    solver = DirectOptimizationConfig(max_iterations=40)
    r_m = optimize_drape(x.float(), S.scaled_inputs(scene.frames([0]), scene.scene.body.faces, 1.0), config, solver)
    r_cm = optimize_drape(x.float() * 100, S.scaled_inputs(scene.frames([0]), scene.scene.body.faces), cm, solver)
    # Same landscape, different paths: torch's L-BFGS takes its first step as min(1, 1/|g|_1)
    # times the gradient and accepts curvature pairs with y.s > 1e-10 (absolute), neither of
    # which scales with the units, so a fixed iteration budget lands at different points
    # (docs/stability.md gives the measured gap).
    e0 = float(total_energy(x.float(), S.scaled_inputs(scene.frames([0]), scene.scene.body.faces, 1.0), config).total)
    # Every tip of this scene starts centimetres inside: with the default barrier's linear
    # push-out force 40 iterations remove about 40 % of the energy (measured 36.6 of 59.9 J).
    assert r_m.loss < 0.7 * e0 and r_cm.loss < 0.7 * e0
    assert r_cm.loss == pytest.approx(r_m.loss, rel=0.25)
    assert float((r_cm.positions / 100 - r_m.positions).norm(dim=-1).mean()) < 1e-2


def test_degenerate_strands_stay_finite(tiny):
    _, frames = tiny
    x0, inputs = S.degenerate_inputs(frames)
    x = x0.clone().requires_grad_(True)
    e = total_energy(x, inputs, EnergyConfig()).total.sum()
    (g,) = torch.autograd.grad(e, x)
    assert math.isfinite(float(e.detach())) and bool(torch.isfinite(g).all())
    result = optimize_drape(x0, inputs, EnergyConfig(), DirectOptimizationConfig(max_iterations=40))
    assert torch.isfinite(result.positions).all() and not result.stop_reason.startswith("diverged")
    reopened = float((result.positions[0, 1, 6] - result.positions[0, 1, 5]).norm())
    assert reopened == pytest.approx(float(inputs.rest_lengths[1, 5]), rel=0.2)  # stretch reopened it


def test_very_long_hair_stays_finite(tiny):
    scene, frames = tiny
    x0, inputs = S.long_hair_inputs(frames, scene.scene.body.faces, 4.0)
    assert float(inputs.rest_lengths.sum(dim=1).max()) > 1.5  # metres: longer than the body is tall/2
    result = optimize_drape(x0, inputs, EnergyConfig(), DirectOptimizationConfig(max_iterations=30))
    assert torch.isfinite(result.positions).all()
    with torch.no_grad():
        assert result.loss < float(total_energy(x0, inputs, EnergyConfig()).total.sum())


@pytest.mark.slow
def test_time_step_ten_times_too_large_stays_finite():
    rows = S.time_step_study(num_frames=3, factors=(10.0,), stride=32, nv=8)
    (row,) = rows
    assert row["finite"] and row["diverged_frames"] == 0


def test_absurd_steps_are_reported_never_nan(tiny):
    _, frames = tiny
    x0 = frames.rigid.positions
    with torch.no_grad():
        e0 = float(total_energy(x0, frames.inputs, EnergyConfig()).total.sum())
    for solver in (DirectOptimizationConfig(method="adam", adam_lr=1e6, max_iterations=10),
                   DirectOptimizationConfig(method="lbfgs", lbfgs_lr=1e8, max_iterations=10),
                   DirectOptimizationConfig(method="lbfgs", max_iterations=10)):
        result = optimize_drape(x0, frames.inputs, EnergyConfig(stretch_weight=1e12), solver)
        assert torch.isfinite(result.positions).all() and math.isfinite(result.loss)
        assert result.loss <= max(e0, float(total_energy(x0, frames.inputs, EnergyConfig(stretch_weight=1e12)).total))


def test_winding_numbers_on_a_sphere():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from meshes import icosphere

    v, f = icosphere(4, radius=1.0)
    v, f = torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.2, 0.1], [1.5, 0.0, 0.0], [0.0, -3.0, 0.0]], dtype=torch.float64)
    w = S.winding_numbers(pts, v, f)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-9)
    check = S.sign_consistency(pts, v, f)
    assert not bool(check["wrong_inside"].any())
    assert check["wrong_outside"].tolist() == [False, False, False, False]  # the centre too (medial)


def test_sign_holds_on_the_medial_axis():
    """Formerly a documented failure (docs/stability.md, "sign holes"): the sign came from the
    pseudo-normal pooled over every face within epsilon of the closest distance, and on the
    medial axis faces from opposite sides cancelled: on a unit icosphere (edge ~0.08) every
    point at the centre and about 40 % of the points 1e-4 from it were called outside. The sign
    now comes from the closest feature's own pseudo-normal (docs/contact.md): none is wrong.
    More medial axes (capsule, slab, the default body's neck and torso) in test_body_sign.py."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from meshes import icosphere

    v, f = icosphere(4, radius=1.0)
    v, f = torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f)
    dirs = torch.randn(100, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    for radius in (0.0, 1e-4, 1e-3):
        check = S.sign_consistency(dirs * radius, v, f)
        assert bool((check["winding"] > 0.5).all())  # all inside: the check cannot pass on nothing
        assert int(check["wrong_outside"].sum()) == 0 and int(check["wrong_inside"].sum()) == 0
        assert bool((check["signed_distance"] < 0).all())
