"""Torch bridge of the contact barrier B(d) (HairFormer Eq. 12-14); device code in
`hairwarp.kernels.barrier`.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from hairwarp import _warp
from hairwarp._validate import check_positive, check_tensor, finite_checks_enabled
from hairwarp.config import BARRIER_VARIANTS
from hairwarp.kernels import barrier as barrier_kernels

# Name -> the integer `variant` of the kernels (BARRIER_PAPER, BARRIER_MONOTONE, BARRIER_QUADRATIC).
_VARIANT_IDS = {name: i for i, name in enumerate(BARRIER_VARIANTS)}


def barrier_variant_id(variant: str) -> int:
    """Integer id of a barrier variant name, as the kernels take it."""
    if variant not in _VARIANT_IDS:
        raise ValueError(f"variant: expected one of {list(BARRIER_VARIANTS)}, got {variant!r}")
    return _VARIANT_IDS[variant]


def check_barrier_parameters(xi: float, dhat: float, bp) -> tuple[float, float, float | torch.Tensor]:
    """Validate (xi, dhat, bp): xi > 0 [m], dhat > 0 [m], 0 < bp < 1.

    `bp` may be a one-element floating tensor (a device scalar the contact kernels read at
    launch, `join_fraction_tensor`): returned as it is; its value is read back and checked only
    while input checks are on (`hairwarp._validate.set_finite_checks`: a captured graph turns
    them off).
    """
    xi = check_positive("xi", xi)
    dhat = check_positive("dhat", dhat)
    if isinstance(bp, torch.Tensor):
        if bp.numel() != 1 or not bp.is_floating_point():
            raise ValueError(f"bp: expected a float or a one-element floating tensor, got shape "
                             f"{tuple(bp.shape)} and dtype {bp.dtype}")
        if finite_checks_enabled() and not 0.0 < float(bp) < 1.0:
            raise ValueError(f"bp: expected a join fraction in (0, 1), got {float(bp)}")
        return xi, dhat, bp.detach()
    bp = float(bp)
    if not 0.0 < bp < 1.0:
        raise ValueError(f"bp: expected a join fraction in (0, 1), got {bp}")
    return xi, dhat, bp


def join_fraction_tensor(bp: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """`bp` as the (1,) tensor the contact kernels read at launch, in `like`'s dtype and device:
    a float is written into a new one; a one-element tensor is viewed as it is (or cast), so a
    CUDA graph captured with it follows the value it holds at each replay.
    """
    if isinstance(bp, torch.Tensor):
        return bp.detach().reshape(1).to(device=like.device, dtype=like.dtype).contiguous()
    return torch.full((1,), bp, dtype=like.dtype, device=like.device)


def _launch(kernel, d: torch.Tensor, xi: float, dhat: float, bp: float, variant_id: int, outputs) -> None:
    if d.numel() == 0:
        return
    with _warp.launch_scope(d.device):
        _warp.launch(
            kernel,
            dim=d.numel(),
            inputs=[_warp.as_warp(d), _warp.scalar(xi, d.dtype), _warp.scalar(dhat, d.dtype),
                    _warp.scalar(bp, d.dtype), variant_id],
            outputs=[_warp.as_warp(o) for o in outputs],
            device=_warp.warp_device(d.device),
        )


class _Barrier(torch.autograd.Function):
    """B(d); its backward is itself differentiable (`_BarrierGradient`), so a double backward
    gives the true second derivative instead of a silent zero.
    """

    @staticmethod
    def forward(ctx, d, xi, dhat, bp, variant_id):
        energy = torch.empty_like(d)
        gradient = torch.empty_like(d)
        _launch(barrier_kernels.barrier_kernel, d, xi, dhat, bp, variant_id, (energy, gradient))
        ctx.save_for_backward(d, gradient)
        ctx.parameters = (xi, dhat, bp, variant_id)
        return energy

    @staticmethod
    def backward(ctx, grad_energy):
        d, gradient = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: dB/dd as a differentiable function of d
            gradient = _BarrierGradient.apply(d, gradient, *ctx.parameters)
        return grad_energy * gradient, None, None, None, None


class _BarrierGradient(torch.autograd.Function):
    """dB/dd (already computed in the forward) with d^2B/dd^2 as its derivative."""

    @staticmethod
    def forward(ctx, d, gradient, xi, dhat, bp, variant_id):
        ctx.save_for_backward(d)
        ctx.parameters = (xi, dhat, bp, variant_id)
        return gradient.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_gradient):
        (d,) = ctx.saved_tensors
        hessian = torch.empty_like(d)
        _launch(barrier_kernels.barrier_hessian_kernel, d, *ctx.parameters, (hessian,))
        return grad_gradient * hessian, None, None, None, None, None


def barrier(d: torch.Tensor, xi: float, dhat: float, bp: float, variant: str = "quadratic") -> torch.Tensor:
    """Contact barrier B(d) of Eq. 12, element-wise, differentiable w.r.t. `d`.

    B is the C-IPC log barrier for d >= d_b = xi + bp * dhat, zero for d >= xi + dhat, and a
    polynomial extrapolation below d_b, so penetration (d < 0) has finite energy.

    Args:
        d: distances [m], any shape, float32 or float64 (signed: negative inside the body).
        xi: hard barrier [m] (1 mm for hair-body, the hair diameter for hair-hair).
        dhat: soft barrier width [m] (the paper uses 1.5 * xi).
        bp: join fraction in (0, 1); the paper anneals it from 0.9 to 0.01 during training.
        variant: "quadratic" (default; the Taylor polynomial of B_0 at d_b: C2 there, the
            penalty strictly increasing with depth, the push-out force growing linearly),
            "monotone" (C2, strictly increasing, quartic beyond |t0|: the force grows with
            depth cubed and overwhelms the stretch term for hair centimetres inside) or
            "paper" (Eq. 12-14 literally, whose penalty falls back to zero at
            d = -(xi + dhat): kept for comparison).

    Returns:
        Tensor like `d`: the barrier value (dimensionless; the caller's weight gives units).
    """
    check_tensor("d", d)
    xi, dhat, bp = check_barrier_parameters(xi, dhat, bp)
    variant_id = barrier_variant_id(variant)
    return _Barrier.apply(d.contiguous(), xi, dhat, float(bp), variant_id)
