"""Write an SMPL-format body model built of overlapping closed primitives, as a quick rig would be.

Reproduces what a user has when a character is built from primitives rather than one skin:
one mesh that is the plain union (concatenation) of closed shells that pass through each other
where they overlap. Written with plain numpy only (no hairwarp writer); hairwarp is imported
afterwards, only to check that `hairwarp.scene.smpl.load_smpl_model` reads the file
(skip with --no-check).

The skeleton is the project's default body's: joints = J_regressor @ v_template of
`src/hairwarp/assets/default_body.npz` (22 joints, y up, metres, facing +z, left at +x), plus
SMPL's two hand joints (22, 23: children of the wrists, 8.5 cm further along the forearm), so the
file has 24 joints in SMPL order. The primitives, each skinned rigidly (weight 1.0) to one joint:

- a UV sphere per joint (24 x 100 triangles), skinned to that joint; the joint's J_regressor row
  is the uniform average of the sphere's vertices, so the regressed joint is the sphere centre;
- a closed capsule along each bone, joint -> child (23 x 144 triangles), skinned to the parent
  joint (the one whose rotation moves the bone), radius 0.8 x the smaller end sphere's;
- a head ellipsoid around the head joint (15), a little larger than the default body's cranium
  (semi-axes 9.8 x 11.8 x 11.5 cm, 720 triangles), skinned to the head;
- a torso ellipsoid (17 x 30 x 12 cm, 352 triangles), skinned to spine2 (6).

6 784 triangles, 3 490 vertices. `shapedirs` is (V, 3, 10): by default ("small") each primitive
scales about its own centre by N(0, 2 %) per unit beta (seeded by --seed), so a beta never moves
a joint sphere's centre; `--shapedirs zero` writes zeros. No `posedirs`, no `head_vertex_indices`
(the head region then comes from the head joint's skin weights). `kintree_table` (2, 24) uint32
with the root's parent 2^32 - 1; `weights` (V, 24) one-hot; `J_regressor` (24, V).

Checks (printed): every primitive is a closed, consistently oriented 2-manifold of Euler
characteristic 2 with positive signed volume (outward normals), the regressed joints equal the
default body's, the weight rows are one-hot; then the file loads with `load_smpl_model`.

    python tools/primitive_body.py --out /tmp/prim/body.npz [--seed 0] [--shapedirs small|zero]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_BODY = os.path.join(HERE, os.pardir, "src", "hairwarp", "assets", "default_body.npz")

# SMPL's 24-joint tree (the first 22 are the default body's).
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
HEAD_JOINT = 15
TORSO_JOINT = 6
HAND_OFFSET = 0.085  # [m] wrist -> SMPL hand joint along the forearm
# Joint sphere radii [m], SMPL order.
SPHERE_RADIUS = (
    0.100, 0.085, 0.085, 0.090, 0.055, 0.055, 0.095, 0.045, 0.045, 0.100, 0.040, 0.040,
    0.050, 0.050, 0.050, 0.060, 0.055, 0.055, 0.042, 0.042, 0.033, 0.033, 0.040, 0.040,
)
BONE_RADIUS_SHARE = 0.8
SPHERE_RES = (6, 10)    # (stacks, slices): 2 * 10 * 5 = 100 triangles
CAPSULE_RES = (7, 12)   # odd stacks: the equator band becomes the cylinder; 144 triangles
HEAD_RES = (16, 24)     # 720 triangles
TORSO_RES = (12, 16)    # 352 triangles
HEAD_CENTER_OFFSET = (0.0, 0.049, 0.012)  # head ellipsoid centre - head joint [m]
HEAD_SEMI_AXES = (0.098, 0.118, 0.115)
TORSO_CENTER = (0.0, 0.04, 0.03)
TORSO_SEMI_AXES = (0.17, 0.30, 0.12)
NUM_BETAS = 10


def uv_sphere(stacks: int, slices: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit UV sphere: poles on +-z, `stacks - 1` rings of `slices`; outward (CCW) triangles."""
    theta = np.pi * np.arange(1, stacks) / stacks
    phi = 2 * np.pi * np.arange(slices) / slices
    ring = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                     np.cos(theta)[:, None] * np.ones_like(phi)], axis=-1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    top, bottom = 0, len(verts) - 1

    def at(r, s):
        return 1 + r * slices + s % slices

    faces = []
    for s in range(slices):
        faces.append((top, at(0, s), at(0, s + 1)))
        faces.append((bottom, at(stacks - 2, s + 1), at(stacks - 2, s)))
        for r in range(stacks - 2):
            a, b, c, d = at(r, s), at(r + 1, s), at(r + 1, s + 1), at(r, s + 1)
            faces.append((a, b, c))
            faces.append((a, c, d))
    return verts, np.asarray(faces, dtype=np.int64)


def frame_along(axis: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose third column is the unit `axis` (a right-handed frame)."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def ellipsoid(center, semi_axes, res) -> tuple[np.ndarray, np.ndarray]:
    verts, faces = uv_sphere(*res)
    # Poles on +-y (up): a positive-determinant permutation (x, y, z) <- (y, z, x) keeps CCW.
    verts = verts[:, [1, 2, 0]]
    return verts * np.asarray(semi_axes) + np.asarray(center), faces


def capsule(a: np.ndarray, b: np.ndarray, radius: float, res) -> tuple[np.ndarray, np.ndarray]:
    """Closed capsule: hemispheres of `radius` centred on `a` and `b`, joined by a cylinder."""
    stacks, slices = res
    assert stacks % 2 == 1
    verts, faces = uv_sphere(stacks, slices)
    length = float(np.linalg.norm(b - a))
    local = verts * radius
    local[verts[:, 2] > 0, 2] += length  # the upper half moves to b
    return local @ frame_along(b - a).T + a, faces


def shell_report(verts: np.ndarray, faces: np.ndarray) -> str | None:
    """Why (verts, faces) is not a closed, consistently outward-oriented 2-manifold of genus 0."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if (counts != 2).any():
        return f"{int((counts == 1).sum())} open and {int((counts > 2).sum())} non-manifold edges"
    if len(np.unique(directed, axis=0)) != len(directed):
        return "inconsistent orientation (a directed edge repeats)"
    used = np.unique(faces)
    euler = len(used) - len(counts) + len(faces)
    if euler != 2:
        return f"Euler characteristic {euler}, not 2"
    p = verts[faces]
    volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6
    if volume <= 0:
        return f"signed volume {volume:.3g} <= 0 (normals point inward)"
    return None


def build(default_body: str, seed: int, shapedirs_mode: str) -> tuple[dict, list]:
    with np.load(default_body) as body:
        joints22 = body["J_regressor"].astype(np.float64) @ body["v_template"].astype(np.float64)
    joints = np.zeros((24, 3))
    joints[:22] = joints22
    for hand, wrist in ((22, 20), (23, 21)):
        forearm = joints[wrist] - joints[PARENTS[wrist]]
        joints[hand] = joints[wrist] + HAND_OFFSET * forearm / np.linalg.norm(forearm)

    parts = []  # (name, joint, verts, faces, centre, is_joint_sphere)
    for j in range(24):
        v, f = uv_sphere(*SPHERE_RES)
        parts.append((f"sphere_{j}", j, v * SPHERE_RADIUS[j] + joints[j], f, joints[j], True))
    for j in range(1, 24):
        p = PARENTS[j]
        radius = BONE_RADIUS_SHARE * min(SPHERE_RADIUS[p], SPHERE_RADIUS[j])
        v, f = capsule(joints[p], joints[j], radius, CAPSULE_RES)
        parts.append((f"bone_{p}_{j}", p, v, f, 0.5 * (joints[p] + joints[j]), False))
    head_center = joints[HEAD_JOINT] + np.asarray(HEAD_CENTER_OFFSET)
    v, f = ellipsoid(head_center, HEAD_SEMI_AXES, HEAD_RES)
    parts.append(("head", HEAD_JOINT, v, f, head_center, False))
    v, f = ellipsoid(TORSO_CENTER, TORSO_SEMI_AXES, TORSO_RES)
    parts.append(("torso", TORSO_JOINT, v, f, np.asarray(TORSO_CENTER), False))

    rng = np.random.default_rng(seed)
    verts, faces, weights_j, shapedirs, regressor_rows = [], [], [], [], {}
    offset = 0
    for name, joint, v, f, centre, is_sphere in parts:
        verts.append(v)
        faces.append(f + offset)
        weights_j.append(np.full(len(v), joint))
        scale = rng.normal(0.0, 0.02, NUM_BETAS) if shapedirs_mode == "small" else np.zeros(NUM_BETAS)
        shapedirs.append((v - centre)[:, :, None] * scale[None, None, :])
        if is_sphere:
            regressor_rows[joint] = np.arange(offset, offset + len(v))
        offset += len(v)
    v_template = np.concatenate(verts)
    num_vertices = len(v_template)
    weights = np.zeros((num_vertices, 24))
    weights[np.arange(num_vertices), np.concatenate(weights_j)] = 1.0
    j_regressor = np.zeros((24, num_vertices))
    for j, rows in regressor_rows.items():
        j_regressor[j, rows] = 1.0 / len(rows)
    kintree = np.array([[2**32 - 1] + list(PARENTS[1:]), list(range(24))], dtype=np.uint32)
    arrays = {
        "v_template": v_template.astype(np.float32),
        "f": np.concatenate(faces).astype(np.int32),
        "J_regressor": j_regressor.astype(np.float32),
        "kintree_table": kintree,
        "weights": weights.astype(np.float32),
        "shapedirs": np.concatenate(shapedirs).astype(np.float32),
    }
    return arrays, parts, joints


def check(arrays: dict, parts: list, joints: np.ndarray) -> list[str]:
    problems = []
    for name, _, v, f, _, _ in parts:
        why = shell_report(v, f)
        if why:
            problems.append(f"{name}: {why}")
    regressed = arrays["J_regressor"].astype(np.float64) @ arrays["v_template"].astype(np.float64)
    err = np.abs(regressed - joints).max()
    if err > 1e-5:
        problems.append(f"regressed joints differ from the skeleton by {err:.3g} m")
    w = arrays["weights"]
    if not ((w.max(1) == 1.0) & (w.sum(1) == 1.0)).all():
        problems.append("weight rows are not one-hot")
    return problems


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--out", required=True, help="the .npz to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of the small shapedirs (default 0)")
    parser.add_argument("--shapedirs", choices=("small", "zero"), default="small",
                        help="per-primitive N(0, 2%%) scale per beta (default), or zeros")
    parser.add_argument("--default-body", default=DEFAULT_BODY, help="where the skeleton comes from")
    parser.add_argument("--no-check", action="store_true", help="skip the load_smpl_model check")
    args = parser.parse_args(argv)

    arrays, parts, joints = build(args.default_body, args.seed, args.shapedirs)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)) or ".", exist_ok=True)
    np.savez(args.out, **arrays)
    v, f = arrays["v_template"], arrays["f"]
    print(f"wrote {args.out}: {len(parts)} primitives, V = {len(v)}, F = {len(f)}, "
          f"bbox {v.min(0).round(3).tolist()} .. {v.max(0).round(3).tolist()} m")
    problems = check(arrays, parts, joints)
    for p in problems:
        print("PROBLEM", p)
    if not problems:
        print(f"checks: all {len(parts)} primitives closed, outward, Euler 2; joints regress to "
              "sphere centres; weights one-hot")
    if not args.no_check:
        from hairwarp.scene.body import SMPLBody  # only to check the written file
        from hairwarp.scene.smpl import load_smpl_model

        model = load_smpl_model(args.out)
        body = SMPLBody(model)
        print(f"load_smpl_model: V = {model.num_vertices}, J = {model.num_joints}, "
              f"K = {model.num_betas}, posedirs = {model.posedirs}; "
              f"head region {body.head_vertex_indices.numel()} vertices")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
