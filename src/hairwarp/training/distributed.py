"""Data-parallel training on PyTorch's own engine: torchrun, torch.distributed, DDP.

    torchrun --nproc_per_node 2 --no-python hairwarp train static --device cuda --out run/

What a run of K ranks means (docs/distributed.md has the user's version):

- Start-up. torchrun sets RANK, WORLD_SIZE and LOCAL_RANK; `init_distributed` reads them and
  starts the process group: NCCL on CUDA (each rank on cuda:LOCAL_RANK, set as torch's and
  Warp's current device, so the Warp energy kernels launch on the rank's own GPU and on torch's
  current stream there), gloo on the CPU. Without those variables, or with WORLD_SIZE = 1,
  nothing is started: the single-process path is the one it always was.
- Batches. `batch_size` is the global batch (the paper's 32). Every rank makes the global
  batch's random draws and builds its own contiguous share of the samples
  (`hairwarp.training.data.shard_bounds`), so the shares together are the single-process batch
  of the same seed and step. Phase 0's one-sample batch is replicated.
- Loss and gradients. A rank back-propagates its batch mean times share x K (share = its
  samples / global samples); DDP averages the gradients over the K ranks, which gives the
  gradient of the global batch mean: the parameters follow the single-process run with the
  same global batch, up to float summation order. The logged loss and terms are the global
  batch means (one small all-reduce per step); a failure on one rank (a NaN, a bad network
  output) stops every rank at the same step instead of leaving the others waiting.
- Files. Rank 0 writes config.toml, log.jsonl, checkpoint.pt and the progress bar; every rank
  waits at a barrier after each checkpoint write and before reading a checkpoint to resume.
- Resume at another world size. A checkpoint holds the weights, the optimizer state (the same
  on every rank), the step and the seed. The global batch of step s depends on (seed, s)
  only, so a run resumed with K' ranks draws the very global batches the K-rank run would
  have drawn, each rank now building 1/K' of them: the same training trajectory, equal up to
  float summation order (not bitwise). batch_size stays global, so no learning-rate change
  is implied; the memory of each rank scales with batch_size / K'.
"""

from __future__ import annotations

import atexit
import inspect
import os
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch import nn

from hairwarp import _warp

ENV_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK")


@dataclass(frozen=True)
class DistributedContext:
    """Where this process stands in a data-parallel run.

    Attributes:
        rank: global rank (0 writes the files).
        world_size: number of ranks (1: no process group).
        local_rank: rank on this host (its GPU index).
        device: the torch device this rank trains on.
        backend: "nccl" or "gloo", or None when no process group is used.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    backend: str | None = None

    @property
    def is_distributed(self) -> bool:
        """More than one rank: a process group and DDP are used."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: writes the log, the checkpoints and the progress bar."""
        return self.rank == 0


def _env_int(env: Mapping, name: str, default: int | None = None) -> int:
    text = env.get(name)
    if text is None:
        if default is None:
            raise ValueError(f"{name}: not set (torchrun sets RANK, WORLD_SIZE and LOCAL_RANK)")
        return default
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{name}: expected an integer, got {text!r}") from None


def plan_from_env(
    device: torch.device | str = "cpu", env: Mapping | None = None, cuda_device_count: int | None = None
) -> DistributedContext:
    """The context torchrun's environment asks for, without starting anything.

    Args:
        device: the device asked for ("cpu", "cuda"; with several ranks "cuda" becomes
            cuda:LOCAL_RANK).
        env: the environment (None: `os.environ`).
        cuda_device_count: visible CUDA devices (None: asks torch).

    Returns:
        A DistributedContext; world_size 1 (no WORLD_SIZE, or WORLD_SIZE = 1) keeps `device`
        as given and uses no backend.

    Raises:
        ValueError: naming the variable or argument: non-integer or inconsistent RANK /
            WORLD_SIZE / LOCAL_RANK, a LOCAL_RANK without a GPU, a device other than cpu or
            cuda, or an explicit cuda:N that is not this rank's GPU.
    """
    env = os.environ if env is None else env
    device = torch.device(device)
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected cpu or cuda, got {device}")
    if "WORLD_SIZE" not in env:
        return DistributedContext(device=device)
    world_size = _env_int(env, "WORLD_SIZE")
    if world_size < 1:
        raise ValueError(f"WORLD_SIZE: expected an int >= 1, got {world_size}")
    rank = _env_int(env, "RANK")
    if not 0 <= rank < world_size:
        raise ValueError(f"RANK: expected 0 <= RANK < WORLD_SIZE={world_size}, got {rank}")
    local_rank = _env_int(env, "LOCAL_RANK", default=rank)
    if local_rank < 0:
        raise ValueError(f"LOCAL_RANK: expected an int >= 0, got {local_rank}")
    if world_size == 1:
        return DistributedContext(device=device)
    if device.type == "cuda":
        count = torch.cuda.device_count() if cuda_device_count is None else cuda_device_count
        if local_rank >= count:
            raise ValueError(f"LOCAL_RANK: {local_rank} but this host shows {count} CUDA device(s)")
        if device.index is not None and device.index != local_rank:
            raise ValueError(
                f"device: {device} asked for, but rank {rank} (LOCAL_RANK={local_rank}) trains on "
                f"cuda:{local_rank}; pass --device cuda"
            )
        return DistributedContext(rank, world_size, local_rank, torch.device("cuda", local_rank), "nccl")
    return DistributedContext(rank, world_size, local_rank, device, "gloo")


def init_distributed(device: torch.device | str = "cpu", env: Mapping | None = None) -> DistributedContext:
    """Join the data-parallel run torchrun started (or do nothing in a single process).

    On CUDA, sets torch's and Warp's current device to cuda:LOCAL_RANK before the process group
    starts (NCCL binds each rank to its GPU). The process group lives until the process exits
    (destroyed then), so several trainings of one torchrun job (static, then dynamic) share it:
    a running process group, this function's or the caller's, is used as it is and must agree
    with the environment. (Destroying and re-creating the group between trainings raced on
    the rendezvous keys of the first one.)

    Args:
        device: "cpu" or "cuda" (see `plan_from_env`).
        env: the environment (None: `os.environ`).

    Returns:
        The DistributedContext.

    Raises:
        ValueError: see `plan_from_env`; or a running process group of another size or rank.
    """
    ctx = plan_from_env(device, env)
    if not ctx.is_distributed:
        return ctx
    if ctx.device.type == "cuda":
        torch.cuda.set_device(ctx.device)
        _warp.set_default_device(ctx.device)
    if dist.is_initialized():
        if (dist.get_rank(), dist.get_world_size()) != (ctx.rank, ctx.world_size):
            raise ValueError(
                f"RANK, WORLD_SIZE: the running process group is rank {dist.get_rank()} of "
                f"{dist.get_world_size()}, the environment says {ctx.rank} of {ctx.world_size}"
            )
        return ctx
    kwargs = {"device_id": ctx.device} if ctx.backend == "nccl" else {}
    dist.init_process_group(backend=ctx.backend, init_method="env://", rank=ctx.rank,
                            world_size=ctx.world_size, **kwargs)
    atexit.register(_destroy)
    return ctx


def _destroy() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def check_process_group(rank: int, world_size: int) -> None:
    """Raise unless a process group of `world_size` ranks runs with this process as `rank`.

    Raises:
        ValueError: naming world_size or rank.
    """
    for name, value, low in (("world_size", world_size, 1), ("rank", rank, 0)):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    if rank >= world_size:
        raise ValueError(f"rank: expected 0 <= rank < world_size={world_size}, got {rank}")
    if world_size == 1:
        return
    if not dist.is_initialized():
        raise ValueError(
            f"world_size: {world_size} ranks asked for but torch.distributed is not initialised; "
            "start the run with torchrun (or call hairwarp.training.distributed.init_distributed)"
        )
    if (dist.get_rank(), dist.get_world_size()) != (rank, world_size):
        raise ValueError(
            f"rank, world_size: ({rank}, {world_size}) asked for, the process group is "
            f"({dist.get_rank()}, {dist.get_world_size()})"
        )


def barrier(device: torch.device) -> None:
    """Wait for every rank (no-op without a process group)."""
    if not dist.is_initialized() or dist.get_world_size() == 1:
        return
    if device.type == "cuda" and dist.get_backend() == "nccl":
        dist.barrier(device_ids=[device.index if device.index is not None else torch.cuda.current_device()])
    else:
        dist.barrier()


def all_reduce_sum(values: list[float], device: torch.device) -> list[float]:
    """Sum a few floats over the ranks (float64, on `device`: NCCL needs a CUDA tensor)."""
    t = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t.tolist()


class LossModule(nn.Module):
    """The model with the trainer's loss as its forward, for DDP.

    DDP prepares the gradient all-reduce in `forward`; the dynamic loss calls `simulate` and
    `functional_regularization`, not `forward`, so the whole loss is one forward here.

    Args:
        model: the network being trained (a submodule: DDP syncs its trainable parameters).
        loss: callable (batch, step, model) -> (loss tensor, terms, extras).
    """

    def __init__(self, model: nn.Module, loss):
        super().__init__()
        self.model = model
        self._loss = loss

    def forward(self, batch, step: int):
        return self._loss(batch, step, self.model)


def wrap_ddp(model: nn.Module, loss) -> nn.parallel.DistributedDataParallel:
    """`LossModule(model, loss)` in DistributedDataParallel (parameters broadcast from rank 0).

    device_ids=None: the batches hold Warp meshes that must not be moved or copied by DDP's
    input scattering (they already live on the rank's device). broadcast_buffers=False: the
    networks' buffers are fixed encodings, never updated by training.
    """
    ddp = nn.parallel.DistributedDataParallel
    # torch >= 2.13 names it forward_sync_buffers (and deprecates broadcast_buffers).
    sync = "forward_sync_buffers" if "forward_sync_buffers" in inspect.signature(ddp).parameters else "broadcast_buffers"
    return ddp(LossModule(model, loss), device_ids=None, **{sync: False})


__all__ = [
    "DistributedContext",
    "ENV_VARIABLES",
    "LossModule",
    "all_reduce_sum",
    "barrier",
    "check_process_group",
    "init_distributed",
    "plan_from_env",
    "wrap_ddp",
]
