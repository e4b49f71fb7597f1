"""Save and load HairFormer networks: self-describing files that rebuild the model.

A checkpoint stores the network's kind ("static", "dynamic", "quaffure", "inertial"), its config as a plain
dict, its weights (float32, or float16 for shipping: half the size, loaded back to float32), and
optionally the optimizer state, the step and user data for resuming training. Files are read
with `torch.load(weights_only=True)`: no code runs at load, so `extra` must be plain data
(dicts, lists, tuples, str, numbers, bools, None, tensors).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from hairwarp.models.config import DynamicConfig, QuaffureConfig, StaticConfig
from hairwarp.models.dynamic import DynamicNetwork
from hairwarp.models.inertial import InertialConfig, InertialStep
from hairwarp.models.quaffure import QuaffureNetwork
from hairwarp.models.static import StaticNetwork

FORMAT = "hairwarp-checkpoint"
VERSION = 1
STORAGE_DTYPES = (torch.float32, torch.float16)

_KINDS = {
    "static": (StaticNetwork, StaticConfig),
    "dynamic": (DynamicNetwork, DynamicConfig),
    "quaffure": (QuaffureNetwork, QuaffureConfig),
    "inertial": (InertialStep, InertialConfig),
}


@dataclass
class Checkpoint:
    """What `load_checkpoint` returns.

    Attributes:
        model: the rebuilt network with its weights, on the requested device, in eval mode.
        config: its config dataclass.
        step: the training step stored with it.
        optimizer_state: the optimizer's `state_dict()`, or None.
        extra: the user data stored with it, or None.
    """

    model: nn.Module
    config: Any
    step: int
    optimizer_state: dict | None
    extra: Any

    def restore_optimizer(self, optimizer: torch.optim.Optimizer) -> torch.optim.Optimizer:
        """Load the stored state into `optimizer` (built on `model`'s trainable parameters, in
        the same order as when saved); its tensors move to the parameters' device.
        """
        if self.optimizer_state is None:
            raise ValueError("optimizer: the checkpoint holds no optimizer state")
        optimizer.load_state_dict(self.optimizer_state)
        return optimizer


def _kind_of(model: nn.Module) -> str:
    for kind, (cls, _) in _KINDS.items():
        if type(model) is cls:
            return kind
    names = ", ".join(cls.__name__ for cls, _ in _KINDS.values())
    raise ValueError(f"model: expected one of {names}, got {type(model).__name__}")


def save_checkpoint(
    path: str | os.PathLike,
    model: nn.Module,
    config=None,
    optimizer: torch.optim.Optimizer | None = None,
    step: int = 0,
    extra: Any = None,
    *,
    dtype: torch.dtype = torch.float32,
) -> None:
    """Write a model (and optionally its training state) to `path`.

    Args:
        path: file to write (conventionally `*.pt`); its folder must exist.
        model: a StaticNetwork, DynamicNetwork or QuaffureNetwork.
        config: the model's config; None takes `model.config`. Must equal `model.config`.
        optimizer: optional optimizer whose state is stored for resuming.
        step: training step to store (>= 0).
        extra: optional plain data to store (curriculum phase, b_p, metrics...).
        dtype: storage dtype of the weights: float32 (exact) or float16 (shipping; weights are
            rounded, loading returns float32).

    Raises:
        ValueError: on an unknown model, a config that does not match it, a bad dtype or step,
            or weights that are not finite in the storage dtype.
    """
    kind = _kind_of(model)
    config = model.config if config is None else config
    if not isinstance(config, _KINDS[kind][1]) or config != model.config:
        raise ValueError(f"config: expected the model's own {_KINDS[kind][1].__name__}")
    if dtype not in STORAGE_DTYPES:
        raise ValueError(f"dtype: expected torch.float32 or torch.float16, got {dtype}")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise ValueError(f"step: expected a non-negative int, got {step!r}")
    state = {}
    for name, value in model.state_dict().items():
        value = value.detach().to("cpu")
        if value.is_floating_point():
            value = value.to(dtype)
            if not bool(torch.isfinite(value).all()):
                raise ValueError(f"model: weight {name} is not finite when stored as {dtype}")
        state[name] = value.clone()
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "kind": kind,
        "config": config.to_dict(),
        "weights_dtype": str(dtype).replace("torch.", ""),
        "state_dict": state,
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "step": step,
        "extra": extra,
    }
    torch.save(payload, os.fspath(path))


def load_checkpoint(
    path: str | os.PathLike, device: torch.device | str = "cpu", *, dtype: torch.dtype = torch.float32
) -> Checkpoint:
    """Rebuild a model from a file written by `save_checkpoint`.

    Args:
        path: the checkpoint file.
        device: where to put the model ("cpu", "cuda", a torch.device).
        dtype: the model's parameter dtype (float32; float64 for gradient checks), whatever
            the storage dtype was.

    Returns:
        A Checkpoint: the model in eval mode (call `.train()` to resume training), its config,
        step, optimizer state and extra data.

    Raises:
        ValueError: if the file is not a hairwarp checkpoint or names an unknown model kind.
    """
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
    payload = torch.load(os.fspath(path), map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"path: {os.fspath(path)} is not a {FORMAT} file")
    if payload.get("version") != VERSION:
        raise ValueError(f"path: unsupported checkpoint version {payload.get('version')!r}")
    kind = payload.get("kind")
    if kind not in _KINDS:
        raise ValueError(f"path: unknown model kind {kind!r}")
    model_cls, config_cls = _KINDS[kind]
    config = config_cls.from_dict(payload["config"])
    model = model_cls(config)
    state = {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in payload["state_dict"].items()}
    model = model.to(dtype=dtype)
    model.load_state_dict(state)
    model = model.to(torch.device(device)).eval()
    return Checkpoint(model, config, int(payload["step"]), payload["optimizer"], payload["extra"])


def parameter_count(model: nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters (shared ones once); `trainable_only` counts `requires_grad` ones."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def storage_bytes(model: nn.Module, dtype: torch.dtype = torch.float16) -> int:
    """Bytes of the model's floating-point state (parameters and persistent buffers) in `dtype`."""
    size = torch.tensor([], dtype=dtype).element_size()
    return sum(v.numel() * (size if v.is_floating_point() else v.element_size()) for v in model.state_dict().values())


__all__ = [
    "Checkpoint",
    "save_checkpoint",
    "load_checkpoint",
    "parameter_count",
    "storage_bytes",
]
