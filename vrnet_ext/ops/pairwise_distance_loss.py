"""VRNet's geometry-structure loss L2: ``loss = pairwise_distance_loss(x, y)``.

``loss_b = sqrt(mean_{i,j} (|x_i - x_j| - |y_i - y_j|)^2)`` over all N^2 ordered pairs. The
compiled kernel walks the pairs row by row with exact coordinate differences (no
|a|^2 - 2ab + |b|^2 expansion) and double accumulation, in O(B N) memory; its backward is
zero where a pair coincides or the loss is exactly 0 (instead of NaN).
"""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_same, check_shape, first_order_only,
                                   float32_region, promote_low_precision)


def pairwise_distance_loss_reference(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Pure-PyTorch loss over the full (B, N, N) distance matrices."""
    check_finite(x, "x")
    check_finite(y, "y")
    dx = (x.unsqueeze(2) - x.unsqueeze(1)).norm(dim=-1)
    dy = (y.unsqueeze(2) - y.unsqueeze(1)).norm(dim=-1)
    return (dx - dy).square().mean(dim=(1, 2)).sqrt()


def pairwise_distance_loss(x: torch.Tensor, y: torch.Tensor, backend: str = "ext") -> torch.Tensor:
    """RMSE between the pairwise-distance matrices of two corresponding clouds.

    Args:
        x: (B, N, 3) points, N >= 2 (bfloat16/float16 are promoted to float32).
        y: (B, N, 3) corresponding points.
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        (B,) loss per batch element.

    Precision (fuzz suite): equal to a float64 evaluation to ~1e3 ulps of the clouds' spread.
    """
    x, y = promote_low_precision(x), promote_low_precision(y)
    check_float(x, "x")
    check_float(y, "y")
    check_shape(x, "x", 3, "(B, N, 3)", last=3)
    if y.shape != x.shape:
        raise ValueError(f"y must have the shape of x {tuple(x.shape)}, got {tuple(y.shape)}")
    check_same({"x": x, "y": y})
    if x.shape[1] < 2:
        raise ValueError(f"x needs at least 2 points per cloud, got {x.shape[1]}")
    if use_extension(backend, x.device):
        return torch.ops.vrnet_ext.pairwise_distance_loss(x, y)
    with float32_region(x):
        return pairwise_distance_loss_reference(x, y)


if has_extension():

    @torch.library.register_fake("vrnet_ext::pairwise_distance_loss")
    def _pairwise_distance_loss_fake(x, y):
        return x.new_empty((x.shape[0],))

    @torch.library.register_fake("vrnet_ext::pairwise_distance_loss_backward")
    def _pairwise_distance_loss_backward_fake(grad_loss, x, y, loss):
        return torch.empty_like(x), torch.empty_like(y)

    def _pdl_setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[0], inputs[1], output)

    def _pdl_backward(ctx, grad_loss):
        x, y, loss = ctx.saved_tensors
        first_order_only("pairwise_distance_loss", grad_loss, x, y)
        return torch.ops.vrnet_ext.pairwise_distance_loss_backward(grad_loss, x, y, loss)

    torch.library.register_autograd(
        "vrnet_ext::pairwise_distance_loss", _pdl_backward, setup_context=_pdl_setup_context
    )
