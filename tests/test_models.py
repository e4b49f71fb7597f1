"""HairFormer networks (Sections 3.2, 3.3, 4.2.3, 4.3.1, 4.5.2): shapes, tapering, nearest lookup,
functional regularization, freezing, one training step, checkpoints, ablations, bad inputs.

Tiny configs on the CPU (CUDA too when present): the whole file runs in seconds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from hairwarp.models import (
    FUSION_CROSS_ATTENTION,
    FUSION_LAYERNORM_CONCAT,
    FUSION_LORA,
    FUSIONS,
    DynamicConfig,
    DynamicNetwork,
    QuaffureConfig,
    QuaffureNetwork,
    StaticConfig,
    StaticNetwork,
    apply_deformation,
    load_checkpoint,
    nearest_cell,
    parameter_count,
    sample_deformation,
    save_checkpoint,
    taper_weights,
)
from references import deformation as ref

# float64 against the float64 loop reference: only summation order differs.
_F64_TOL = 1e-12
# simulate() batches the per-frame attention/head over frames; a frame-by-frame forward loop
# runs them one frame at a time: float32 matmuls of different shapes may round differently.
_F32_TOL = 1e-6
# float16 storage rounds each weight to 11 significant bits (relative 2^-11 ~ 5e-4); the head's
# last layer is tiny (millimetre outputs), partly in float16's subnormal range, so outputs
# agree to a few percent of their own size.
_F16_REL_TOL = 3e-2
# A stand-in loss needs a few millimetres of error to descend from a millimetre initial map.
_LR = 1e-3

BATCH = 2
MOTION_DIM = 9


def _inputs(cfg, batch=BATCH, dtype=torch.float32, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(batch, cfg.latent_dim, generator=g, dtype=torch.float64)
    beta = torch.randn(batch, cfg.shape_dim, generator=g, dtype=torch.float64)
    theta = 0.3 * torch.randn(batch, cfg.pose_dim, generator=g, dtype=torch.float64)
    return tuple(t.to(dtype=dtype, device=device) for t in (z, beta, theta))


def _motion(dcfg, batch=BATCH, frames=None, dtype=torch.float32, device="cpu", seed=1):
    g = torch.Generator().manual_seed(seed)
    shape = (batch, dcfg.window, dcfg.motion_dim) if frames is None else (batch, frames, dcfg.window, dcfg.motion_dim)
    return torch.randn(*shape, generator=g).to(dtype=dtype, device=device)


def _hair(num_strands, num_vertices, batch=BATCH, dtype=torch.float32, device="cpu", seed=2):
    """Straight strands hanging from roots spread over a grid, with root UVs."""
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(num_strands, 2, generator=g, dtype=torch.float64)
    roots = torch.cat([uv[:, :1] * 0.2 - 0.1, torch.full((num_strands, 1), 1.7), uv[:, 1:] * 0.2 - 0.1], 1)
    drop = torch.linspace(0.0, 0.2, num_vertices, dtype=torch.float64)
    rigid = roots[:, None, :] - drop[None, :, None] * torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    rigid = rigid[None].expand(batch, -1, -1, -1).contiguous()
    return rigid.to(dtype=dtype, device=device), uv.to(dtype=dtype, device=device)


@pytest.fixture
def static_net():
    torch.manual_seed(0)
    return StaticNetwork(StaticConfig.tiny())


# ------------------------------------------------------------------------------------------------
# Shapes through the networks
# ------------------------------------------------------------------------------------------------
def test_static_output_shapes(device):
    torch.manual_seed(0)
    cfg = StaticConfig.tiny()
    net = StaticNetwork(cfg).to(device)
    z, beta, theta = _inputs(cfg, device=device)
    features = net.features(z, beta, theta)
    deformation = net(z, beta, theta)
    assert features.shape == (BATCH, cfg.num_cells, cfg.model_dim)
    assert deformation.shape == (BATCH, cfg.grid_height, cfg.grid_width, cfg.num_vertices, 3)
    assert deformation.device.type == device.type
    assert torch.isfinite(deformation).all()
    # Small but non-zero initial deformations, inside the paper's 0.01 clip (Section 4.2.1).
    magnitude = deformation.abs().max().item()
    assert 0.0 < magnitude < cfg.deformation_clip
    # Different bodies give different maps (the body enters through I_hb).
    assert not torch.equal(deformation[0], deformation[1])
    rigid, uv = _hair(20, cfg.num_vertices, device=device)
    positions = net.drape(z, beta, theta, rigid, uv)
    assert positions.shape == rigid.shape


def test_held_joints_are_read_as_the_standing_pose(tmp_path):
    """`StaticConfig.held_joints`: the body encoder reads the standing pose's angles for those
    joints, so moving them leaves the map unchanged, while any other joint still moves it; a
    checkpoint keeps the setting, and a network with none held reads every joint."""
    from hairwarp.scene.motion import standing_pose
    from hairwarp.scene.skeleton import JOINT

    torch.manual_seed(0)
    arms = ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow")
    cfg = dataclasses.replace(StaticConfig.tiny(), held_joints=arms)
    net = StaticNetwork(cfg).double()
    free = StaticNetwork(StaticConfig.tiny()).double()
    free.load_state_dict(net.state_dict())
    z, beta, theta = _inputs(cfg, dtype=torch.float64)
    raised = theta.clone()
    for j in arms:
        raised[:, 3 * JOINT[j]:3 * JOINT[j] + 3] += torch.tensor([0.3, -0.5, 1.2], dtype=torch.float64)
    nodded = theta.clone()
    nodded[:, 3 * JOINT["head"]] += 0.4
    assert torch.equal(net(z, beta, raised), net(z, beta, theta))
    assert not torch.allclose(net(z, beta, nodded), net(z, beta, theta))
    assert not torch.allclose(free(z, beta, raised), free(z, beta, theta))
    # Held = the free network handed the standing pose's angles at those joints.
    standing = theta.clone()
    columns = [3 * JOINT[j] + k for j in arms for k in range(3)]
    standing[:, columns] = standing_pose().double()[columns]
    assert torch.allclose(net(z, beta, raised), free(z, beta, standing), atol=1e-12)
    assert StaticConfig.from_dict(cfg.to_dict()).held_joints == arms
    save_checkpoint(tmp_path / "held.pt", net, cfg)
    loaded = load_checkpoint(tmp_path / "held.pt", dtype=torch.float64).model
    assert loaded.config.held_joints == arms
    assert torch.equal(loaded(z, beta, raised), net(z, beta, theta))
    for bad in (("left_knee", "left_knee"), ("left_elbo",), "left_elbow"):
        with pytest.raises(ValueError, match="held_joints"):
            StaticConfig(held_joints=bad)


def test_static_float64_and_clip():
    torch.manual_seed(0)
    cfg = dataclasses.replace(StaticConfig.tiny(), head_init_gain=1.0)  # large outputs, to be clipped
    net = StaticNetwork(cfg).double()
    z, beta, theta = _inputs(cfg, dtype=torch.float64)
    raw = net(z, beta, theta)
    assert raw.dtype == torch.float64
    assert raw.abs().max().item() > cfg.deformation_clip
    clipped = net(z, beta, theta, clip=cfg.deformation_clip)
    assert clipped.abs().max().item() == pytest.approx(cfg.deformation_clip)
    inside = raw.abs() < cfg.deformation_clip
    assert inside.sum() > 0
    assert torch.equal(clipped[inside], raw[inside])


def test_dynamic_multi_frame_with_gru_state(static_net, device):
    static_net = static_net.to(device)
    dcfg = DynamicConfig.tiny(motion_dim=MOTION_DIM)
    net = DynamicNetwork.from_static(static_net, dcfg)
    cfg = net.config.static
    z, beta, _ = _inputs(cfg, device=device)
    frames = 4
    poses = 0.3 * torch.randn(BATCH, frames, cfg.pose_dim, generator=torch.Generator().manual_seed(5)).to(device)
    motion = _motion(dcfg, frames=frames, device=device)

    out = net.simulate(z, beta, poses, motion)
    assert out.deformation_map.shape == (BATCH, frames, cfg.grid_height, cfg.grid_width, cfg.num_vertices, 3)
    assert out.hidden.shape == (BATCH, cfg.model_dim)
    assert out.static_features.shape == (BATCH, frames, cfg.num_cells, cfg.model_dim)

    # The same sequence one frame at a time, carrying C_dyn by hand.
    hidden, hiddens = None, []
    for t in range(frames):
        step = net(z, beta, poses[:, t], motion[:, t], hidden)
        assert step.deformation_map.shape == (BATCH, cfg.grid_height, cfg.grid_width, cfg.num_vertices, 3)
        torch.testing.assert_close(step.deformation_map, out.deformation_map[:, t], rtol=_F32_TOL, atol=_F32_TOL)
        hidden = step.hidden
        hiddens.append(hidden)
    torch.testing.assert_close(hidden, out.hidden, rtol=_F32_TOL, atol=_F32_TOL)
    # The state really evolves, and carrying it matters.
    assert not torch.allclose(hiddens[0], hiddens[-1])
    fresh = net(z, beta, poses[:, -1], motion[:, -1])
    assert not torch.allclose(fresh.hidden, hiddens[-1])

    # Continuing a simulation from its last hidden state equals one longer simulation.
    first = net.simulate(z, beta, poses[:, :2], motion[:, :2])
    second = net.simulate(z, beta, poses[:, 2:], motion[:, 2:], hidden=first.hidden)
    torch.testing.assert_close(second.deformation_map, out.deformation_map[:, 2:], rtol=_F32_TOL, atol=_F32_TOL)

    rigid, uv = _hair(16, cfg.num_vertices, device=device)
    positions, next_hidden = net.drape(z, beta, poses[:, 0], motion[:, 0], rigid, uv)
    assert positions.shape == rigid.shape and next_hidden.shape == (BATCH, cfg.model_dim)


def test_quaffure_output_shapes(device):
    torch.manual_seed(0)
    cfg = QuaffureConfig.tiny()
    net = QuaffureNetwork(cfg).to(device)
    z, beta, theta = _inputs(cfg, device=device)
    deformation = net(z, beta, theta)
    assert deformation.shape == (BATCH, 32, 32, cfg.num_vertices, 3)
    assert 0.0 < deformation.abs().max().item() < cfg.deformation_clip
    rigid, uv = _hair(30, cfg.num_vertices, device=device)
    positions = net.drape(z, beta, theta, rigid, uv)
    assert positions.shape == rigid.shape
    assert torch.equal(positions[:, :, :2], rigid[:, :, :2])
    assert (positions[:, :, 2:] != rigid[:, :, 2:]).any()


# ------------------------------------------------------------------------------------------------
# Deformation application: nearest lookup (Eq. 2) and tapering (Section 4.2.3)
# ------------------------------------------------------------------------------------------------
def test_taper_weights_fix_two_vertices_and_scale_linearly():
    n = 100
    weights = taper_weights(n, dtype=torch.float64)
    np.testing.assert_allclose(weights.numpy(), ref.taper_weights(n), rtol=0, atol=_F64_TOL)
    assert weights[0] == 0.0 and weights[1] == 0.0
    assert weights[-1] == 1.0
    # Linear from index 2 on: (v - 1) / (N - 1) for the paper's 1-based v.
    steps = torch.diff(weights[2:])
    assert steps.numel() == n - 3
    torch.testing.assert_close(steps, torch.full_like(steps, 1.0 / (n - 1)), rtol=0, atol=_F64_TOL)
    assert weights[2] == pytest.approx(2.0 / (n - 1))


def test_nearest_cell_known_uvs():
    uv = torch.tensor(
        [
            [0.0, 0.0],  # first cell
            [1.0, 1.0],  # the far corner belongs to the last cell
            [0.13, 0.0],  # u * 8 = 1.04 -> column 1
            [0.0, 0.26],  # v * 8 = 2.08 -> row 2
            [0.5, 0.5],  # the centre: row 4, column 4
            [0.99, 0.01],  # top-right: row 0, column 7
            [-0.1, 1.2],  # outside: nearest edge cell, row 7, column 0
        ]
    )
    expected = torch.tensor([0, 63, 1, 16, 36, 7, 56])
    assert torch.equal(nearest_cell(uv, 8, 8), expected)
    for i in range(uv.shape[0]):
        row, col = ref.nearest_cell(uv[i].numpy(), 8, 8)
        assert row * 8 + col == expected[i]

    # The 32x32 scalp roots at their cell centres fall 4x4 into each 8x8 cell.
    side = (torch.arange(32) + 0.5) / 32
    grid_uv = torch.stack(torch.meshgrid(side, side, indexing="xy"), dim=-1).reshape(-1, 2)  # (u, v)
    cells = nearest_cell(grid_uv, 8, 8)
    assert torch.equal(torch.bincount(cells, minlength=64), torch.full((64,), 16))

    # The lookup reads the right cell: a map whose cells hold their own index.
    n = 5
    ids = torch.arange(64, dtype=torch.float64).reshape(1, 8, 8, 1, 1).expand(1, 8, 8, n, 3)
    sampled = sample_deformation(ids, uv.double())
    assert sampled.shape == (1, uv.shape[0], n, 3)
    assert torch.equal(sampled[0, :, 0, 0], expected.double())


def test_apply_deformation_matches_reference_and_fixes_vertices_0_and_1(rng):
    b, m, n, gh, gw = 2, 40, 7, 8, 8
    rigid = torch.from_numpy(rng.normal(size=(b, m, n, 3)))
    dmap = torch.from_numpy(rng.normal(size=(b, gh, gw, n, 3)))  # metre-scale: far beyond real
    shared_uv = torch.from_numpy(rng.uniform(size=(m, 2)))
    per_batch_uv = torch.from_numpy(rng.uniform(size=(b, m, 2)))
    for uv in (shared_uv, per_batch_uv):
        out = apply_deformation(rigid, dmap, uv)
        expected = ref.apply_deformation(rigid.numpy(), dmap.numpy(), uv.numpy())
        np.testing.assert_allclose(out.numpy(), expected, rtol=0, atol=_F64_TOL)
        assert torch.equal(out[:, :, :2], rigid[:, :, :2])  # exactly, not approximately
        moved = (out[:, :, 2:] - rigid[:, :, 2:]).norm(dim=-1)
        assert (moved > 0).all()
        # Linear scaling along the strand: deformation / taper is the same cell value.
        raw = sample_deformation(dmap, uv)
        torch.testing.assert_close(
            (out - rigid)[:, :, 2:], raw[:, :, 2:] * taper_weights(n, dtype=torch.float64)[2:, None]
        )

    # float32 keeps vertices 0 and 1 exact too.
    out32 = apply_deformation(rigid.float(), dmap.float(), shared_uv.float())
    assert torch.equal(out32[:, :, :2], rigid.float()[:, :, :2])


def test_apply_deformation_gradient_central_differences(rng):
    rigid = torch.from_numpy(rng.normal(size=(1, 6, 5, 3))).requires_grad_(True)
    dmap = torch.from_numpy(rng.normal(size=(1, 4, 4, 5, 3))).requires_grad_(True)
    uv = torch.from_numpy(rng.uniform(size=(6, 2)))
    assert torch.autograd.gradcheck(lambda r, d: apply_deformation(r, d, uv), (rigid, dmap), eps=1e-6, atol=1e-8)
    # The map's gradient is zero on the fixed vertices and on cells no strand uses.
    apply_deformation(rigid, dmap, uv).sum().backward()
    assert (dmap.grad[..., :2, :] == 0).all()
    used = torch.zeros(16, dtype=torch.bool)
    used[nearest_cell(uv, 4, 4)] = True
    grad_norm = dmap.grad.reshape(16, -1).abs().sum(dim=1)
    assert (grad_norm[used] > 0).all() and (grad_norm[~used] == 0).all()
    assert used.sum() > 1


# ------------------------------------------------------------------------------------------------
# Dynamic head initialisation, functional regularization (Eq. 4), freezing
# ------------------------------------------------------------------------------------------------
def test_dynamic_head_starts_equal_to_static_head(static_net):
    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    features = torch.randn(3, static_net.config.num_cells, static_net.config.model_dim)
    static_out = static_net.head(features)
    assert static_out.abs().max() > 0
    assert torch.equal(net.head(features), static_out)
    assert torch.equal(net.dynamic_head(features), static_out)
    # A copy, not the same module: training the dynamic head leaves the static one alone.
    assert net.head is not static_net.head
    assert all(p.requires_grad for p in net.head.parameters())


def _stand_in_step(net, z, beta, theta, motion, params):
    """One Adam step on the squared distance of the output positions to a target."""
    cfg = net.config.static
    rigid, uv = _hair(24, cfg.num_vertices)
    target = rigid.clone()
    target[:, :, 2:, 1] -= 0.05  # 5 cm lower: gravity-like
    optimizer = torch.optim.Adam(params, lr=_LR)
    positions, _ = net.drape(z, beta, theta, motion, rigid, uv)
    loss = ((positions - target) ** 2).sum(-1).mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss


def test_functional_regularization_zero_at_init_then_positive(static_net):
    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    z, beta, theta = _inputs(static_net.config)
    motion = _motion(net.config)
    out = net(z, beta, theta, motion)
    reg = net.functional_regularization(out.static_features)
    assert reg.dim() == 0 and reg.item() == 0.0  # exactly: the head is a copy
    assert out.static_features.abs().max() > 0

    _stand_in_step(net, z, beta, theta, motion, net.trainable_parameters())
    reg = net.functional_regularization(out.static_features)
    assert reg.item() > 0.0
    reg.backward()  # differentiable w.r.t. the dynamic head only
    assert net.head.net[0].weight.grad is not None and net.head.net[0].weight.grad.abs().max() > 0
    assert all(p.grad is None for p in static_net.parameters())

    weighted = DynamicNetwork.from_static(
        static_net, dataclasses.replace(net.config, func_reg_weight=2.5)
    )
    weighted.load_state_dict(net.state_dict())
    torch.testing.assert_close(weighted.functional_regularization(out.static_features), 2.5 * reg.detach())


def test_static_network_frozen_inside_dynamic(static_net):
    before = {k: v.clone() for k, v in static_net.state_dict().items()}
    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    assert net.static is static_net
    static_params = list(static_net.parameters())
    assert len(static_params) > 0 and not any(p.requires_grad for p in static_params)
    trainable = {id(p) for p in net.trainable_parameters()}
    assert len(trainable) > 0 and not trainable & {id(p) for p in static_params}

    net.train()
    assert net.training and not static_net.training
    z, beta, theta = _inputs(static_net.config)
    motion = _motion(net.config)
    _stand_in_step(net, z, beta, theta, motion, net.trainable_parameters())
    assert all(p.grad is None for p in static_params)
    for k, v in static_net.state_dict().items():
        assert torch.equal(v, before[k]), k
    grads = [p.grad for p in net.trainable_parameters() if p.grad is not None]
    assert len(grads) > 0 and any(g.abs().max() > 0 for g in grads)


# ------------------------------------------------------------------------------------------------
# One training step on a stand-in loss
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["static", "quaffure"])
def test_adam_step_lowers_stand_in_loss(kind):
    torch.manual_seed(0)
    net = StaticNetwork(StaticConfig.tiny()) if kind == "static" else QuaffureNetwork(QuaffureConfig.tiny())
    cfg = net.config
    z, beta, theta = _inputs(cfg)
    rigid, uv = _hair(24, cfg.num_vertices)
    target = rigid.clone()
    target[:, :, 2:, 1] -= 0.05

    def loss_fn():
        return ((net.drape(z, beta, theta, rigid, uv) - target) ** 2).sum(-1).mean()

    optimizer = torch.optim.Adam(net.parameters(), lr=_LR)
    losses = []
    for _ in range(3):
        loss = loss_fn()
        losses.append(loss.item())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    losses.append(loss_fn().item())
    assert losses[0] > 0
    assert losses[1] < losses[0] and losses[-1] < losses[1]


# ------------------------------------------------------------------------------------------------
# Checkpoints
# ------------------------------------------------------------------------------------------------
def _build(kind):
    torch.manual_seed(0)
    if kind == "static":
        return StaticNetwork(StaticConfig.tiny())
    if kind == "quaffure":
        return QuaffureNetwork(QuaffureConfig.tiny())
    static = StaticNetwork(StaticConfig.tiny())
    net = DynamicNetwork.from_static(static, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    with torch.no_grad():  # move the dynamic head off its copy, so the round trip tests it
        net.head.net[0].weight.add_(0.01)
    return net


def _run(net):
    cfg = net.config.static if isinstance(net, DynamicNetwork) else net.config
    z, beta, theta = _inputs(cfg)
    if isinstance(net, DynamicNetwork):
        return net(z, beta, theta, _motion(net.config)).deformation_map
    return net(z, beta, theta)


@pytest.mark.parametrize("kind", ["static", "dynamic", "quaffure"])
def test_checkpoint_round_trip(kind, tmp_path):
    net = _build(kind).eval()
    with torch.no_grad():
        expected = _run(net)
    assert expected.abs().max() > 0

    path32 = tmp_path / "model32.pt"
    save_checkpoint(path32, net, net.config, step=7, extra={"phase": 2, "bp": 0.5})
    ckpt = load_checkpoint(path32)
    assert type(ckpt.model) is type(net)
    assert ckpt.config == net.config and ckpt.step == 7 and ckpt.extra == {"phase": 2, "bp": 0.5}
    assert ckpt.optimizer_state is None
    with torch.no_grad():
        assert torch.equal(_run(ckpt.model), expected)
    if kind == "dynamic":
        assert not any(p.requires_grad for p in ckpt.model.static.parameters())

    path16 = tmp_path / "model16.pt"
    save_checkpoint(path16, net, dtype=torch.float16)
    assert path16.stat().st_size < 0.6 * path32.stat().st_size
    half = load_checkpoint(path16)
    assert next(half.model.parameters()).dtype == torch.float32
    with torch.no_grad():
        got = _run(half.model)
    assert not torch.equal(got, expected)  # rounded, so storage really was half precision
    scale = expected.abs().max().item()
    torch.testing.assert_close(got, expected, rtol=0, atol=_F16_REL_TOL * scale)


def test_checkpoint_resume_continues_training_exactly(tmp_path):
    torch.manual_seed(0)
    net = StaticNetwork(StaticConfig.tiny())
    cfg = net.config
    z, beta, theta = _inputs(cfg)
    rigid, uv = _hair(24, cfg.num_vertices)
    target = rigid + 0.01

    def step(model, optimizer):
        loss = ((model.drape(z, beta, theta, rigid, uv) - target) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    optimizer = torch.optim.Adam(net.parameters(), lr=_LR)
    step(net, optimizer)
    save_checkpoint(tmp_path / "resume.pt", net, cfg, optimizer=optimizer, step=1)
    step(net, optimizer)  # the uninterrupted run

    ckpt = load_checkpoint(tmp_path / "resume.pt")
    resumed = ckpt.model.train()
    assert ckpt.step == 1 and ckpt.optimizer_state is not None
    optimizer2 = ckpt.restore_optimizer(torch.optim.Adam(resumed.parameters(), lr=_LR))
    step(resumed, optimizer2)
    for (name, a), b in zip(net.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name


def test_config_dict_round_trip_and_sizes():
    for cfg in (StaticConfig(), StaticConfig.tiny(), DynamicConfig(), DynamicConfig.tiny(fusion=FUSION_LORA),
                QuaffureConfig(), QuaffureConfig.tiny()):
        assert type(cfg).from_dict(cfg.to_dict()) == cfg
    defaults = StaticConfig()
    assert (defaults.model_dim, defaults.latent_dim, defaults.num_cells, defaults.num_vertices) == (512, 512, 64, 100)
    dyn = DynamicConfig()
    assert (dyn.window, dyn.lora_rank, dyn.lora_alpha, dyn.fusion) == (10, 4, 4.0, FUSION_CROSS_ATTENTION)
    with pytest.raises(ValueError, match="unknown"):
        StaticConfig.from_dict({**StaticConfig().to_dict(), "bogus": 1})


# ------------------------------------------------------------------------------------------------
# Ablation variants (Section 4.5.2)
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fusion", FUSIONS)
def test_ablation_variants_run_and_train(static_net, fusion):
    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM, fusion=fusion))
    cfg = static_net.config
    z, beta, theta = _inputs(cfg)
    motion = _motion(net.config, frames=2)
    poses = torch.stack([theta, theta * 0.9], dim=1)
    out = net.simulate(z, beta, poses, motion)
    assert out.deformation_map.shape == (BATCH, 2, cfg.grid_height, cfg.grid_width, cfg.num_vertices, 3)
    assert torch.isfinite(out.deformation_map).all()

    drift0 = net.head_drift(out.static_features[:, 0]).item()
    reg0 = net.functional_regularization(out.static_features[:, 0]).item()
    if fusion == FUSION_LAYERNORM_CONCAT:
        assert net.head.net[0].in_features == 2 * cfg.model_dim
        assert len(net.static_dynamic_blocks) == 0
        assert reg0 < 1e-12  # not exactly zero: the LayerNorm sits in front of the copied head
    else:
        assert len(net.static_dynamic_blocks) == net.config.num_static_dynamic_layers
        assert drift0 == 0.0 and reg0 == 0.0

    trainable = net.trainable_parameters()
    loss = _stand_in_step(net, z, beta, theta, motion[:, 0], trainable)
    assert loss.item() > 0
    with_grad = [p for p in trainable if p.grad is not None and p.grad.abs().max() > 0]
    assert len(with_grad) > 0
    if fusion == FUSION_LORA:
        assert not net.uses_functional_regularization
        frozen_head = [p for n, p in net.head.named_parameters() if ".base." in n]
        adapters = [p for n, p in net.head.named_parameters() if ".down." in n or ".up." in n]
        assert len(frozen_head) > 0 and not any(p.requires_grad for p in frozen_head)
        assert len(adapters) == 2 * net.config.static.head_layers and all(p.requires_grad for p in adapters)
        # Eq. 4 is replaced by LoRA: zero even after the head moved.
        assert net.head_drift(out.static_features[:, 0]).item() > 0
        assert net.functional_regularization(out.static_features[:, 0]).item() == 0.0
    else:
        assert net.uses_functional_regularization
        assert net.functional_regularization(out.static_features[:, 0]).item() > reg0


def test_parameter_counts_scale_with_config(static_net):
    tiny_static = parameter_count(static_net)
    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    assert parameter_count(net) > parameter_count(net, trainable_only=True) > 0
    assert parameter_count(net) - parameter_count(net, trainable_only=True) == tiny_static


# ------------------------------------------------------------------------------------------------
# Bad inputs
# ------------------------------------------------------------------------------------------------
def test_bad_inputs_raise_value_error_naming_the_argument(static_net):
    cfg = static_net.config
    z, beta, theta = _inputs(cfg)
    with pytest.raises(ValueError, match="^z:"):
        static_net(z[:, :-1], beta, theta)
    with pytest.raises(ValueError, match="^theta:"):
        static_net(z, beta, theta[:, :63])
    with pytest.raises(ValueError, match="^beta:"):
        static_net(z, beta[:, :10], theta)
    with pytest.raises(ValueError, match="^beta:.*batch"):
        static_net(z, beta[:1], theta)
    with pytest.raises(ValueError, match="^z:.*dtype"):
        static_net(z.double(), beta, theta)
    with pytest.raises(ValueError, match="^theta:.*NaN"):
        static_net(z, beta, theta.clone().fill_(float("nan")))
    with pytest.raises(ValueError, match="^z:.*empty"):
        static_net(z[:0], beta[:0], theta[:0])
    with pytest.raises(ValueError, match="^z:"):
        static_net(z[0], beta, theta)  # unbatched
    with pytest.raises(ValueError, match="^clip:"):
        static_net(z, beta, theta, clip=-1.0)

    quaffure = QuaffureNetwork(QuaffureConfig.tiny())
    with pytest.raises(ValueError, match="^z:"):
        quaffure(z[:, :5], beta, theta)
    with pytest.raises(ValueError, match="^theta:"):
        quaffure(z, beta, theta[:, :65])

    net = DynamicNetwork.from_static(static_net, DynamicConfig.tiny(motion_dim=MOTION_DIM))
    motion = _motion(net.config)
    with pytest.raises(ValueError, match="^z:"):
        net(z[:, 1:], beta, theta, motion)
    with pytest.raises(ValueError, match="^theta:"):
        net(z, beta, theta[:, 1:], motion)
    with pytest.raises(ValueError, match="^motion:"):
        net(z, beta, theta, motion[:, 1:])  # wrong window
    with pytest.raises(ValueError, match="^motion:"):
        net(z, beta, theta, motion[..., 1:])  # wrong descriptor size
    with pytest.raises(ValueError, match="^hidden:"):
        net(z, beta, theta, motion, torch.zeros(BATCH, cfg.model_dim + 1))
    with pytest.raises(ValueError, match="^poses:"):
        net.simulate(z, beta, theta, motion)  # one pose per batch entry, not a sequence
    with pytest.raises(ValueError, match="^motion:.*frames"):
        net.simulate(z, beta, theta[:, None].expand(-1, 3, -1), _motion(net.config, frames=2))
    with pytest.raises(ValueError, match="^static_features:"):
        net.functional_regularization(torch.zeros(BATCH, cfg.num_cells + 1, cfg.model_dim))

    rigid, uv = _hair(10, cfg.num_vertices)
    dmap = torch.zeros(BATCH, 8, 8, cfg.num_vertices, 3)
    with pytest.raises(ValueError, match="^rigid:"):
        apply_deformation(rigid[..., :2], dmap, uv)
    with pytest.raises(ValueError, match="^deformation_map:.*vertices"):
        apply_deformation(rigid, dmap[..., 1:, :], uv)
    with pytest.raises(ValueError, match="^deformation_map:.*dtype"):
        apply_deformation(rigid, dmap.double(), uv)
    with pytest.raises(ValueError, match="^root_uv:"):
        apply_deformation(rigid, dmap, uv[1:])
    with pytest.raises(ValueError, match="^root_uv:"):
        apply_deformation(rigid, dmap, uv[:, :1])
    with pytest.raises(ValueError, match="^root_uv:.*NaN"):
        apply_deformation(rigid, dmap, uv.clone().fill_(float("inf")))
    with pytest.raises(ValueError, match="^num_vertices:"):
        taper_weights(2)


def test_bad_configs_and_checkpoint_inputs(static_net, tmp_path):
    with pytest.raises(ValueError, match="model_dim"):
        StaticConfig(model_dim=30, num_heads=4)
    with pytest.raises(ValueError, match="fusion"):
        DynamicConfig(fusion="concat")
    with pytest.raises(ValueError, match="num_vertices"):
        StaticConfig(num_vertices=2)
    with pytest.raises(ValueError, match="channels"):
        QuaffureConfig(channels=(8, 8, 8))
    other = DynamicConfig.tiny(motion_dim=MOTION_DIM)
    with pytest.raises(ValueError, match="^config:"):
        DynamicNetwork(dataclasses.replace(other, static=StaticConfig()), static_net)
    with pytest.raises(ValueError, match="^dtype:"):
        save_checkpoint(tmp_path / "x.pt", static_net, dtype=torch.bfloat16)
    with pytest.raises(ValueError, match="^config:"):
        save_checkpoint(tmp_path / "x.pt", static_net, QuaffureConfig.tiny())
    with pytest.raises(ValueError, match="^model:"):
        save_checkpoint(tmp_path / "x.pt", torch.nn.Linear(2, 2), StaticConfig.tiny())
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="^path:"):
        load_checkpoint(tmp_path / "foreign.pt")
