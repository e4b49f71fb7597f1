"""The trained networks as harness methods, and the inference API behind them.

Tiny untrained networks stand in for trained ones (what is tested is the plumbing: shapes, the
fixed vertices, the GRU run, checkpoints, errors); one test loads the shipped checkpoint.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import hairwarp.evaluation.network_methods as network_methods
from hairwarp.evaluation.methods import list_methods, make_method
from hairwarp.evaluation.scenes import comparison_scene
from hairwarp.inference import HairFormerSimulator, load_default_simulator
from hairwarp.models import DynamicConfig, DynamicNetwork, QuaffureConfig, QuaffureNetwork, StaticConfig, StaticNetwork
from hairwarp.models.checkpoint import save_checkpoint

# Tiny networks read the 512-d hair latent of the shipped basis.
TINY_N = 12


def _tiny_static() -> StaticNetwork:
    torch.manual_seed(0)
    return StaticNetwork(dataclasses.replace(StaticConfig.tiny(), latent_dim=512, num_vertices=TINY_N))


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ckpt")
    static = _tiny_static()
    # A nonzero head, so the drape differs from the rigid placement.
    with torch.no_grad():
        for p in static.parameters():
            p.add_(0.01 * torch.randn_like(p))
    dyn_cfg = dataclasses.replace(DynamicConfig.tiny(motion_dim=132), static=static.config)
    dynamic = DynamicNetwork.from_static(static, dyn_cfg)
    quaffure = QuaffureNetwork(dataclasses.replace(QuaffureConfig.tiny(), latent_dim=512, num_vertices=TINY_N))
    paths = {}
    for name, model in (("static", static), ("dynamic", dynamic), ("quaffure", quaffure)):
        paths[name] = str(folder / f"{name}.pt")
        save_checkpoint(paths[name], model)
        network_methods.set_checkpoint(name, paths[name])
    yield paths
    for name in paths:
        network_methods.set_checkpoint(name, None)


@pytest.fixture(scope="module")
def poses_scene():
    return comparison_scene("medium_poses", strand_stride=16, num_vertices=TINY_N)


def test_network_methods_are_registered():
    assert {"static", "dynamic", "quaffure"} <= set(list_methods())


@pytest.mark.parametrize("name", ["static", "dynamic", "quaffure"])
def test_drape_shapes_fixed_vertices_and_time(checkpoints, poses_scene, name):
    frames = poses_scene.frames()
    method = make_method(name)
    method.prepare(poses_scene)
    result = method.drape(frames)
    rigid = frames.rigid.positions
    assert result.positions.shape == rigid.shape
    assert torch.isfinite(result.positions).all()
    assert torch.equal(result.positions[:, :, :2], rigid[:, :, :2])  # vertices 0 and 1 fixed
    assert (result.positions - rigid).abs().max() > 0  # the network moved the hair
    assert result.time_ms is not None and result.time_ms > 0


def test_dynamic_on_a_static_pose_is_the_held_pose_simulation(checkpoints, poses_scene):
    frames = poses_scene.frames()
    method = make_method("dynamic")
    method.prepare(poses_scene)
    result = method.drape(frames)
    sim = network_methods._simulator("dynamic", torch.device("cpu"))
    hold = network_methods.HOLD_FRAMES
    b = 1
    expected = sim.simulate_poses(poses_scene.scene, frames.poses[b].expand(hold, -1), frames.betas[b],
                                  frames.rigid.positions[b].expand(hold, -1, -1, -1), 60.0)[-1]
    torch.testing.assert_close(result.positions[b], expected)
    assert result.info["hold_frames"] == hold


def test_dynamic_simulates_a_motion_frame_by_frame(checkpoints):
    scene = comparison_scene("whiplash", strand_stride=16, num_vertices=TINY_N)
    frames = scene.frames(list(range(6)))
    method = make_method("dynamic")
    result = method.simulate(scene, frames=frames)
    assert result.positions.shape == frames.rigid.positions.shape
    # The GRU carries state: frame t depends on the frames before it, so a sequence started
    # later gives another answer for the same frame.
    later = method.simulate(scene, frames=scene.frames(list(range(3, 6))))
    assert (later.positions[-1] - result.positions[-1]).abs().max() > 0


def test_static_method_falls_back_to_the_static_network_inside_a_dynamic_checkpoint(checkpoints, poses_scene):
    network_methods.set_checkpoint("static", checkpoints["dynamic"])
    try:
        frames = poses_scene.frames([0])
        method = make_method("static")
        method.prepare(poses_scene)
        from_dynamic = method.drape(frames).positions
    finally:
        network_methods.set_checkpoint("static", checkpoints["static"])
    method = make_method("static")
    method.prepare(poses_scene)
    torch.testing.assert_close(from_dynamic, method.drape(frames).positions)


def test_errors_name_the_problem(checkpoints, poses_scene, tmp_path):
    with pytest.raises(ValueError, match="name"):
        network_methods.set_checkpoint("lbfgs", checkpoints["static"])
    with pytest.raises(FileNotFoundError, match="checkpoint"):
        network_methods.set_checkpoint("static", tmp_path / "missing.pt")
    network_methods.set_checkpoint("dynamic", checkpoints["quaffure"])
    try:
        method = make_method("dynamic")
        method.prepare(poses_scene)
        with pytest.raises(ValueError, match="not a dynamic network"):
            method.drape(poses_scene.frames([0]))
    finally:
        network_methods.set_checkpoint("dynamic", checkpoints["dynamic"])
    method = make_method("static")
    with pytest.raises(ValueError, match="prepare"):
        method.drape(poses_scene.frames([0]))
    wrong_n = comparison_scene("medium_rest", strand_stride=16, num_vertices=TINY_N + 1)
    method.prepare(wrong_n)
    with pytest.raises(ValueError, match="num_vertices"):
        method.drape(wrong_n.frames())


def test_simulate_poses_rejects_mismatched_frames(checkpoints, poses_scene):
    sim = network_methods._simulator("dynamic", torch.device("cpu"))
    frames = poses_scene.frames()
    with pytest.raises(ValueError, match="poses"):
        sim.simulate_poses(poses_scene.scene, frames.poses[:2], frames.betas[0], frames.rigid.positions, 60.0)
    static_only = HairFormerSimulator(_tiny_static())
    with pytest.raises(ValueError, match="dynamic"):
        static_only.simulate_poses(poses_scene.scene, frames.poses, frames.betas[0], frames.rigid.positions, 60.0)


def test_shipped_checkpoint_loads_and_drapes():
    sim = load_default_simulator("cpu")
    assert sim is not None and sim.dynamic is not None
    n = sim.static.config.num_vertices
    scene = comparison_scene("medium_rest", strand_stride=32, num_vertices=n)
    frames = scene.frames()
    drape = sim.drape(scene.scene, frames)
    assert drape.shape == frames.rigid.positions.shape
    assert torch.isfinite(drape).all()
    assert torch.equal(drape[:, :, :2], frames.rigid.positions[:, :, :2])
