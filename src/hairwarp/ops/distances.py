"""Torch bridges of the primitive distances (segment-segment, point-triangle); device code in
`hairwarp.kernels.distances`.

The distance and its gradient come from one kernel pass; the backward only scales the saved
gradient (envelope theorem, see the kernel module). At d = 0 the gradient is a subgradient
along the primitives' common normal, never NaN.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from hairwarp import _warp
from hairwarp._validate import check_same_dtype, check_tensor
from hairwarp.kernels import distances as distance_kernels


def _check_points(**points: torch.Tensor) -> tuple[int, torch.device, torch.dtype]:
    """All arguments (K, 3) float tensors with one K, one dtype, one device, finite."""
    items = list(points.items())
    first_name, first = items[0]
    check_tensor(first_name, first, shape=(None, 3))
    for name, t in items[1:]:
        check_tensor(name, t, shape=(None, 3), device=first.device)
        if t.shape[0] != first.shape[0]:
            raise ValueError(
                f"{name}: expected {first.shape[0]} rows like {first_name}, got shape {tuple(t.shape)}"
            )
    check_same_dtype(**points)
    return first.shape[0], first.device, first.dtype


def _launch_pairwise(kernel, inputs: list[torch.Tensor], n_params: int):
    """Run a 4-primitive distance kernel; returns distance (K,), params (K, n), gradient (K, 4, 3)."""
    ref = inputs[0]
    k = ref.shape[0]
    distance = torch.empty(k, dtype=ref.dtype, device=ref.device)
    params = torch.empty(k, n_params, dtype=ref.dtype, device=ref.device)
    gradient = torch.empty(k, 4, 3, dtype=ref.dtype, device=ref.device)
    if k > 0:
        with _warp.launch_scope(ref.device):
            _warp.launch(
                kernel,
                dim=k,
                inputs=[_warp.as_warp(t.contiguous(), vec3=True) for t in inputs],
                outputs=[_warp.as_warp(distance), _warp.as_warp(params), _warp.as_warp(gradient, vec3=True)],
                device=_warp.warp_device(ref.device),
            )
    return distance, params, gradient


class _EdgeEdgeDistance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, p0, p1, q0, q1):
        kernel = distance_kernels.edge_edge_distance_kernel
        distance, _, gradient = _launch_pairwise(kernel, [p0, p1, q0, q1], 2)
        ctx.save_for_backward(gradient)
        return distance

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_distance):
        (gradient,) = ctx.saved_tensors
        g = grad_distance[:, None, None] * gradient
        return g[:, 0], g[:, 1], g[:, 2], g[:, 3]


class _PointTriangleDistance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, p, a, b, c):
        kernel = distance_kernels.point_triangle_distance_kernel
        distance, _, gradient = _launch_pairwise(kernel, [p, a, b, c], 3)
        ctx.save_for_backward(gradient)
        return distance

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_distance):
        (gradient,) = ctx.saved_tensors
        g = grad_distance[:, None, None] * gradient
        return g[:, 0], g[:, 1], g[:, 2], g[:, 3]


def edge_edge_distance(
    p0: torch.Tensor, p1: torch.Tensor, q0: torch.Tensor, q1: torch.Tensor
) -> torch.Tensor:
    """Distance between segments p0[k]-p1[k] and q0[k]-q1[k], differentiable w.r.t. all four.

    This is the d of HairFormer Eq. 12 for hair-hair contact. Robust for parallel, crossing,
    touching and zero-length segments: the result is finite and the gradient is never NaN
    (at d = 0 it is the subgradient along the unit normal of the two segment directions).

    Args:
        p0: (K, 3) first endpoints of the first segments [m], float32 or float64.
        p1: (K, 3) second endpoints of the first segments [m].
        q0: (K, 3) first endpoints of the second segments [m].
        q1: (K, 3) second endpoints of the second segments [m].

    Returns:
        (K,) distances [m], dtype and device of the inputs.

    Raises:
        ValueError: naming the argument, for a wrong shape, dtype or device, or NaN/Inf.
    """
    _check_points(p0=p0, p1=p1, q0=q0, q1=q1)
    return _EdgeEdgeDistance.apply(p0, p1, q0, q1)


def edge_edge_parameters(
    p0: torch.Tensor, p1: torch.Tensor, q0: torch.Tensor, q1: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest-point parameters of `edge_edge_distance` (not differentiable).

    Args:
        p0, p1, q0, q1: (K, 3) segment endpoints [m] as in `edge_edge_distance`.

    Returns:
        (s, t): (K,) each, in [0, 1]; the closest points are p0 + s (p1 - p0), q0 + t (q1 - q0).
    """
    _check_points(p0=p0, p1=p1, q0=q0, q1=q1)
    _, params, _ = _launch_pairwise(
        distance_kernels.edge_edge_distance_kernel, [t.detach() for t in (p0, p1, q0, q1)], 2
    )
    return params[:, 0], params[:, 1]


def point_triangle_distance(
    p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> torch.Tensor:
    """Unsigned distance from p[k] to triangle a[k] b[k] c[k], differentiable w.r.t. all four.

    Degenerate (zero-area) triangles are measured as their edges. At d = 0 the gradient is the
    subgradient along the triangle's unit normal (zero if the triangle is degenerate too).

    Args:
        p: (K, 3) query points [m], float32 or float64.
        a: (K, 3) first triangle vertices [m].
        b: (K, 3) second triangle vertices [m].
        c: (K, 3) third triangle vertices [m].

    Returns:
        (K,) distances [m], dtype and device of the inputs.

    Raises:
        ValueError: naming the argument, for a wrong shape, dtype or device, or NaN/Inf.
    """
    _check_points(p=p, a=a, b=b, c=c)
    return _PointTriangleDistance.apply(p, a, b, c)


def point_triangle_barycentric(
    p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> torch.Tensor:
    """Barycentric coordinates (K, 3) of the closest point of `point_triangle_distance`.

    Args:
        p, a, b, c: (K, 3) as in `point_triangle_distance` [m].

    Returns:
        (K, 3) (u, v, w), non-negative, summing to 1: closest point u a + v b + w c.
    """
    _check_points(p=p, a=a, b=b, c=c)
    _, params, _ = _launch_pairwise(
        distance_kernels.point_triangle_distance_kernel, [t.detach() for t in (p, a, b, c)], 3
    )
    return params
