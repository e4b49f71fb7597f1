"""tools/swing_decomposition.py: the lag, axis and groom / strand split of a swing against the physics'."""

import importlib.util
import math
import os

import pytest
import torch

_PATH = os.path.join(os.path.dirname(__file__), os.pardir, "tools", "swing_decomposition.py")
_spec = importlib.util.spec_from_file_location("swing_decomposition", _PATH)
sd = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sd)


def _swinging(frames=60, strands=6, vertices=5, delay=0):
    """Rigid strands hanging along -y, and the same strands whose vertices swing in x with a
    per-strand amplitude, `delay` frames late, plus a per-strand y motion of its own phase."""
    rigid = torch.zeros(frames, strands, vertices, 3, dtype=torch.float64)
    rigid[..., 1] = -0.05 * torch.arange(vertices, dtype=torch.float64)
    rigid[..., 0] = 0.02 * torch.arange(strands, dtype=torch.float64)[:, None]
    t = torch.arange(frames, dtype=torch.float64) - delay
    amplitude = 0.01 * (1.0 + torch.arange(strands, dtype=torch.float64))
    phase = torch.linspace(0.0, math.pi, strands, dtype=torch.float64)
    x = rigid.clone()
    x[..., 0] += (amplitude[None, :] * torch.sin(2 * math.pi * t[:, None] / 30))[..., None]
    x[..., 1] += (0.005 * torch.sin(2 * math.pi * t[:, None] / 20 + phase[None, :]))[..., None]
    return x, rigid


def test_a_late_swing_is_found_at_its_lag():
    physics, rigid = _swinging()
    late, _ = _swinging(delay=3)
    out = sd.decompose(late, physics, rigid)
    assert out["best_lag"] == 3
    assert out["best_lag_correlation"] == pytest.approx(1.0, abs=1e-9)
    assert out["lag_correlation"][0] < 0.95
    same = sd.decompose(physics, physics, rigid)
    assert same["best_lag"] == 0
    for part in ("groom_mean", "strand_residual"):
        assert same[part]["correlation"] == pytest.approx(1.0, abs=1e-9)
        assert same[part]["step_rms_mm"] == pytest.approx(same[part]["physics_rms_mm"])


def test_a_groom_moving_as_one_has_the_mean_swing_and_no_residual():
    physics, rigid = _swinging()
    offset = physics - rigid
    together = rigid + offset.mean(dim=1, keepdim=True)  # every strand does the groom's mean
    out = sd.decompose(together, physics, rigid)
    assert out["groom_mean"]["correlation"] == pytest.approx(1.0, abs=1e-9)
    assert out["groom_mean"]["step_rms_mm"] == pytest.approx(out["groom_mean"]["physics_rms_mm"])
    assert out["strand_residual"]["step_rms_mm"] == pytest.approx(0.0, abs=1e-9)
    assert out["strand_residual"]["physics_rms_mm"] > 1.0
    assert out["axes"]["z"]["physics_rms_mm"] == pytest.approx(0.0, abs=1e-12)
    assert out["axes"]["z"]["correlation"] is None
