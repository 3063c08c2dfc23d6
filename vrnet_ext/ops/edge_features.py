"""DGCNN edge tensor: ``feats = edge_features(x, idx)`` with channels ``[x_j - x_i, x_i]``."""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_float, check_index, check_index_range, check_same, check_shape,
                                   float32_region, promote_low_precision, trusted_values, values_checked)


def validate_graph(values: torch.Tensor, idx: torch.Tensor, values_name: str) -> None:
    """Checks a (B, C, M) value tensor and a (B, N, k) neighbour index into its M points."""
    check_float(values, values_name)
    check_index(idx, "idx")
    check_shape(values, values_name, 3, "(B, C, N)")
    check_shape(idx, "idx", 3, "(B, N, k)")
    check_same({values_name: values, "idx": idx})
    if idx.shape[0] != values.shape[0]:
        raise ValueError(f"idx batch ({idx.shape[0]}) must match {values_name} batch ({values.shape[0]})")
    if idx.shape[2] < 1:
        raise ValueError("idx must have k >= 1 neighbours")
    if values.shape[2] == 0 or idx.shape[1] == 0:
        raise ValueError(f"empty cloud: {values_name} has {values.shape[2]} points and idx {idx.shape[1]} rows")


def gather_neighbours(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """(B, C, M), (B, N, k) -> (B, C, N, k) with out[b, c, n, j] = values[b, c, idx[b, n, j]].

    The references' gather; it checks the index range itself (the compiled kernels do so in C++).
    """
    check_index_range(idx, values.shape[2], "idx")
    B, C, _ = values.shape
    N, k = idx.shape[1:]
    flat = idx.reshape(B, 1, N * k).expand(B, C, N * k)
    return values.gather(2, flat).reshape(B, C, N, k)


def edge_features_reference(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Pure-PyTorch edge tensor (gather + concat)."""
    neighbours = gather_neighbours(x, idx)
    centre = x.unsqueeze(-1).expand_as(neighbours)
    return torch.cat([neighbours - centre, centre], dim=1)


def edge_features(x: torch.Tensor, idx: torch.Tensor, backend: str = "ext") -> torch.Tensor:
    """Edge features of a kNN graph.

    Args:
        x: (B, C, N) point features (bfloat16/float16 are promoted to float32).
        idx: (B, N, k) int64 neighbour indices into the N points (e.g. from :func:`knn`).
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        (B, 2C, N, k): ``[x[idx] - x_i, x_i]`` along channels.
    """
    x = promote_low_precision(x)
    validate_graph(x, idx, "x")
    if idx.shape[1] != x.shape[2]:
        raise ValueError(f"idx must have shape (B, N, k) with N = {x.shape[2]}, got {tuple(idx.shape)}")
    if use_extension(backend, x.device):
        return torch.ops.vrnet_ext.edge_features(x, idx)
    with float32_region(x):
        return edge_features_reference(x, idx)


if has_extension():

    @torch.library.register_fake("vrnet_ext::edge_features")
    def _edge_features_fake(x, idx):
        return x.new_empty((x.shape[0], 2 * x.shape[1], x.shape[2], idx.shape[2]))

    @torch.library.register_fake("vrnet_ext::edge_features_backward")
    def _edge_features_backward_fake(grad_out, idx, num_points):
        return grad_out.new_empty((grad_out.shape[0], grad_out.shape[1] // 2, num_points))

    def _edge_features_setup_context(ctx, inputs, output):
        x, idx = inputs
        ctx.save_for_backward(idx)
        ctx.num_points = x.shape[2]
        ctx.trusted = not values_checked()  # indices checked (or trusted) by the forward

    def _edge_features_backward(ctx, grad_out):
        (idx,) = ctx.saved_tensors
        with trusted_values(ctx.trusted):
            return torch.ops.vrnet_ext.edge_features_backward(grad_out, idx, ctx.num_points), None

    torch.library.register_autograd(
        "vrnet_ext::edge_features", _edge_features_backward, setup_context=_edge_features_setup_context
    )

    # The backward is linear in grad_out: its own derivative is the forward (second-order gradients).
    def _edge_features_backward_setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[1])

    def _edge_features_double_backward(ctx, grad_grad_x):
        (idx,) = ctx.saved_tensors
        return torch.ops.vrnet_ext.edge_features(grad_grad_x.contiguous(), idx), None, None

    torch.library.register_autograd("vrnet_ext::edge_features_backward", _edge_features_double_backward,
                                    setup_context=_edge_features_backward_setup_context)
