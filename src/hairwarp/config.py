"""Physical constants and loss weights of the hair energy (HairFormer Section 3.4, Eq. 5-16).

The paper hardcodes its physical parameters; here every weight and constant is a field of one
dataclass, readable and changeable at run time (`dataclasses.replace(cfg, bending_weight=0)`).
Units: metres, seconds, kilograms; energies in joules where the term is physical (gravity,
inertia), otherwise in the weight's units times the dimensionless or squared-metre measure the
equation sums.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

# The loss terms in the order the fused kernels report them (columns of the per-term output).
STRAND_TERMS = (
    "stretch",  # Eq. 7
    "bending",  # Eq. 8
    "auxiliary",  # Eq. 9
    "smoothness",  # Eq. 10
    "gravity",  # Eq. 11
    "root_alignment",  # Eq. 15
    "inertia",  # Eq. 16
)
CONTACT_TERMS = (
    "hair_body_contact",  # Eq. 12 with d = signed distance to the body
    "hair_hair_contact",  # Eq. 12 with d = segment-segment distance
)
ALL_TERMS = STRAND_TERMS + CONTACT_TERMS
# Vertices 0 and 1 of every strand are fixed to the scalp (the paper): no method, deformation
# or optimizer moves them, and the metrics of Table 1 count only the others.
NUM_FIXED_VERTICES = 2
# Extrapolations of the contact barrier below its join point (`hairwarp.ops.barrier`), in the
# order of the kernels' integer ids.
BARRIER_VARIANTS = ("paper", "monotone", "quadratic")


@dataclass
class EnergyConfig:
    """Weights and physical constants of the total energy (Eq. 5 static, Eq. 6 dynamic).

    The paper gives no values. Ours were chosen on the default scene (long straight hair on
    the default body at rest, 1024 x 100). With them and the default "quadratic" barrier,
    150 L-BFGS iterations on a 2-core CPU take the comparison scenes (every 8th root x 100
    vertices) from 48.4 % to 9.3 % penetration at 4.0 % mean length change ("table1", every
    tip centimetres inside) and from 2.7-7.0 % to 0 % at 0.03 % ("medium_poses"); with the
    quartic "monotone" barrier the first stalls at 48.4 % / 35.5 % (60 iterations): its
    force at depth stretches the strands instead of moving them. Mind the normalisations of
    the paper: Eq. 7, 9, 10, 15, 16 are means over vertices or segments (so their weights are
    large: k_s = 1e8 over 1e5 segments is a per-segment stiffness of ~1e3 J/m^2), while Eq. 8, 11
    and the contact terms are sums; the means divide by `reference_strand_count` strands, not
    by the number simulated, so that a reduced groom is the same hair.

    Attributes:
        stretch_weight: k_s of Eq. 7 [J/m^2]; multiplies the mean squared segment-length error.
        bending_weight: k_b of Eq. 8 [J/rad]; multiplies the summed turning angles.
        bending_eps: epsilon of Eq. 8 [m] (validity threshold and normalisation guard).
        auxiliary_weight: lambda_aux of Eq. 9 [J/m^2]; pull toward the rigid placement.
        smoothness_weight: lambda_smooth of Eq. 10 [J/m^2].
        vertex_mass: m of Eq. 11 and 16 [kg] per moving vertex of a guide strand (a guide
            stands for a bundle of hairs, so this is the bundle's mass per vertex).
        gravity: gravitational acceleration [m/s^2], y up.
        gravity_weight: dimensionless multiplier of Eq. 11 (1 = physical gravity).
        root_alignment_weight: lambda_root of Eq. 15 [J].
        root_alignment_segments: k'_align of Eq. 15: moving segments per strand aligned with the
            scalp normal.
        root_alignment_eps: epsilon_norm of Eq. 15 [m].
        inertia_weight: lambda_inertia of Eq. 16 (dimensionless). Eq. 16 is a mean over the
            moving vertices while gravity (Eq. 11) is a sum: lambda_inertia = R N_mov (R the
            `reference_strand_count`; ~1e5 for 1024 x 100) makes the pair physical (the
            implicit-Euler incremental potential); a weight of 1 would make the dynamics all
            but quasi-static.
        time_step: Delta t of Eq. 16 [s] (1/60 in the paper).
        hair_body_weight: lambda_hb of Eq. 12 for hair-body contact [J], per vertex.
        hair_body_xi: hard barrier xi for hair-body contact [m] (1 mm in the paper).
        hair_body_dhat: soft barrier width for hair-body contact [m] (1.5 xi in the paper).
        hair_hair_weight: lambda_hh of Eq. 12 for hair-hair contact [J], per segment pair.
        hair_diameter: xi for hair-hair contact [m]: the diameter of a guide strand's bundle.
        hair_hair_dhat: soft barrier width for hair-hair contact [m] (1.5 xi in the paper).
        barrier_join_fraction: b_p of Eq. 12, d_b = xi + b_p * dhat; the paper anneals it from
            0.9 to 0.01 while training, 0.01 being its final value.
        barrier_variant: "quadratic" (default: the barrier's Taylor polynomial at d_b, force
            growing linearly with depth), "monotone" (quartic growth) or "paper" (Eq. 12-14
            literally); see `hairwarp.ops.barrier`.
        hair_hair_capacity_per_segment: pair-buffer capacity of the hair-hair broad phase, in
            candidate pairs per segment; overflow is reported, never dropped silently.
        reference_strand_count: R, the strand count the means of Eq. 7, 9, 10, 15 and 16 divide
            by (default 1 024, the size the weights were chosen at): every strand gets the energy
            it has in a groom of R strands, whatever the M strands simulated (the total grows
            with M, as a sum does; hair-hair contact, a sum over pairs, still sees the sparser
            hair). 0: the M strands handed in, as the paper writes Eq. 7-16. Then a groom's
            physics depends on how many of its strands are simulated: gravity (Eq. 11) is a
            sum, so at 256 strands each strand's stiffness and inertia weigh 4x what they weigh
            at 1 024 against its weight. Measured (docs/physics.md, "Sixteenth session"): the
            torso bend's physics at 64 / 256 strands has its tips 48 / 34 mm from the full
            groom's with R = 0, 6.7 / 5.3 mm with R = 1 024 (tip swing 12 / 18 and 44 / 44 mm,
            full groom 44 mm).
    """

    stretch_weight: float = 1.0e8
    bending_weight: float = 1.0e-6
    bending_eps: float = 1.0e-6
    auxiliary_weight: float = 1.0e2
    smoothness_weight: float = 1.0e3
    vertex_mass: float = 1.0e-5
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    gravity_weight: float = 1.0
    root_alignment_weight: float = 1.0
    root_alignment_segments: int = 3
    root_alignment_eps: float = 1.0e-8
    inertia_weight: float = 1.0e5
    time_step: float = 1.0 / 60.0
    hair_body_weight: float = 1.0e3
    hair_body_xi: float = 1.0e-3
    hair_body_dhat: float = 1.5e-3
    hair_hair_weight: float = 1.0e3
    hair_diameter: float = 5.0e-4
    hair_hair_dhat: float = 7.5e-4
    barrier_join_fraction: float = 0.01
    barrier_variant: str = "quadratic"
    hair_hair_capacity_per_segment: int = 16
    reference_strand_count: int = 1024

    def replace(self, **changes) -> "EnergyConfig":
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{f.name}: expected a finite number, got {value}")
        for name in ("hair_body_xi", "hair_body_dhat", "hair_diameter", "hair_hair_dhat", "time_step"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}: expected a positive length/time, got {getattr(self, name)}")
        if not 0.0 < self.barrier_join_fraction < 1.0:
            raise ValueError(f"barrier_join_fraction: expected a value in (0, 1), got {self.barrier_join_fraction}")
        if self.barrier_variant not in BARRIER_VARIANTS:
            raise ValueError(f"barrier_variant: expected one of {list(BARRIER_VARIANTS)}, "
                             f"got {self.barrier_variant!r}")
        if self.root_alignment_segments < 0:
            raise ValueError(f"root_alignment_segments: expected >= 0, got {self.root_alignment_segments}")
        if len(self.gravity) != 3:
            raise ValueError(f"gravity: expected 3 numbers, got {self.gravity}")
        if isinstance(self.reference_strand_count, bool) or not isinstance(self.reference_strand_count, int) \
                or self.reference_strand_count < 0:
            raise ValueError(f"reference_strand_count: expected an int >= 0, got {self.reference_strand_count!r}")

    def strand_normalization(self, num_strands: int) -> int:
        """The M that the means of Eq. 7, 9, 10, 15 and 16 divide by for a groom of `num_strands`
        strands: `reference_strand_count`, or `num_strands` where that is 0 (the paper's means).
        """
        return self.reference_strand_count or num_strands

    def inertia_stiffness(self, num_strands: int, num_vertices: int) -> float:
        """Eq. 16's stiffness per moving vertex [J/m^2]: lambda_inertia m / (M (N-2) h^2), M the
        `strand_normalization` of a groom of `num_strands` strands of `num_vertices` vertices.
        """
        return (self.inertia_weight * self.vertex_mass
                / (self.strand_normalization(num_strands) * (num_vertices - NUM_FIXED_VERTICES) * self.time_step ** 2))

    def weights(self) -> dict[str, float]:
        """The weight of each term by name (zero turns the term off)."""
        return {
            "stretch": self.stretch_weight,
            "bending": self.bending_weight,
            "auxiliary": self.auxiliary_weight,
            "smoothness": self.smoothness_weight,
            "gravity": self.gravity_weight,
            "root_alignment": self.root_alignment_weight,
            "inertia": self.inertia_weight,
            "hair_body_contact": self.hair_body_weight,
            "hair_hair_contact": self.hair_hair_weight,
        }
