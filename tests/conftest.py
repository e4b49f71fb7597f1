"""Shared test set-up: devices in one place, Warp initialised once, float64 by default."""

import pytest
import torch

from hairwarp import _warp

_warp.init()

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    """Every device the machine has: CPU always, CUDA when present."""
    return torch.device(request.param)


@pytest.fixture
def rng():
    """A seeded numpy generator, so each test sees the same random cases every run."""
    import numpy as np

    return np.random.default_rng(1234)
