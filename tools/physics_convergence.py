"""Where an implicit-Euler step of the physics converges slowly, and which energy term makes it.

    python3 tools/physics_convergence.py --device cuda --motion whiplash --steps 6,12,18 --out OUT

From the tight trajectory's states (the `reference` setting) at the chosen frames, one step of
the fast solver capped at each iteration count (tolerance 1e-12: only the cap stops it), against
the tight solve of the same step: the mean vertex distance [mm] over all moving vertices and
split by where a vertex is (its index along the strand; whether the tight solution has it
within the hair-body barrier's reach, or within a hair-hair pair's cutoff of another strand)
and the share of the error held by the worst 1 % of strands. Then the same with one energy term
switched off at a time (each against its own tight solve), so that the iteration count a term
costs is read off directly. Writes OUT/physics_convergence.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from dataclasses import replace

import torch


def root_block_solver_class():
    """`PhysicsSolver` with the first `ROOT_BLOCK` moving vertices of each strand preconditioned
    by their own block of the step's Hessian (an experiment): at a step's start the block (the
    targets' 3K x 3K second derivatives of the whole energy, by central differences of the
    gradient, all strands at once) is inverted to the square root, and the solver's variables
    there are z = H^(1/2) t / sqrt(k_min); the other vertices keep the diagonal scaling.
    """
    from hairwarp.config import NUM_FIXED_VERTICES
    from hairwarp.solvers.physics import PhysicsSolver, vertex_stiffness

    K = ROOT_BLOCK

    class RootBlockSolver(PhysicsSolver):
        def __init__(self, rest, rigid, normals, body, energy_config, config):
            super().__init__(rest, rigid, normals, body, energy_config, config)
            m = rigid.shape[1]
            eye = torch.eye(3 * K, device=self.device, dtype=rigid.dtype).expand(m, 3 * K, 3 * K)
            self.block = eye.clone()
            self.block_inverse = eye.clone()
            self.k_min = float(vertex_stiffness(energy_config, rest).min())

        def _assemble(self, z):
            free = z.reshape(self.free_shape)
            b, m = free.shape[:2]
            root = torch.einsum("mij,bmj->bmi", self.block, free[:, :, :K].reshape(b, m, 3 * K)).reshape(b, m, K, 3)
            tail = free[:, :, K:] * self.scale[:, :, K:]
            x = torch.cat([self.rigid[:, :, :NUM_FIXED_VERTICES], root, tail], dim=2)
            from hairwarp.ops.strand_projection import follow_the_leader

            return follow_the_leader(self.rigid, x)

        def _variables(self, x):
            free = x[:, :, NUM_FIXED_VERTICES:]
            b, m = free.shape[:2]
            root = torch.einsum("mij,bmj->bmi", self.block_inverse, free[:, :, :K].reshape(b, m, 3 * K))
            return torch.cat([root.reshape(b, m, K, 3), free[:, :, K:] / self.scale[:, :, K:]], dim=2)

        def step(self):
            start = self.prediction()
            start[:, :, :NUM_FIXED_VERTICES] = self.rigid[:, :, :NUM_FIXED_VERTICES]
            m = start.shape[1]
            eye = torch.eye(3 * K, device=self.device, dtype=start.dtype).expand(m, 3 * K, 3 * K)
            self.block.copy_(eye)
            self.block_inverse.copy_(eye)
            z0 = self._variables(start).contiguous()
            eps = 1.0e-5
            columns = []
            for j in range(3 * K):
                grads = []
                for sign in (1.0, -1.0):
                    z = z0.clone()
                    z[:, :, j // 3, j % 3] += sign * eps
                    grads.append(self._energy(z.reshape(-1), graph_safe=False)[1].reshape(self.free_shape))
                columns.append(((grads[0] - grads[1])[0, :, :K].reshape(m, 3 * K)) / (2 * eps))
            hessian = torch.stack(columns, dim=2).double()
            hessian = 0.5 * (hessian + hessian.transpose(1, 2))
            values, vectors = torch.linalg.eigh(hessian)
            values = values.clamp_min(self.k_min)
            root_k = self.k_min ** 0.5
            block = vectors @ torch.diag_embed(values.rsqrt() * root_k) @ vectors.transpose(1, 2)
            inverse = vectors @ torch.diag_embed(values.sqrt() / root_k) @ vectors.transpose(1, 2)
            self.block.copy_(block.to(start.dtype))
            self.block_inverse.copy_(inverse.to(start.dtype))
            return super().step()

    return RootBlockSolver


# Moving vertices per strand in the experimental root block (`root_block_solver_class`).
ROOT_BLOCK = 4


def add_step_arguments(parser: argparse.ArgumentParser, *, device: str, strand_stride: int, steps: str) -> None:
    """The options every experiment on `TightSteps` takes: --device, --motion, --strand-stride, --steps."""
    parser.add_argument("--device", default=device)
    parser.add_argument("--motion", default="whiplash")
    parser.add_argument("--strand-stride", type=int, default=strand_stride)
    parser.add_argument("--steps", default=steps, help="frames whose step is checked")


class TightSteps:
    """A motion's first frames, simulated at the tight setting (1e-7 m: the steps' 1e-5 m / 100, as
    the session-12 result files were made), and what a step from its states needs: the posed
    frames, one body, the rest lengths and the energy at the motion's frame spacing. Shared by
    this tool and `tools/physics_grouped_lbfgs.py`.
    """

    def __init__(self, motion: str, strand_stride: int, last_step: int, device: torch.device):
        from hairwarp.config import EnergyConfig
        from hairwarp.evaluation.scenes import comparison_scene
        from hairwarp.ops import BodyMesh
        from hairwarp.solvers.physics import PhysicsConfig, simulate_physics

        self.scene = comparison_scene(motion, reduced=False, strand_stride=strand_stride).scene
        frames = list(range(last_step + 1))
        self.energy = EnergyConfig().replace(time_step=1.0 / float(self.scene.motion.fps))
        # the diagonal scaling's tight solves, the yardstick of every result file since session 12
        self.config = PhysicsConfig(tolerance=1e-5, strand_preconditioner=False).tight()
        self.tight = simulate_physics(self.scene, frames, device=device, config=self.config)
        self.posed = self.scene.frames(frames, device=device, build_body=False)
        self.body = BodyMesh(self.posed.posed.vertices[:1],
                             self.scene.body.faces.to(device=device, dtype=torch.int32), bvh="lbvh")
        self.rest = self.scene.rest_lengths.to(device)

    def place(self, solver, t: int) -> None:
        """Put `solver` (of any float type) at step t: the frames t-2..t (the warm start reads the
        rigid placements' history) and the tight states t-1, t-2."""
        d = solver.rigid.dtype
        for k in (t - 2, t - 1, t):
            solver.set_frame(self.posed.rigid.positions[k:k + 1].to(d), self.posed.rigid.normals[k:k + 1].to(d),
                             self.posed.posed.vertices[k:k + 1])
        solver.set_state(self.tight.positions[t - 1].to(d), self.tight.positions[t - 2].to(d))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_step_arguments(parser, device="cuda", strand_stride=1, steps="6,12,18")
    parser.add_argument("--caps", default="8,16,32,48,64,96,128,192")
    parser.add_argument("--variants", default="all,no_hair_hair,no_hair_body,no_root_alignment,no_contact",
                        help="energy variants: all, no_hair_hair, no_hair_body, no_root_alignment, no_contact, no_bending")
    parser.add_argument("--solver-variant", action="append", default=[],
                        help="NAME:FIELD=VALUE,... a PhysicsConfig variant (repeatable); EnergyConfig fields "
                             "switch terms off (hair_hair_weight=0)")
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"),
                        help="the solves' float type (the tight solves of each step too)")
    parser.add_argument("--reference-dtype", default=None, choices=("float32", "float64"),
                        help="the tight solves' float type (default: --dtype)")
    parser.add_argument("--out", default="hairwarp-out")
    args = parser.parse_args(argv)
    from hairwarp.ops import hair_body_signed_distance
    from hairwarp.solvers.physics import PhysicsConfig, PhysicsSolver

    device = torch.device(args.device)
    steps = [int(s) for s in args.steps.split(",")]
    caps = [int(c) for c in args.caps.split(",")]
    setup = TightSteps(args.motion, args.strand_stride, max(steps), device)
    base_energy, tight_config, body, place = setup.energy, setup.config, setup.body, setup.place
    posed, rest = setup.posed, setup.rest
    dtype = getattr(torch, args.dtype)
    reference_dtype = getattr(torch, args.reference_dtype or args.dtype)
    rigid_all = {d: posed.rigid.positions.to(d) for d in {dtype, reference_dtype}}
    normals_all = {d: posed.rigid.normals.to(d) for d in {dtype, reference_dtype}}
    n = rest.shape[1] + 1
    bins = {"2-5": (2, 6), "6-20": (6, 21), "21-60": (21, 61), "61-": (61, n)}
    off = {"all": {}, "no_hair_hair": {"hair_hair_weight": 0.0}, "no_hair_body": {"hair_body_weight": 0.0},
           "no_root_alignment": {"root_alignment_weight": 0.0},
           "no_contact": {"hair_hair_weight": 0.0, "hair_body_weight": 0.0}, "root_block": {},
           "no_bending": {"bending_weight": 0.0}}

    solver_variants = {}
    solver_fields = {f.name for f in dataclasses.fields(PhysicsConfig)}
    for spec in args.solver_variant:
        label, _, fields = spec.partition(":")
        pairs = {k: float(v) for k, v in (f.split("=") for f in fields.split(",") if f)}
        # Fields of PhysicsConfig set the solver; the rest switch energy terms (e.g. hair_hair_weight=0).
        solver_variants[label] = {k: v for k, v in pairs.items() if k in solver_fields}
        off[label] = {k: v for k, v in pairs.items() if k not in solver_fields}
    rows = []
    for name in [v for v in args.variants.split(",") if v] + list(solver_variants):
        energy = base_energy.replace(**off[name])
        reference = PhysicsSolver(rest.to(reference_dtype), rigid_all[reference_dtype][:1],
                                  normals_all[reference_dtype][:1], body, energy, tight_config)
        solutions, where, tight_its = {}, {}, {}
        for t in steps:
            place(reference, t)
            report = reference.step()
            tight_its[t] = report.iterations
            x = reference.prev.clone()
            solutions[t] = x
            with torch.no_grad():
                near_body = hair_body_signed_distance(x[0].float(), body) < energy.hair_body_xi + energy.hair_body_dhat
            # hair-hair: a vertex within the cutoff of a vertex of another strand (a coarse grid).
            cutoff = energy.hair_diameter + energy.hair_hair_dhat
            p = x[0].reshape(-1, 3).float()
            strand = torch.arange(x.shape[1], device=device).repeat_interleave(n)
            cell = torch.floor(p / cutoff).long()
            key = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
            near_hair = torch.zeros(p.shape[0], dtype=torch.bool, device=device)
            order = torch.argsort(key)
            ks, ss = key[order], strand[order]
            same = (ks[1:] == ks[:-1]) & (ss[1:] != ss[:-1])
            near_hair[order[1:][same]] = True
            near_hair[order[:-1][same]] = True
            where[t] = {"near_body": near_body, "near_hair": near_hair.reshape(x.shape[1:3])}
        for cap in caps:
            config = replace(PhysicsConfig(), max_iterations=cap, tolerance=1e-12, **solver_variants.get(name, {}))
            solver_class = root_block_solver_class() if name.startswith("root_block") else PhysicsSolver
            solver = solver_class(rest.to(dtype), rigid_all[dtype][:1], normals_all[dtype][:1], body, energy, config)
            for t in steps:
                place(solver, t)
                solver.step()
                err = (solver.prev.double() - solutions[t].double()).norm(dim=-1)[0] * 1e3  # (M, N) mm
                moving = err[:, 2:]
                per_strand = moving.mean(dim=1)
                worst = torch.topk(per_strand, max(1, per_strand.numel() // 100)).values.sum() / per_strand.sum()
                row = {"variant": name, "cap": cap, "step": t, "tight_iterations": tight_its[t],
                       "mean_mm": float(moving.mean()), "p99_mm": float(torch.quantile(moving.flatten(), 0.99)),
                       "max_mm": float(moving.max()), "worst_1pct_strands_share": float(worst)}
                for label, (a, b) in bins.items():
                    row[f"mean_mm_vertices_{label}"] = float(err[:, a:b].mean())
                for label in ("near_body", "near_hair"):
                    mask = where[t][label][:, 2:]
                    row[f"mean_mm_{label}"] = float(moving[mask].mean()) if bool(mask.any()) else None
                    row[f"share_{label}"] = float(mask.float().mean())
                rows.append(row)
                print(f"{name:18s} cap {cap:4d} step {t:3d}: mean {row['mean_mm']:.3f} p99 {row['p99_mm']:.3f} "
                      f"max {row['max_mm']:.2f} mm; by index "
                      + " ".join(f"{row[f'mean_mm_vertices_{k}']:.3f}" for k in bins)
                      + f"; near body {row['mean_mm_near_body']} near hair {row['mean_mm_near_hair']}; "
                      f"worst 1 % strands {100 * row['worst_1pct_strands_share']:.0f} %; tight its {tight_its[t]}",
                      flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "physics_convergence.json"), "w") as f:
        json.dump({"motion": args.motion, "strand_stride": args.strand_stride, "steps": steps, "caps": caps,
                   "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
