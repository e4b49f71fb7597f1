"""Torch autograd bridges over the Warp kernels. Every function takes and returns torch tensors."""

from hairwarp.ops.barrier import barrier
from hairwarp.ops.distances import edge_edge_distance, point_triangle_distance
from hairwarp.ops.hair_body_contact import (
    BodyMesh,
    hair_body_contact_energy,
    hair_body_keep_out_push,
    hair_body_signed_distance,
    hair_body_signed_distance_and_normal,
    point_mesh_signed_distance,
)
from hairwarp.ops.hair_hair_contact import hair_hair_contact_energy, hair_hair_contact_pairs
from hairwarp.ops.strand_projection import follow_the_leader
from hairwarp.ops.strand_energies import (
    auxiliary_energy,
    bending_energy,
    compute_rest_lengths,
    gravity_energy,
    inertia_energy,
    root_alignment_energy,
    smoothness_energy,
    strand_energies,
    stretch_energy,
)

__all__ = [
    "barrier",
    "follow_the_leader",
    "edge_edge_distance",
    "point_triangle_distance",
    "hair_hair_contact_energy",
    "hair_hair_contact_pairs",
    "BodyMesh",
    "hair_body_contact_energy",
    "hair_body_keep_out_push",
    "hair_body_signed_distance",
    "hair_body_signed_distance_and_normal",
    "point_mesh_signed_distance",
    "auxiliary_energy",
    "bending_energy",
    "compute_rest_lengths",
    "gravity_energy",
    "inertia_energy",
    "root_alignment_energy",
    "smoothness_energy",
    "strand_energies",
    "stretch_energy",
]
