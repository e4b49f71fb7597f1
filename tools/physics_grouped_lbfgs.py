"""An experiment: L-BFGS with one memory per group of strands for the physics' implicit-Euler step.

    python3 tools/physics_grouped_lbfgs.py --device cpu --strand-stride 2 --steps 12,18 --group-strands 0,128

docs/physics.md ("Twelfth session") measured that a step converges slower per iteration as the
strand count grows (64-256 strands: 0.01-0.04 mm from the tight step after 64 iterations; 1 024:
0.45-0.59 mm), with contact or without. Here the direction of each group of `--group-strands`
strands comes from the two-loop recursion over that group's own curvature pairs and scale
(0: one group, the global memory), and one Armijo line search on the total energy keeps the step
safe (the per-strand memory tried earlier failed on its line search, not on its directions).
Torch only, eager, from the tight trajectory's states; an iteration is one energy evaluation (a
rejected trial counts). Prints and writes OUT/physics_grouped_lbfgs.json: the mean distance of
the moving vertices to the tight step [mm] after each cap.
"""

from __future__ import annotations

import argparse
import json
import os

import torch


def grouped_lbfgs(energy, z0: torch.Tensor, groups: torch.Tensor, num_groups: int, caps: list[int], record, *,
                  history: int = 8, max_step: float = 0.02, c1: float = 1e-4, restart: int = 5, precondition=None):
    """Minimise `energy(z) -> (f, g)` from z0 (n,) with a memory per group (`groups`: (n,) group of
    each entry); calls `record(evaluations, z)` when the evaluation count reaches each cap.
    `precondition(q) -> H0 q` (an inverse Hessian's approximation) replaces H0 = gamma I, and the
    first direction -g / max(1, |g|_1) becomes -H0 g."""
    z = z0.clone()
    f, g = energy(z)
    evaluations = 1
    n = z.numel()
    S = torch.zeros(history, n, dtype=torch.float64)
    Y = torch.zeros(history, n, dtype=torch.float64)
    rho = torch.zeros(history, num_groups, dtype=torch.float64)
    gamma = torch.zeros(num_groups, dtype=torch.float64)
    head = -1
    pending = sorted(caps)

    def group_dot(a, b):
        return torch.zeros(num_groups, dtype=torch.float64).index_add_(0, groups, a * b)

    def steepest(grad):
        if precondition is not None:
            return -precondition(grad)
        return -grad * min(1.0, 1.0 / float(grad.abs().sum()))

    def direction(grad):
        if not bool((rho != 0).any()):
            return steepest(grad), True
        q = grad.clone()
        alphas = []
        order = [(head - k) % history for k in range(history)]
        for k in order:
            a = rho[k] * group_dot(S[k], q)
            alphas.append(a)
            q -= a[groups] * Y[k]
        q = q * gamma[groups] if precondition is None else precondition(q)
        for k, a in zip(reversed(order), reversed(alphas)):
            b = rho[k] * group_dot(Y[k], q)
            q += (a - b)[groups] * S[k]
        d = -q
        if float(torch.dot(d, grad)) >= 0:
            return steepest(grad), True
        return d, False

    d, _ = direction(g)
    t = 1.0
    rejections = 0
    while pending:
        largest = float(d.view(-1, 3).norm(dim=1).max())
        step = min(t, max_step / max(largest, 1e-30))
        trial = z + step * d
        f_trial, g_trial = energy(trial)
        evaluations += 1
        slope = float(torch.dot(g, d))
        if f_trial <= f + c1 * step * slope:
            s, y = trial - z, g_trial - g
            sy, ss, yy = group_dot(s, y), group_dot(s, s), group_dot(y, y)
            ok = sy > 1e-10 * ss  # the cautious update, per group
            head = (head + 1) % history
            S[head], Y[head] = s, y
            rho[head] = torch.where(ok, 1.0 / sy.clamp_min(1e-300), torch.zeros_like(sy))
            gamma = torch.where(ok, sy / yy.clamp_min(1e-300), gamma)
            if bool((gamma <= 0).any()) and bool((gamma > 0).any()):  # a group with no pair yet
                gamma = torch.where(gamma > 0, gamma, gamma[gamma > 0].mean())
            z, f, g = trial, f_trial, g_trial
            rejections = 0
            d, _ = direction(g)
            t = 1.0
        else:
            rejections += 1
            # the minimiser of the quadratic through f, the slope and the trial's f, in [0.1, 0.5] t
            denominator = 2.0 * (f_trial - f - slope * step)
            t = step * min(max(-slope * step / denominator if denominator > 0 else 0.5, 0.1), 0.5)
            if rejections >= restart:
                rho.zero_()
                d, _ = direction(g)
                t, rejections = 1.0, 0
        while pending and evaluations >= pending[0]:
            record(pending.pop(0), z)
    return z


def main(argv=None):
    from physics_convergence import add_step_arguments

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_step_arguments(parser, device="cpu", strand_stride=2, steps="12,18")
    parser.add_argument("--caps", default="32,64,96")
    parser.add_argument("--group-strands", default="0,128", help="strands a group (0: one group), comma-separated")
    parser.add_argument("--max-steps", default="0.02",
                        help="the farthest a trial moves a variable's point [m] (`PhysicsConfig.max_step`), "
                             "comma-separated, crossed with --group-strands")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)
    from physics_convergence import TightSteps

    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver

    device = torch.device(args.device)
    steps = [int(s) for s in args.steps.split(",")]
    caps = [int(c) for c in args.caps.split(",")]
    setup = TightSteps(args.motion, args.strand_stride, max(steps), device)
    posed, rest, tight = setup.posed, setup.rest, setup.tight
    solver = PhysicsSolver(rest, posed.rigid.positions[:1], posed.rigid.normals[:1], setup.body, setup.energy,
                           PhysicsConfig())
    m, n = rest.shape[0], rest.shape[1] + 1
    rows = []
    runs = [(int(g), float(s)) for g in args.group_strands.split(",") for s in args.max_steps.split(",")]
    for spec, max_step in runs:
        per_group = m if spec <= 0 else spec
        strand_group = torch.arange(m) // per_group
        groups = strand_group[:, None].expand(m, (n - NUM_FIXED_VERTICES) * 3).reshape(-1)
        num_groups = int(strand_group.max()) + 1
        for t in steps:
            setup.place(solver, t)
            start = solver.prediction()
            start[:, :, :NUM_FIXED_VERTICES] = solver.rigid[:, :, :NUM_FIXED_VERTICES]
            z0 = solver._variables(start).reshape(-1).double()

            def energy(z):
                f, g, _ = solver._energy(z.to(start.dtype), False)
                return float(f), g.double()

            def record(cap, z):
                x = solver._assemble(z.to(start.dtype)).detach()
                distance = float((x - tight.positions[t]).norm(dim=-1)[..., NUM_FIXED_VERTICES:].mean()) * 1e3
                rows.append({"group_strands": per_group, "groups": num_groups, "max_step": max_step, "step": t,
                             "cap": cap, "mean_mm": distance})
                print(f"{per_group:5d} strands a group ({num_groups} groups), max step {max_step:g} m, step {t}, "
                      f"{cap} it.: {distance:.3f} mm", flush=True)

            grouped_lbfgs(energy, z0, groups, num_groups, caps, record, max_step=max_step)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "physics_grouped_lbfgs.json"), "w") as f:
        json.dump({"motion": args.motion, "strand_stride": args.strand_stride, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
