"""Bring your own character: mesh bodies (static and animated), foreign grooms (USD curves,
.data from another head) fitted to the scalp, SMPL models with another beta count.

Every file here is written by the test itself with trimesh, pxr or numpy, as a user's tool would.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from pxr import Usd, UsdGeom, Vt

import hairwarp as hw
from hairwarp.builder import build_scene
from hairwarp.io.hair_data import write_hair_data
from hairwarp.metrics import penetration_percent
from hairwarp.ops import hair_body_signed_distance
from hairwarp.scene.groom import fit_similarity_to_scalp
from hairwarp.scene.rotations import np_axis_angle_to_matrix
from hairwarp.scene.scene import default_scene

# Roots must stay on the moving surface to this [m] in every frame (the goal: 1 mm).
ROOT_ON_SURFACE_TOL = 1e-3
# A known similarity is recovered to this [m] on the roots (the goal: 1 mm).
FIT_TOL = 1e-3


@pytest.fixture(scope="module")
def default():
    return default_scene("bob", "head_turn", duration=0.5)


@pytest.fixture(scope="module")
def mesh_files(default, tmp_path_factory):
    """The default body's rest mesh as .obj, and four posed frames as an .npz and a USD animation."""
    folder = tmp_path_factory.mktemp("bodies")
    body = default.body
    faces = body.faces.numpy()
    trimesh.Trimesh(body.rest_vertices.numpy(), faces, process=False).export(folder / "body.obj")
    frames = default.motion.poses[[0, 8, 16, 24]]
    posed = body.pose(betas=torch.zeros(4, 16), poses=frames).vertices.numpy()
    np.savez(folder / "anim.npz", vertices=posed, faces=faces, fps=np.array(15.0))
    stage = Usd.Stage.CreateNew(str(folder / "anim.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)  # a z-up tool in centimetres
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(15.0)
    mesh = UsdGeom.Mesh.Define(stage, "/Character/Skin")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.reshape(-1).tolist()))
    points = mesh.CreatePointsAttr()
    for t, v in enumerate(posed):
        z_up_cm = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1) * 100.0  # y-up metres -> z-up centimetres
        points.Set(Vt.Vec3fArray.FromNumpy(z_up_cm.astype(np.float32)), Usd.TimeCode(t))
    stage.Save()
    still = Usd.Stage.CreateNew(str(folder / "still.usda"))
    m = UsdGeom.Mesh.Define(still, "/Body")
    m.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.reshape(-1).tolist()))
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(body.rest_vertices.numpy()))
    still.Save()
    return folder, posed


# ------------------------------------------------------------------ bodies


def test_static_mesh_body_drapes_with_the_physics(mesh_files):
    folder, _ = mesh_files
    scene = build_scene("bob", body=str(folder / "body.obj"), strand_stride=32, num_vertices=20)
    assert not scene.body.has_smpl_pose and scene.num_frames == 1
    r = hw.drape(scene, method="lbfgs", max_iterations=5)
    assert r.positions.shape == (scene.hairstyle.num_strands, 20, 3)
    assert torch.isfinite(r.positions).all()


@pytest.mark.parametrize("name", ["anim.npz", "anim.usda"])
def test_animated_mesh_carries_attached_hair_with_roots_on_the_surface(mesh_files, name):
    folder, posed = mesh_files
    scene = build_scene("bob", body=str(folder / name), strand_stride=32, num_vertices=20)
    assert scene.num_frames == 4 and scene.motion.fps == 15.0
    frames = scene.frames()
    torch.testing.assert_close(frames.posed.vertices, torch.as_tensor(posed), atol=2e-5, rtol=0)  # units, axes
    d = hair_body_signed_distance(frames.rigid.positions, frames.body_mesh)
    assert float(d[:, :, 0].abs().max()) < ROOT_ON_SURFACE_TOL
    # The hair follows the head: the roots move with the surface from frame to frame.
    moved = (frames.rigid.positions[-1, :, 0] - frames.rigid.positions[0, :, 0]).norm(dim=-1)
    assert float(moved.max()) > 0.01


def test_networks_refuse_a_mesh_body_in_one_line_and_auto_falls_back(mesh_files):
    folder, _ = mesh_files
    scene = build_scene("bob", body=str(folder / "anim.npz"), strand_stride=64)
    with pytest.raises(ValueError, match="needs an SMPL-convention body"):
        hw.simulate(scene, method="dynamic")
    r = hw.drape(scene, method="auto", max_iterations=2)
    assert r.info["chosen"].startswith("lbfgs")


def test_mesh_body_windows_keep_the_rest_pose(mesh_files):
    folder, _ = mesh_files
    one = build_scene("bob", body=str(folder / "anim.npz"), frame=2, strand_stride=64)
    assert one.num_frames == 1 and one.body.num_frames == 1
    whole = build_scene("bob", body=str(folder / "anim.npz"), strand_stride=64)
    torch.testing.assert_close(one.frames().rigid.positions[0], whole.frames([2]).rigid.positions[0])


def test_malformed_bodies_get_one_clear_line(mesh_files, tmp_path):
    folder, _ = mesh_files
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(tmp_path / "cloud.ply")
    with pytest.raises(ValueError, match="body: cloud.ply holds no triangles"):
        build_scene("bob", body=str(tmp_path / "cloud.ply"))
    box = trimesh.creation.box()
    trimesh.Trimesh(box.vertices, box.faces[:-1], process=False).export(tmp_path / "open.obj")
    with pytest.raises(ValueError, match="body: open.obj: not a closed surface"):
        build_scene("bob", body=str(tmp_path / "open.obj"))
    np.savez(tmp_path / "nofaces.npz", vertices=np.zeros((2, 10, 3)))
    with pytest.raises(ValueError, match="no faces"):
        build_scene("bob", body=str(tmp_path / "nofaces.npz"))
    with pytest.raises(ValueError, match="pose: a mesh body plays its own"):
        build_scene("bob", body=str(folder / "anim.npz"), pose="head_turn")


def test_simulate_needs_time_samples(mesh_files, tmp_path, capsys):
    from hairwarp.cli import main

    folder, _ = mesh_files
    assert main(["simulate", "--body", str(folder / "still.usda"), "--strand-stride", "64",
                 "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "--body:" in err and "time samples" in err


# ------------------------------------------------------------------ grooms


def _usd_groom(path, strands, *, z_up_cm=False):
    stage = Usd.Stage.CreateNew(str(path))
    if z_up_cm:
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    curves = UsdGeom.BasisCurves.Define(stage, "/Groom/Curves")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([len(s) for s in strands]))
    pts = np.concatenate(strands)
    if z_up_cm:
        pts = np.stack([pts[:, 0], -pts[:, 2], pts[:, 1]], axis=1) * 100.0
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    stage.Save()


def test_usd_groom_with_any_vertex_count(default, tmp_path):
    x = default.hairstyle.strands.double().numpy()[::16]
    rng = np.random.default_rng(0)
    strands = [s[:: int(rng.integers(1, 4))] for s in x]  # 34 to 100 vertices per strand
    assert len({len(s) for s in strands}) > 1
    _usd_groom(tmp_path / "groom.usda", strands, z_up_cm=True)
    scene = build_scene(str(tmp_path / "groom.usda"), num_vertices=30, fit="none")
    assert scene.hairstyle.strands.shape == (len(strands), 30, 3)
    got = scene.hairstyle.strands.double()
    # Units and axes converted, each strand kept whole (tips in place after the root's snap).
    expected_tips = torch.as_tensor(np.stack([s[-1] - s[0] for s in strands])) + got[:, 0]
    torch.testing.assert_close(got[:, -1], expected_tips, atol=1e-5, rtol=0)
    _usd_groom(tmp_path / "bad.usda", [x[0], x[1][:1]])
    with pytest.raises(ValueError, match="hairstyle: curve 1 of /Groom/Curves has 1 vertex"):
        build_scene(str(tmp_path / "bad.usda"))


def test_fit_recovers_a_known_similarity(default):
    grid = default.scalp.positions.double().numpy()
    s, angle, offset = 1.08, np.radians(6.0), np.array([0.03, 1.2, -0.05])
    rot = np_axis_angle_to_matrix(np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3]) * angle)
    # The groom of another head: our scalp roots seen in that head's frame.
    foreign = (grid - offset) @ rot / s
    fit = fit_similarity_to_scalp(foreign, default.scalp, grid)
    assert abs(fit.scale - s) < 1e-3
    assert np.abs(fit.apply(foreign) - grid).max() < FIT_TOL


def test_a_groom_from_another_head_is_fitted_not_dragged_in(tmp_path, capsys):
    base = default_scene("long_straight", grow_around_body=True, strand_stride=8)
    x = base.hairstyle.strands.double().numpy()
    centre = base.body.rest_vertices[base.body.head_vertex_indices].double().numpy().mean(0)
    rot = np_axis_angle_to_matrix(np.array([0.0, np.radians(4.0), np.radians(3.0)]))
    foreign = (1.08 * (x - centre) @ rot.T + np.array([0.0, 1.6, 0.0])) * 100.0  # 8 % larger, 1.6 m up, cm
    write_hair_data(tmp_path / "foreign.data", torch.tensor(foreign, dtype=torch.float32))
    pen = {}
    for fit in ("none", "auto"):
        scene = build_scene(str(tmp_path / "foreign.data"), fit=fit)
        frames = scene.frames()
        pen[fit] = float(penetration_percent(frames.rigid.positions, frames.body_mesh))
        assert float(hair_body_signed_distance(frames.rigid.positions, frames.body_mesh)[..., 0].abs().max()) < 1e-3
    assert "scale 0.9" in capsys.readouterr().out  # what the fit did is printed
    assert pen["none"] > 20.0  # roots projected alone drag the strands into the head
    assert pen["auto"] <= 5.0


# ------------------------------------------------------------------ SMPL shape coefficients


def test_a_ten_beta_model_takes_a_sixteen_beta_motion(tmp_path, capsys):
    import importlib.resources

    data = dict(np.load(str(importlib.resources.files("hairwarp") / "assets" / "default_body.npz")))
    data["shapedirs"] = data["shapedirs"][:, :, :10]
    data = {k: v for k, v in data.items() if k not in ("attribution", "metadata_json")}
    np.savez(tmp_path / "smpl10.npz", **data)
    t = 4
    np.savez(tmp_path / "motion.npz", poses=np.zeros((t, 156)), trans=np.zeros((t, 3)),
             betas=np.linspace(0.1, 1.6, 16), mocap_framerate=np.array(60.0), gender=np.array("neutral"))
    scene = build_scene("bob", body=str(tmp_path / "smpl10.npz"), pose=str(tmp_path / "motion.npz"),
                        strand_stride=64, num_vertices=10)
    assert scene.body.num_betas == 10
    assert "using the first 10" in capsys.readouterr().out
    frames = scene.frames()
    assert frames.posed.vertices.shape[0] == t and torch.isfinite(frames.rigid.positions).all()
