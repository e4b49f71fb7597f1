"""An experiment: Newton steps on each strand's own Hessian for the physics' implicit-Euler step.

    python3 tools/physics_strand_newton.py --device cpu --strand-stride 16 --steps 6 --iterations 5 --out OUT
    python3 tools/physics_strand_newton.py --strand-stride 16 --steps 6 --iterations 0 \
        --preconditioners string,hessian --out OUT

What it found (thirteenth session, docs/physics.md section 1): without the segments' tension
(`--tension 0`) the Newton steps' line search cut every step to 1/4-1/16 even with contact and
bending off: on the rest lengths a hanging strand's restoring force is its tension, which the
energy's Hessian at exact lengths lacks. With it, steps of length 1; hair-hair contact (left out
of the per-strand Hessian) is what still shortens them. As L-BFGS's H0 (`--preconditioners
hessian`) the same matrix reached the tight step in 16 evaluations where L-BFGS took 64: the
origin of `PhysicsConfig.strand_preconditioner`.

docs/physics.md ("Twelfth session") found that L-BFGS needs ~100 iterations a step at full size
and that the error it leaves is spread over every strand, from the root to the tips. Here each
iteration takes a Newton direction per strand instead: the Hessian of the step's energy in the
positions (stretch included: its k_s makes the step keep the segment lengths to first order, as
follow-the-leader keeps them exactly) by central differences of the gradient, five vertex colours
x three coordinates at once over all strands (the strand terms couple a vertex with its two
neighbours on each side; hair-hair contact, which couples strands, is left out of the Hessian),
each strand's 3(N-2) x 3(N-2) block made positive definite (eigenvalues at least the inertia's)
and solved. The trial x + t d goes through follow-the-leader onto the rest lengths, and an Armijo
line search on the whole energy (hair-hair included) takes it. `--reuse` keeps the first
iteration's Hessian for the step (one Hessian a step). Torch only, eager, from the tight
trajectory's states (`TightSteps`); prints and writes OUT/physics_strand_newton.json: the mean
distance of the moving vertices to the tight step [mm] after each iteration and the energy
evaluations it took (the Hessian's 30 gradients counted).
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace

import torch

NUM_FIXED = 2  # hairwarp.config.NUM_FIXED_VERTICES
COLOURS = 5  # a vertex couples with vertices up to two away along its strand (bending, smoothness)


def k_inertia_of(energy, m: int, v: int) -> float:
    """The inertia's stiffness per moving vertex [J/m^2] (Eq. 16's Hessian)."""
    return energy.inertia_weight * energy.vertex_mass / (m * v * energy.time_step ** 2)


def banded_hessian(gradient, x_free: torch.Tensor, h: float) -> torch.Tensor:
    """Per-strand dense Hessian blocks (M, 3V, 3V) of `gradient(x_free) -> (M, V, 3)` by central
    differences, 15 colour/coordinate columns at once (entries beyond two vertices are zero)."""
    m, v, _ = x_free.shape
    H = torch.zeros(m, v, 3, v, 3, dtype=torch.float64, device=x_free.device)
    index = torch.arange(v, device=x_free.device)
    for colour in range(COLOURS):
        mask = (index % COLOURS) == colour
        for k in range(3):
            step = torch.zeros_like(x_free)
            step[:, mask, k] = h
            column = (gradient(x_free + step).double() - gradient(x_free - step).double()) / (2 * h)  # (M, V, 3)
            # Vertex i reads the perturbed vertex j of this colour within two of it.
            offset = (colour - index) % COLOURS
            offset = torch.where(offset > 2, offset - COLOURS, offset)
            j = index + offset
            ok = (j >= 0) & (j < v)
            i_ok, j_ok = index[ok], j[ok]
            H[:, i_ok, :, j_ok, k] = column[:, i_ok, :].permute(1, 0, 2)  # advanced indices come first
    H = H.reshape(m, 3 * v, 3 * v)
    return 0.5 * (H + H.transpose(1, 2))


def tension_stiffness(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The rest lengths' share of the Hessian of the Lagrangian, (M, 3V, 3V) over the moving vertices:
    the dense float64 form, for this experiment, of what the solver's
    `hairwarp.kernels.strand_preconditioner.segment_tension_stiffness_kernel` adds to its bands.

    On the rest lengths a segment's tension lambda_e (the multiplier of |x_{e+1} - x_e| = l_e) stiffens
    the strand across the segment by lambda_e / l_e (I - u u^T): a hanging strand is a pendulum
    whose restoring force is its weight's tension, which the energy's own Hessian at exact lengths
    lacks. The tensions come from the force balance along the strand, tip to root (least squares
    of g + sum_e lambda_e grad c_e = 0): lambda_{i-1} = -(g_i - lambda_i u_i) . u_{i-1}.
    x: (M, N, 3) positions on the rest lengths; g: (M, V, 3) the energy's gradient at the moving
    vertices (V = N - 2).
    """
    m, n, _ = x.shape
    v = n - NUM_FIXED
    e = x[:, 1:] - x[:, :-1]  # (M, N-1, 3) segment e joins vertices e and e+1
    length = e.norm(dim=-1, keepdim=True)
    u = e / length
    lam = torch.zeros(m, n - 1, dtype=x.dtype, device=x.device)
    carry = torch.zeros(m, 3, dtype=x.dtype, device=x.device)  # lambda_i u_i of the segment beyond vertex i
    for i in range(n - 1, NUM_FIXED - 1, -1):  # moving vertex i, segment i-1 before it
        force = g[:, i - NUM_FIXED] - carry
        lam[:, i - 1] = -(force * u[:, i - 1]).sum(-1)
        carry = lam[:, i - 1, None] * u[:, i - 1]
    # A compressed segment (lambda < 0) would soften the strand: kept at zero (a positive definite
    # matrix; the line search sees the rest).
    block = (lam.clamp_min(0.0) / length[..., 0])[..., None, None] * (torch.eye(3, dtype=x.dtype, device=x.device)
                                                       - u[..., :, None] * u[..., None, :])  # (M, N-1, 3, 3)
    H = torch.zeros(m, v, 3, v, 3, dtype=x.dtype, device=x.device)
    for seg in range(NUM_FIXED - 1, n - 1):  # segments with a moving end (segment 1 joins fixed 1 and moving 2)
        a, b = seg - NUM_FIXED, seg + 1 - NUM_FIXED  # moving indices of its ends (a < 0: fixed)
        H[:, b, :, b, :] += block[:, seg]
        if a >= 0:
            H[:, a, :, a, :] += block[:, seg]
            H[:, a, :, b, :] -= block[:, seg]
            H[:, b, :, a, :] -= block[:, seg]
    return H.reshape(m, 3 * v, 3 * v), lam


def string_matrix(energy, x: torch.Tensor, g: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """The strand's stiffness without bending and contact, (M, 3V, 3V): inertia and the auxiliary
    pull (diagonal), smoothness (second differences), root alignment's diagonal
    (`vertex_stiffness`) and the segments' tension (`tension_stiffness`)."""
    from hairwarp.solvers.physics import vertex_stiffness

    m, n, _ = x.shape
    v = n - NUM_FIXED
    eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
    smooth = 2.0 * energy.smoothness_weight / (m * (n - 2))
    second = torch.zeros(n - 2, n, dtype=x.dtype, device=x.device)  # joints 1..N-2
    idx = torch.arange(n - 2, device=x.device)
    second[idx, idx] = 1.0
    second[idx, idx + 1] = -2.0
    second[idx, idx + 2] = 1.0
    lap = smooth * (second.T @ second)[NUM_FIXED:, NUM_FIXED:]  # (V, V)
    diagonal = vertex_stiffness(energy.replace(smoothness_weight=0.0), rest).to(x.dtype)  # (M, V) inertia, aux, root
    H = torch.kron(lap, eye3)[None].expand(m, 3 * v, 3 * v).clone()
    H += torch.diag_embed(diagonal.repeat_interleave(3, dim=1))
    H += tension_stiffness(x, g)[0]
    return H


def main(argv=None):
    from physics_convergence import add_step_arguments

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_step_arguments(parser, device="cpu", strand_stride=2, steps="6,12")
    parser.add_argument("--iterations", type=int, default=12)
    parser.add_argument("--lbfgs-caps", default="16,32,64")
    parser.add_argument("--preconditioners", default="",
                        help="L-BFGS runs with H0 from: hessian (the Newton matrix), string (string_matrix), none")
    parser.add_argument("--caps", default="16,32,48,64,96", help="the preconditioned L-BFGS runs' caps")
    parser.add_argument("--reuse", action="store_true", help="one Hessian a step (the first iteration's)")
    parser.add_argument("--hessian-hair-hair", action="store_true", help="hair-hair contact in the Hessian too")
    parser.add_argument("--tension", type=int, default=1, help="add the segments' tension stiffness (1) or not (0)")
    parser.add_argument("--h", type=float, default=1e-7, help="finite-difference step [m] (float64)")
    parser.add_argument("--off", default="", help="energy weights set to 0 in the Newton solves (NAME,...; "
                        "the tight steps keep them: compare the energies' decrease, not the distances)")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)
    from physics_convergence import TightSteps

    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver

    device = torch.device(args.device)
    steps = [int(s) for s in args.steps.split(",")]
    setup = TightSteps(args.motion, args.strand_stride, max(steps), device)
    energy = setup.energy.replace(**{f"{name}_weight": 0.0 for name in args.off.split(",") if name})
    rest = setup.rest
    rigid = setup.posed.rigid.positions[:1]
    normals = setup.posed.rigid.normals[:1]
    rows = []
    for t in steps:
        tight = setup.tight.positions[t][0].double()  # (M, N, 3)
        # The L-BFGS (the default solver) at its caps, for the comparison in the same run.
        for cap in [int(c) for c in args.lbfgs_caps.split(",") if c]:
            solver = PhysicsSolver(rest, rigid, normals, setup.body, energy,
                                   replace(PhysicsConfig(), max_iterations=cap, tolerance=1e-12))
            setup.place(solver, t)
            solver.step()
            err = (solver.prev[0].double() - tight).norm(dim=-1)[:, 2:].mean() * 1e3
            rows.append({"step": t, "solver": "lbfgs", "evaluations": cap, "mean_mm": float(err)})
            print(f"step {t} lbfgs {cap:4d} evaluations: mean {float(err):.4f} mm", flush=True)
        # float64 solvers: on the rest lengths (follow-the-leader, the line search's energy) and
        # in the positions (stretch as a term: the Hessian's and the gradient's energy).
        d = torch.float64
        on_lengths = PhysicsSolver(rest.to(d), rigid.to(d), normals.to(d), setup.body, energy,
                                   replace(PhysicsConfig(), stiffness_scaling=0.0))
        in_positions = PhysicsSolver(rest.to(d), rigid.to(d), normals.to(d), setup.body, energy,
                                     replace(PhysicsConfig(), stiffness_scaling=0.0, inextensible=False))
        hessian_energy = energy if args.hessian_hair_hair else energy.replace(hair_hair_weight=0.0)
        for_hessian = PhysicsSolver(rest.to(d), rigid.to(d), normals.to(d), setup.body, hessian_energy,
                                    replace(PhysicsConfig(), stiffness_scaling=0.0, inextensible=False))
        for s in (on_lengths, in_positions, for_hessian):
            setup.place(s, t)
        shape = on_lengths.free_shape
        m, v = shape[1], shape[2]

        def f_on_lengths(free):
            f, g, _ = on_lengths._energy(free.reshape(-1), graph_safe=False)
            return float(f)

        def grad_positions(free, solver=in_positions):
            return solver._energy(free.reshape(-1), graph_safe=False)[1].reshape(m, v, 3)

        start = on_lengths.prediction()
        start[:, :, :NUM_FIXED_VERTICES] = on_lengths.rigid[:, :, :NUM_FIXED_VERTICES]
        x = on_lengths._assemble(on_lengths._variables(start)).detach()[0]  # on the rest lengths
        for name in [p for p in args.preconditioners.split(",") if p]:
            from physics_grouped_lbfgs import grouped_lbfgs

            free0 = x[:, NUM_FIXED_VERTICES:].contiguous()
            g0 = grad_positions(free0).double()
            precondition = None
            if name != "none":
                if name == "hessian":
                    P = banded_hessian(lambda z: grad_positions(z, for_hessian), free0, args.h)
                    P = P + tension_stiffness(x, g0)[0]
                    lam, vec = torch.linalg.eigh(P)
                    lam = lam.clamp_min(k_inertia_of(energy, m, v))
                    P = vec @ torch.diag_embed(lam) @ vec.transpose(1, 2)
                else:
                    P = string_matrix(energy, x, g0, rest.to(d))
                factor = torch.linalg.cholesky(P)

                def precondition(q, factor=factor):
                    return torch.cholesky_solve(q.reshape(m, 3 * v, 1), factor).reshape(-1)

            def energy_z(z):
                f, g, _ = on_lengths._energy(z, False)
                return float(f), g.double()

            def record(cap, z, name=name):
                xz = on_lengths._assemble(z).detach()[0]
                err = float((xz - tight).norm(dim=-1)[:, 2:].mean() * 1e3)
                rows.append({"step": t, "solver": f"lbfgs_{name}", "evaluations": cap, "mean_mm": err})
                print(f"step {t} lbfgs H0={name} {cap:4d} evaluations: mean {err:.4f} mm", flush=True)

            groups = torch.zeros(free0.numel(), dtype=torch.long)
            grouped_lbfgs(energy_z, free0.reshape(-1), groups, 1, [int(c) for c in args.caps.split(",")], record,
                          precondition=precondition)
        if args.iterations == 0:
            continue
        k_inertia = k_inertia_of(energy, m, v)
        evaluations, hessian, f = 0, None, f_on_lengths(x[:, NUM_FIXED_VERTICES:])
        evaluations += 1
        for it in range(1, args.iterations + 1):
            free = x[:, NUM_FIXED_VERTICES:].contiguous()
            g = grad_positions(free).double().reshape(m, 3 * v)
            evaluations += 1
            if hessian is None or not args.reuse:
                H = banded_hessian(lambda z: grad_positions(z, for_hessian), free, args.h)
                evaluations += 6 * COLOURS
                if args.tension:
                    H = H + tension_stiffness(x, g.reshape(m, v, 3))[0]
                lam, vec = torch.linalg.eigh(H)
                lam = lam.clamp_min(k_inertia)
                hessian = (lam, vec)
            lam, vec = hessian
            direction = -(vec @ ((vec.transpose(1, 2) @ g[..., None]) / lam[..., None]))[..., 0]
            direction = direction.reshape(m, v, 3)
            slope = float((direction.reshape(-1) * g.reshape(-1)).sum())
            step, accepted = 1.0, False
            for _ in range(20):
                trial = free + step * direction
                f_trial = f_on_lengths(trial)
                evaluations += 1
                if f_trial <= f + 1e-4 * step * slope:
                    accepted = True
                    break
                step *= 0.5
            if accepted:
                xs = torch.cat([x[:, :NUM_FIXED_VERTICES], free + step * direction], dim=1)[None]
                x = on_lengths._assemble(on_lengths._variables(xs)).detach()[0]
                f = f_trial
            err = (x - tight).norm(dim=-1)[:, 2:].mean() * 1e3
            rows.append({"step": t, "solver": "newton_reuse" if args.reuse else "newton", "iteration": it,
                         "evaluations": evaluations, "mean_mm": float(err), "step_length": step if accepted else 0.0,
                         "energy": f})
            print(f"step {t} newton it {it:2d} ({evaluations:4d} evaluations): mean {float(err):.4f} mm, "
                  f"t {step if accepted else 0.0:.3g}, E {f:.8g}", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "physics_strand_newton.json"), "w") as fh:
        json.dump({"motion": args.motion, "strand_stride": args.strand_stride, "steps": steps, "reuse": args.reuse,
                   "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
