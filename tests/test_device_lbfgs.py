"""L-BFGS with the device-resident backtracking line search (`hairwarp.solvers.device_lbfgs`)."""

import pytest
import torch

from hairwarp.config import EnergyConfig
from hairwarp.energy import total_energy
from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.metrics import length_change_percent, penetration_percent
from hairwarp.solvers.device_lbfgs import DeviceLBFGS, lbfgs_direction
from hairwarp.solvers.direct import DirectOptimizationConfig, optimize_drape

# The tiny Table 1 scene of tests/test_direct.py (and its quartic barrier, for the same reason).
_STRIDE, _NV = 32, 12
_CONFIG = EnergyConfig(barrier_variant="monotone")


@pytest.fixture(scope="module")
def table1():
    return comparison_scene("table1", strand_stride=_STRIDE, num_vertices=_NV).frames([0])


def _two_loop(g, pairs, gamma):
    """The textbook two-loop recursion (Nocedal & Wright, Algorithm 7.4), float64, pairs oldest first."""
    q = g.clone()
    alphas = []
    for s, y in reversed(pairs):
        a = (s @ q) / (s @ y)
        alphas.append(a)
        q = q - a * y
    r = gamma * q
    for (s, y), a in zip(pairs, reversed(alphas)):
        b = (y @ r) / (s @ y)
        r = r + s * (a - b)
    return -r


@pytest.mark.parametrize("filled", [0, 1, 3, 5])
@pytest.mark.parametrize("head", [0, 3])
def test_lbfgs_direction_equals_the_two_loop_recursion(filled, head):
    """Rows newest first from `head` backwards around the ring (the solver's layout), stale rows
    (rho = 0) holding garbage that must be ignored."""
    gen = torch.Generator().manual_seed(filled)
    n, m = 40, 5
    hessian = torch.randn(n, n, generator=gen, dtype=torch.float64)
    hessian = hessian @ hessian.T / n + torch.eye(n, dtype=torch.float64)
    pairs = []  # oldest first, with y = H s (so s.y > 0)
    for _ in range(filled):
        s = torch.randn(n, generator=gen, dtype=torch.float64)
        pairs.append((s, hessian @ s))
    g = torch.randn(n, generator=gen, dtype=torch.float64)
    gamma = float(pairs[-1][0] @ pairs[-1][1] / (pairs[-1][1] @ pairs[-1][1])) if pairs else 0.3
    expected = _two_loop(g, pairs, gamma)
    S = torch.randn(m, n, generator=gen)  # stale rows: ignored where rho = 0
    Y = torch.randn(m, n, generator=gen)
    rho = torch.zeros(m)
    order = (head - torch.arange(m)) % m
    for k, (s, y) in enumerate(reversed(pairs)):  # newest first
        row = int(order[k])
        S[row], Y[row], rho[row] = s.float(), y.float(), float(1.0 / (s @ y))
    d = lbfgs_direction(g.float(), S, Y, rho, torch.tensor(gamma), order=order)
    torch.testing.assert_close(d.double(), expected, rtol=2e-4, atol=2e-5 * float(expected.abs().max()))
    assert float(g.float() @ d) < 0  # a descent direction


def _rosenbrock(x, graph_safe):
    """Sum of 2-D Rosenbrock valleys over consecutive pairs, NaN where any x > 3 (a trial step
    that far must be rejected, never taken)."""
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        a, b = x[0::2], x[1::2]
        f = (100.0 * (b - a * a) ** 2 + (1.0 - a) ** 2).sum()
        f = torch.where((x > 3.0).any(), torch.full_like(f, float("nan")), f)
        (g,) = torch.autograd.grad(f, x)
    return f.detach(), g, 0


def test_backtracking_lbfgs_minimises_rosenbrock_and_never_climbs():
    x0 = torch.tensor([-1.2, 1.0, -0.5, 2.0, 0.0, 0.0], dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=5, lbfgs_max_step=10.0)
    opt = DeviceLBFGS(_rosenbrock, x0, solver, chunk=1, point_size=2)
    losses = [float(opt.f)]
    for _ in range(300):
        opt.iterate()
        losses.append(float(opt.trace[0]))
    assert all(b <= a for a, b in zip(losses, losses[1:]))  # Armijo: never an increase
    assert all(torch.isfinite(torch.tensor(losses)))  # NaN trials rejected, not taken
    assert losses[0] > 10.0
    torch.testing.assert_close(opt.x, torch.ones(6, dtype=torch.float64), atol=1e-4, rtol=0)


def test_max_step_bounds_every_trial():
    seen = []

    def energy(x, graph_safe):
        seen.append(x.detach().clone())
        return _rosenbrock(x, graph_safe)

    x0 = torch.tensor([-1.2, 1.0, 2.5, -2.0], dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_max_step=0.05)
    opt = DeviceLBFGS(energy, x0, solver, chunk=1, point_size=2)
    for _ in range(20):
        before = opt.x.clone()
        opt.iterate()
        move = (seen[-1] - before).reshape(-1, 2).norm(dim=1).max()
        assert float(move) <= 0.05 * (1 + 1e-9)
    assert float(opt.f) < float(_rosenbrock(x0, False)[0])


def test_backtracking_drape_lowers_energy_like_strong_wolfe(table1):
    x0 = table1.rigid.positions
    pen0 = float(penetration_percent(x0, table1.body_mesh))
    assert pen0 > 30.0
    runs = {}
    for line_search in ("strong_wolfe", "backtracking"):
        solver = DirectOptimizationConfig(max_iterations=80, patience=80, lbfgs_line_search=line_search)
        runs[line_search] = optimize_drape(x0, table1.inputs, _CONFIG, solver)
    result = runs["backtracking"]
    x = result.positions
    assert torch.equal(x[:, :, :2], x0[:, :, :2])
    with torch.no_grad():
        e0 = float(total_energy(x0, table1.inputs, _CONFIG).total.sum())
        e = float(total_energy(x, table1.inputs, _CONFIG).total.sum())
    assert result.loss == pytest.approx(e, rel=1e-4)
    assert result.iterations == 80 and result.evaluations == 81
    losses = [h["loss"] for h in result.history]
    assert losses[0] == pytest.approx(e0, rel=1e-5)
    assert all(b <= a for a, b in zip(losses, losses[1:]))
    # As good as torch's strong-Wolfe L-BFGS for the same number of energy evaluations (within 50 %).
    assert result.loss < 0.01 * e0
    assert result.loss < 1.5 * runs["strong_wolfe"].loss
    assert float(penetration_percent(x, table1.body_mesh)) < 0.5 * pen0
    assert float(length_change_percent(x, table1.inputs.rest_lengths)) < 2.0


def test_backtracking_records_metrics_every_chunk_and_stops_on_patience(table1):
    calls = []

    def metrics(x):
        calls.append(x.shape)
        return {"penetration": float(penetration_percent(x, table1.body_mesh))}

    solver = DirectOptimizationConfig(max_iterations=40, patience=500, record_every=10,
                                      lbfgs_line_search="backtracking")
    result = optimize_drape(table1.rigid.positions, table1.inputs, _CONFIG, solver, metrics=metrics)
    assert [h["iteration"] for h in result.history] == [0, 10, 20, 30, 40]
    assert all("penetration" in h for h in result.history) and len(calls) == 5
    times = [h["time_s"] for h in result.history]
    assert all(b >= a for a, b in zip(times, times[1:]))
    # Patience: a drape already at its optimum stops after `patience` iterations without decrease.
    stalled = optimize_drape(result.positions, table1.inputs, _CONFIG, DirectOptimizationConfig(
        max_iterations=400, patience=5, lbfgs_chunk=5, min_decrease=1e-2, lbfgs_line_search="backtracking"))
    assert stalled.stop_reason == "patience" and stalled.iterations < 400


def test_line_search_option_is_checked():
    with pytest.raises(ValueError, match="lbfgs_line_search"):
        DirectOptimizationConfig(lbfgs_line_search="wolfe")
    with pytest.raises(ValueError, match="lbfgs_chunk"):
        DirectOptimizationConfig(lbfgs_chunk=0)
    with pytest.raises(ValueError, match="lbfgs_max_step"):
        DirectOptimizationConfig(lbfgs_max_step=0.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device; this machine has none")
def test_cuda_graph_backtracking_equals_eager():
    frames = comparison_scene("table1", strand_stride=_STRIDE, num_vertices=_NV).frames([0], device="cuda")
    runs = []
    for graph in (False, True):
        solver = DirectOptimizationConfig(max_iterations=30, patience=100, lbfgs_chunk=10, cuda_graph=graph,
                                          lbfgs_line_search="backtracking")
        runs.append(optimize_drape(frames.rigid.positions, frames.inputs, _CONFIG, solver))
    eager, graph = runs
    assert graph.iterations == eager.iterations == 30
    assert graph.loss == pytest.approx(eager.loss, rel=1e-3)
    torch.testing.assert_close(graph.positions, eager.positions, atol=1e-4, rtol=0)


@pytest.mark.parametrize("passes", ["warp", "torch"])
def test_kept_curvature_products_equal_recomputed_ones(passes):
    """The solver keeps s_k . y_j as pairs enter (two products per step); after many steps,
    stores, skips and clears it equals S Y^T computed afresh."""
    x0 = torch.tensor([-1.2, 1.0, -0.5, 2.0, 0.0, 0.0], dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=4, lbfgs_max_step=10.0)
    opt = DeviceLBFGS(_rosenbrock, x0, solver, chunk=1, point_size=2, passes=passes)
    for _ in range(25):
        opt.iterate()
        torch.testing.assert_close(opt.SY, opt.S @ opt.Y.T, rtol=1e-9, atol=1e-12)
    assert bool((opt.rho > 0).all())  # the memory filled up, so the shifts were exercised


def test_auto_line_search_is_backtracking_only_on_cuda_graphs():
    from hairwarp.solvers.direct import line_search

    auto = DirectOptimizationConfig()
    assert line_search(auto, torch.device("cpu")) == "strong_wolfe"
    assert line_search(auto, torch.device("cuda")) == "backtracking"
    assert line_search(DirectOptimizationConfig(cuda_graph=False), torch.device("cuda")) == "strong_wolfe"
    assert line_search(DirectOptimizationConfig(lbfgs_line_search="backtracking"), torch.device("cpu")) == "backtracking"


@pytest.mark.parametrize("passes", ["warp", "torch"])
def test_kernel_direction_equals_the_closed_form_through_stores_skips_and_clears(passes):
    """The direction `iterate` leaves for the next trial (Warp kernels: block sums over n, the two
    loops on one thread) equals `lbfgs_direction` on the same state, step after step around the
    ring; where the memory's direction does not descend (or the memory is empty) it is
    -min(1, 1/|g|_1) g."""
    x0 = torch.tensor([-1.2, 1.0, -0.5, 2.0, 0.0, 0.0, 1.5, -0.3], dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=3, lbfgs_max_step=10.0,
                                      lbfgs_restart=1)  # every rejection clears the memory
    opt = DeviceLBFGS(_rosenbrock, x0, solver, chunk=1, point_size=2, passes=passes)
    used = fallback = 0
    for _ in range(60):
        opt.iterate()
        m = opt.rho.shape[0]
        order = (opt.head - torch.arange(m)) % m
        if float(opt.rho[opt.head]) != 0.0:
            expected = lbfgs_direction(opt.g, opt.S, opt.Y, opt.rho, opt.gamma, opt.SY, order)
            torch.testing.assert_close(opt.direction(), expected, rtol=1e-9, atol=1e-12)
            used += 1
        else:
            first = min(1.0, 1.0 / float(opt.g.abs().sum()))
            torch.testing.assert_close(opt.direction(), -first * opt.g, rtol=1e-12, atol=0.0)
            fallback += 1
    assert used >= 10 and fallback >= 5  # both branches, many times


def _stiff_quartic(x, graph_safe):
    """A badly scaled convex quadratic plus a quartic over points of three (float64), for many
    stores and a full ring."""
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        scales = torch.logspace(0, 3, x.numel(), dtype=x.dtype)
        f = 0.5 * (scales * (x - 0.3) ** 2).sum() + 0.25 * (x.view(-1, 3).square().sum(dim=1) ** 2).sum()
        (g,) = torch.autograd.grad(f, x)
    return f.detach(), g, 0


def test_warp_and_torch_passes_take_the_same_steps():
    """The passes over n as Warp kernels with block sums (the CUDA path, run here on the CPU) and as
    torch products (the CPU path) feed the same decisions: the same iterates, losses, memory and
    next direction, step after step, through rejections and a wrapped ring."""
    gen = torch.Generator().manual_seed(3)
    x0 = 3 * torch.randn(3 * 67, generator=gen, dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=5, lbfgs_max_step=2.0)
    runs = {p: DeviceLBFGS(_stiff_quartic, x0, solver, chunk=1, passes=p) for p in ("warp", "torch")}
    rejected = 0
    for _ in range(40):
        for opt in runs.values():
            opt.iterate()
        warp_run, torch_run = runs["warp"], runs["torch"]
        rejected += int(warp_run.flags[0]) == 0
        # The sums' order differs (block sums against products), so float64 rounding, growing slowly.
        for name in ("x", "g", "f", "S", "Y", "rho", "SY", "gamma", "head", "t", "g_norm1", "gmax"):
            expected = getattr(torch_run, name)
            scale = float(expected.abs().max()) if expected.is_floating_point() else 0.0
            torch.testing.assert_close(getattr(warp_run, name), expected, rtol=1e-8, atol=1e-10 * max(1.0, scale),
                                       msg=name)
        torch.testing.assert_close(warp_run.direction(), torch_run.direction(), rtol=1e-8, atol=1e-10)
    assert float(runs["warp"].f) < 0.05 * float(_stiff_quartic(x0, False)[0])
    assert bool((runs["warp"].rho > 0).all())  # the ring filled and wrapped
    assert rejected >= 1


def test_torch_passes_are_refused_off_the_cpu():
    with pytest.raises(ValueError, match="passes"):
        DeviceLBFGS(_rosenbrock, torch.zeros(4, dtype=torch.float64), DirectOptimizationConfig(), chunk=1,
                    point_size=2, passes="numpy")


def test_refresh_gives_the_memorys_direction_at_the_iterate():
    """`refresh` (the physics' pair-list rebuild): the energy at x again and the two-loop direction
    from the kept memory, equal to `lbfgs_direction` on that state; t back to 1."""
    gen = torch.Generator().manual_seed(5)
    x0 = 3 * torch.randn(3 * 20, generator=gen, dtype=torch.float64)
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=4, lbfgs_max_step=2.0)
    opt = DeviceLBFGS(_stiff_quartic, x0, solver, chunk=1)
    for _ in range(11):  # a full ring, wrapped
        opt.iterate()
    f_before = float(opt.f)
    opt.t.fill_(0.25)
    opt.refresh()
    m = opt.rho.shape[0]
    order = (opt.head - torch.arange(m)) % m
    expected = lbfgs_direction(opt.g, opt.S, opt.Y, opt.rho, opt.gamma, opt.SY, order)
    torch.testing.assert_close(opt.direction(), expected, rtol=1e-9, atol=1e-12)
    assert float(opt.f) == pytest.approx(f_before, rel=1e-12) and float(opt.t) == 1.0
    assert bool((opt.rho > 0).all())


def test_a_restart_without_memory_repeats_a_fresh_solver_bit_for_bit():
    """`restart_at` with the memory cleared starts the ring where a new solver does, so a solver
    reused for a second problem (a teacher's second start, a static drape's restart) takes the
    steps a fresh one takes, to the bit (the products over the ring's rows run in row order)."""
    gen = torch.Generator().manual_seed(7)
    first, second = (torch.randn(3 * 4000, generator=gen) for _ in range(2))
    solver = DirectOptimizationConfig(lbfgs_line_search="backtracking", lbfgs_history=8, lbfgs_max_step=2.0)
    reused = DeviceLBFGS(_stiff_quartic, first, solver, chunk=1)
    for _ in range(13):  # the ring part filled, its head moved on
        reused.iterate()
    reused.restart_at(second)
    fresh = DeviceLBFGS(_stiff_quartic, second, solver, chunk=1)
    for _ in range(30):
        reused.iterate()
        fresh.iterate()
    assert torch.equal(reused.x, fresh.x) and torch.equal(reused.f, fresh.f)
