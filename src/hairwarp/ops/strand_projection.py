"""Torch bridge of the follow-the-leader length projection; device code in
`hairwarp.kernels.strand_projection`.

A deformation added to the rigid placement (Eq. 2) stretches strands unless the network learns
to rotate every segment exactly; projecting the deformed strand back to its rest lengths makes
length preservation hold by construction, so the stretch term no longer fights the contact
terms in training (`StaticConfig.length_projection = "follow_the_leader"`).
"""

from __future__ import annotations

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from hairwarp import _warp
from hairwarp._validate import check_tensor
from hairwarp.config import NUM_FIXED_VERTICES
from hairwarp.kernels import strand_projection as kernels

# Below this leader-to-target distance [m] the rigid segment direction is kept (no gradient).
FOLLOW_THE_LEADER_EPS = 1e-9
# The adjoint's gain cap when none is asked for: above any l_i / |q_i - x_(i-1)| a float32 holds.
UNCAPPED_GAIN = 1e30


def _tiled(target: torch.Tensor, tiled: bool | None) -> bool:
    """Whether the tile kernels (a block per strand) run: on CUDA, for strands that fit their
    shared memory (`kernels.TILED_MAX_SHARED_BYTES`); `tiled` forces the choice (tests).
    """
    if tiled is not None:
        return tiled
    fits = 5 * target.shape[-2] * 3 * target.element_size() <= kernels.TILED_MAX_SHARED_BYTES
    return target.is_cuda and fits


def _launch(direction: str, target: torch.Tensor, arrays, outputs, tiled: bool | None = None,
            max_gain: float | None = None) -> None:
    """The projection's `direction` ("forward" or "adjoint") over the strands of `target`
    (..., M, N, 3): `kernel`(*arrays, [N,] eps, [max_gain,] *outputs), one thread or one block
    per strand; the adjoint's gain capped at `max_gain` (None: uncapped).
    """
    n = target.shape[-2]
    strands = target.numel() // (3 * n)
    if strands == 0:
        return
    scalars = [_warp.scalar(FOLLOW_THE_LEADER_EPS, target.dtype)]
    if direction == "adjoint":
        scalars.append(_warp.scalar(UNCAPPED_GAIN if max_gain is None else max_gain, target.dtype))
    inputs = [_warp.as_warp(a, vec3=True) for a in arrays]
    outputs = [_warp.as_warp(o, vec3=True) for o in outputs]
    device = _warp.warp_device(target.device)
    with _warp.launch_scope(target.device):
        if _tiled(target, tiled):
            vec = wp.vec3d if target.dtype == torch.float64 else wp.vec3f
            forward, adjoint = kernels.follow_the_leader_tiled_kernels(n, vec)
            _warp.launch(forward if direction == "forward" else adjoint, dim=strands, inputs=inputs + scalars,
                         outputs=outputs, device=device, block_dim=kernels.TILED_BLOCK_DIM)
        else:
            kernel = kernels.follow_the_leader_kernel if direction == "forward" else kernels.follow_the_leader_adjoint_kernel
            _warp.launch(kernel, dim=strands, inputs=inputs + [n] + scalars, outputs=outputs, device=device)


class _FollowTheLeader(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rigid, target, tiled, max_gain):
        rigid, target = rigid.contiguous(), target.contiguous()
        out = torch.empty_like(target)
        _launch("forward", target, (rigid, target), (out,), tiled)
        ctx.save_for_backward(rigid, target, out)
        ctx.tiled = tiled
        ctx.max_gain = max_gain
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        rigid, target, out = ctx.saved_tensors
        grad_target = torch.empty_like(target)
        _launch("adjoint", target, (rigid, target, out, grad_out.contiguous()), (grad_target,), ctx.tiled, ctx.max_gain)
        return None, grad_target, None, None


def follow_the_leader(rigid: torch.Tensor, target: torch.Tensor, *, check: bool = True,
                      tiled: bool | None = None, max_gain: float | None = None) -> torch.Tensor:
    """Project target strands onto the rest segment lengths of the rigid placement.

    x_k = target_k for the fixed vertices k < 2; then x_i = x_{i-1} + l_i * unit(target_i -
    x_{i-1}) with l_i = |rigid_i - rigid_{i-1}|: every segment of the result has its rest length,
    and each vertex lies on the ray from its (projected) predecessor towards its target.

    Args:
        rigid: (..., M, N, 3) strands whose segment lengths are the rest lengths [m] (the
            rigid placement, Eq. 1); treated as constant (no gradient).
        target: (..., M, N, 3) wanted positions [m], same shape, dtype and device.
        check: validate the arguments (False: a caller that built them; each check of a
            tensor's values waits for a GPU).
        tiled: run the tile kernels (a block per strand, the strand in shared memory) or the
            one-thread kernels; default: the tile kernels on CUDA where the strand fits.
        max_gain: None, the exact gradient; a number, the adjoint with each vertex's gain
            l_i / |target_i - x_(i-1)| capped at it (the same kernels; the forward is the same).
            The exact gain grows without bound as a target nears its projected leader: rollouts
            of the chain inertial step, whose targets come within a few per cent of a segment
            of it, had gradients that jumped by 100x from step to step
            (docs/network_diagnosis.md, "Fifteenth session").

    Returns:
        (..., M, N, 3) projected positions [m], differentiable w.r.t. `target`.

    Raises:
        ValueError: on a wrong shape, dtype or device, fewer than 3 vertices, NaN or Inf.
    """
    if check:
        check_tensor("rigid", rigid, shape=["...", None, 3])
        check_tensor("target", target, dtypes=(rigid.dtype,), device=rigid.device)
        if target.shape != rigid.shape:
            raise ValueError(f"target: expected shape {tuple(rigid.shape)} like rigid, got {tuple(target.shape)}")
        if rigid.dim() < 3 or rigid.shape[-2] <= NUM_FIXED_VERTICES:
            raise ValueError(f"rigid: expected (..., M, N, 3) with N > {NUM_FIXED_VERTICES}, got {tuple(rigid.shape)}")
    if max_gain is not None and not max_gain > 0:
        raise ValueError(f"max_gain: expected None or a positive number, got {max_gain}")
    return _FollowTheLeader.apply(rigid.detach(), target, tiled, None if max_gain is None else float(max_gain))


__all__ = ["FOLLOW_THE_LEADER_EPS", "follow_the_leader"]
