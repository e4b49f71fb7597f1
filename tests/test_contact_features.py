"""Contact features of the rigid placement (`hairwarp.models.contact_features`, the static
network's `contact_samples` option): their values against an analytic sphere, the cell pooling,
the network that reads them (shapes, a training step, the checks on its input), and the method
that drapes with them."""

import math

import numpy as np
import pytest
import torch

from hairwarp.models import StaticConfig, StaticNetwork
from hairwarp.models.contact_features import (
    DISTANCE_SCALE,
    FEATURES_PER_SAMPLE,
    OFFSET_SCALE,
    contact_features,
    network_deformation,
    sample_indices,
)
from hairwarp.ops import BodyMesh
from meshes import icosphere

RADIUS = 0.1


def _sphere_body():
    v, f = icosphere(frequency=16, radius=RADIUS)
    return BodyMesh(torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f, dtype=torch.int64))


def _strands(batch=2, num_vertices=12):
    """Four straight strands falling along -y through a sphere at the origin: two roots at
    x = +-0.05 (they cross it), two at x = +-0.3 (they miss it); batch item 1 shifted by 1 cm."""
    xs = torch.tensor([0.05, -0.05, 0.3, -0.3], dtype=torch.float64)
    drop = torch.linspace(0.0, 0.3, num_vertices, dtype=torch.float64)
    rigid = torch.zeros(batch, 4, num_vertices, 3, dtype=torch.float64)
    rigid[..., 0] = xs[:, None]
    rigid[..., 1] = 0.15 - drop
    rigid[1, ..., 2] += 0.01
    # Strands 0 and 2 in cell 0, strands 1 and 3 in cell 3 of a 2 x 2 grid.
    root_uv = torch.tensor([[0.1, 0.1], [0.9, 0.9], [0.2, 0.2], [0.8, 0.8]], dtype=torch.float64)
    return rigid, root_uv


def _reference(rigid, root_uv, samples):
    """Per-cell means of (clamped distance, push vector, offset) from the analytic sphere."""
    x = rigid.numpy()[:, :, sample_indices(rigid.shape[2], samples).numpy()]
    r = np.linalg.norm(x, axis=-1)
    d = r - RADIUS
    n = x / r[..., None]
    per = np.concatenate([np.clip(d, -DISTANCE_SCALE, DISTANCE_SCALE)[..., None] / DISTANCE_SCALE,
                          (np.clip(-d, 0, DISTANCE_SCALE) / DISTANCE_SCALE)[..., None] * n,
                          (x - rigid.numpy()[:, :, :1]) / OFFSET_SCALE], axis=-1).reshape(x.shape[0], 4, -1)
    out = np.zeros((x.shape[0], 4, per.shape[-1]))
    out[:, 0] = per[:, [0, 2]].mean(1)
    out[:, 3] = per[:, [1, 3]].mean(1)
    return out


def test_features_match_an_analytic_sphere_pooled_per_cell():
    rigid, root_uv = _strands()
    got = contact_features(rigid, root_uv, _sphere_body(), 2, 2, samples=5)
    assert got.shape == (2, 4, 5 * FEATURES_PER_SAMPLE)
    expected = _reference(rigid, root_uv, 5)
    # The icosphere's facets sit inside the sphere by up to ~0.3 mm and their normals are off
    # the radial direction by up to ~1 deg: the push vector differs by ~1e-2 of its length.
    assert np.abs(got.numpy() - expected).max() < 0.02
    assert float(got[:, 1:3].abs().max()) == 0.0  # cells without strands
    assert float(got[:, 0, 1::FEATURES_PER_SAMPLE].max()) > 0.1  # inside vertices push outwards


def test_network_reads_contact_features_and_trains():
    torch.manual_seed(0)
    cfg = StaticConfig(**{**StaticConfig.tiny().to_dict(), "grid_height": 2, "grid_width": 2, "num_vertices": 12,
                          "contact_samples": 5})
    net = StaticNetwork(cfg).double()
    rigid, root_uv = _strands()
    body = _sphere_body()
    z, beta, theta = torch.randn(2, cfg.latent_dim).double(), torch.zeros(2, 16).double(), torch.zeros(2, 66).double()
    d = network_deformation(net, z, beta, theta, rigid, root_uv, body)
    assert d.shape == (2, 2, 2, 12, 3)
    # The features change the output: the same inputs with the sphere moved away differ.
    v, f = icosphere(frequency=16, radius=RADIUS, center=(0.0, 0.0, 5.0))
    far = BodyMesh(torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f, dtype=torch.int64))
    assert not torch.allclose(d, network_deformation(net, z, beta, theta, rigid, root_uv, far))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    contact = net.contact_features(rigid, root_uv, body)
    losses = []
    for _ in range(20):
        x = net.drape(z, beta, theta, rigid, root_uv, contact=contact)
        loss = (x[..., 1] - rigid[..., 1] - 0.01).square().mean()  # lift every strand by 1 cm
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
    assert net.contact_encoder[0].weight.grad.abs().max() > 0
    with pytest.raises(ValueError, match="contact: this network reads contact features"):
        net(z, beta, theta)
    with pytest.raises(ValueError, match="contact: expected shape"):
        net(z, beta, theta, contact=contact[:, :3])
    with pytest.raises(ValueError, match="body: the network reads contact features"):
        net.contact_features(rigid, root_uv, None)
    plain = StaticNetwork(StaticConfig(**{**cfg.to_dict(), "contact_samples": 0})).double()
    assert plain.contact_features(rigid, root_uv, body) is None
    with pytest.raises(ValueError, match="contact: this network reads no contact features"):
        plain(z, beta, theta, contact=contact)
    with pytest.raises(ValueError, match="contact_samples"):
        StaticConfig(contact_samples=-1)
    assert math.isfinite(losses[-1])
