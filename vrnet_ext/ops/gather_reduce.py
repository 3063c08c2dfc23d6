"""Fused neighbour gather + reduction: ``out = gather_reduce(values, idx, reduce="max")``.

It makes DGCNN's EdgeConv cheap: with W = [W1 W2],
``max_k W [x_j - x_i; x_i] = max_k (W1 x)_j + ((W2 - W1) x)_i``, so a layer projects every point
once and gathers the maximum without building the (B, O, N, k) tensor.
"""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import float32_region, promote_low_precision, trusted_values, values_checked
from vrnet_ext.ops.edge_features import gather_neighbours, validate_graph

REDUCTIONS = ("max", "min", "sum", "mean")


def gather_reduce_reference(values: torch.Tensor, idx: torch.Tensor, reduce: str = "max") -> torch.Tensor:
    """Pure-PyTorch gather of (B, C, N, k) neighbours, then a reduction over k."""
    gathered = gather_neighbours(values, idx)
    if reduce == "max":
        return gathered.max(dim=-1).values
    if reduce == "min":
        return gathered.min(dim=-1).values
    if reduce == "sum":
        return gathered.sum(dim=-1)
    return gathered.mean(dim=-1)


def gather_reduce(values: torch.Tensor, idx: torch.Tensor, reduce: str = "max", backend: str = "ext") -> torch.Tensor:
    """Reduce each point's neighbour values.

    Args:
        values: (B, C, M) per-point values (bfloat16/float16 are promoted to float32).
        idx: (B, N, k) int64 indices into the M points.
        reduce: ``"max"``, ``"min"``, ``"sum"`` or ``"mean"``.
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        (B, C, N) with ``out[b, c, n] = reduce_j values[b, c, idx[b, n, j]]``. The max/min backward
        routes the gradient to the winning neighbour (the first one on ties).
    """
    if reduce not in REDUCTIONS:
        raise ValueError(f"reduce must be one of {REDUCTIONS}, got {reduce!r}")
    values = promote_low_precision(values)
    validate_graph(values, idx, "values")
    if use_extension(backend, values.device):
        return torch.ops.vrnet_ext.gather_reduce(values, idx, reduce)[0]
    with float32_region(values):
        return gather_reduce_reference(values, idx, reduce)


if has_extension():

    @torch.library.register_fake("vrnet_ext::gather_reduce")
    def _gather_reduce_fake(values, idx, reduce):
        B, C, N = values.shape[0], values.shape[1], idx.shape[1]
        arg_batch = B if reduce in ("max", "min") else 0
        return values.new_empty((B, C, N)), values.new_empty((arg_batch, C, N), dtype=torch.int64)

    @torch.library.register_fake("vrnet_ext::gather_reduce_backward")
    def _gather_reduce_backward_fake(grad_out, idx, arg, reduce, num_values):
        return grad_out.new_empty((grad_out.shape[0], grad_out.shape[1], num_values))

    def _gather_reduce_setup_context(ctx, inputs, output):
        values, idx, reduce = inputs
        ctx.save_for_backward(idx, output[1])
        ctx.reduce = reduce
        ctx.num_values = values.shape[2]
        ctx.trusted = not values_checked()  # indices checked (or trusted) by the forward

    def _gather_reduce_backward(ctx, grad_out, _grad_arg):
        idx, arg = ctx.saved_tensors
        with trusted_values(ctx.trusted):
            grad = torch.ops.vrnet_ext.gather_reduce_backward(grad_out, idx, arg, ctx.reduce, ctx.num_values)
        return grad, None, None

    torch.library.register_autograd(
        "vrnet_ext::gather_reduce", _gather_reduce_backward, setup_context=_gather_reduce_setup_context
    )

    # The backward is linear in grad_out: its derivative gathers the values' gradient at each output's
    # neighbours (all of them, or the winning slot for max / min) - second-order gradients.
    def _gather_reduce_backward_setup_context(ctx, inputs, output):
        _grad_out, idx, arg, reduce, _num_values = inputs
        ctx.save_for_backward(idx, arg)
        ctx.reduce = reduce

    def _gather_reduce_double_backward(ctx, grad_grad_values):
        idx, arg = ctx.saved_tensors
        if ctx.reduce in ("max", "min"):
            winners = idx.unsqueeze(1).expand(-1, arg.shape[1], -1, -1).gather(3, arg.unsqueeze(3)).squeeze(3)
            grad = grad_grad_values.gather(2, winners)
        else:
            grad = torch.ops.vrnet_ext.gather_reduce(grad_grad_values.contiguous(), idx, ctx.reduce)[0]
        return grad, None, None, None, None

    torch.library.register_autograd("vrnet_ext::gather_reduce_backward", _gather_reduce_double_backward,
                                    setup_context=_gather_reduce_backward_setup_context)
