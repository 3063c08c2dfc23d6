"""EdgeConv without the (B, O, N, k) edge tensor.

The layer is ``Conv2d(2C, O, 1, bias=False) -> BatchNorm2d(O) -> LeakyReLU -> max over k`` applied
to ``edge_features(x, idx)``. With W = [W1 W2], the pre-activation of edge (n, j) is
``a[idx[n, j]] + b[n]`` where ``a = W1 x`` and ``b = (W2 - W1) x``: the layer projects every point
once (one matrix product for both terms) and :func:`vrnet_ext.ops.edge_norm_max` does the rest
(batch statistics from per-point sums, the max over k taken before the monotone BN + LeakyReLU).

Only (B, O, N) tensors are stored, and the parameters keep ``Conv2d``/``BatchNorm2d`` layouts, so
``backend="torch"`` runs the materialising layer on the very same weights and buffers.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext.nn.inference_cache import inference_cached
from vrnet_ext.ops import edge_features, edge_norm_max


class EdgeConv(nn.Module):
    """DGCNN edge convolution: (B, C, N) features + (B, N, k) graph -> (B, O, N)."""

    def __init__(self, in_channels: int, out_channels: int, negative_slope: float = 0.2,
                 eps: float = 1e-5, momentum: float | None = 0.1) -> None:
        super().__init__()
        if not 0 <= negative_slope < float("inf"):
            raise ValueError(f"negative_slope must be a finite number >= 0 (EdgeConv takes the max over neighbours "
                             f"before the LeakyReLU), got {negative_slope}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.negative_slope = negative_slope
        self.conv = nn.Conv2d(2 * in_channels, out_channels, kernel_size=1, bias=False)
        self.bn = nn.BatchNorm2d(out_channels, eps=eps, momentum=momentum)

    def forward(self, x: torch.Tensor, idx: torch.Tensor, backend: str = "ext") -> torch.Tensor:
        """x (B, C, N), idx (B, N, k) int64 -> (B, O, N). ``backend="torch"`` materialises edges."""
        if x.dim() != 3 or x.shape[1] != self.in_channels:
            raise ValueError(f"x must have shape (B, {self.in_channels}, N), got {tuple(x.shape)}")
        if backend == "torch":
            edges = edge_features(x, idx, backend="torch")
            z = F.leaky_relu(self.bn(self.conv(edges)), self.negative_slope)
            return z.max(dim=-1).values
        return self._fused(x, idx)

    def _projection_weight(self) -> torch.Tensor:
        """(C, 2O) [W1 | W2 - W1]^T: one product gives both terms of every point."""
        weight = self.conv.weight.flatten(1)
        w_neighbour, w_centre = weight[:, : self.in_channels], weight[:, self.in_channels:]
        return torch.cat([w_neighbour, w_centre - w_neighbour]).mT

    def _fused(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        weight = inference_cached(self, "projection weight", (self.conv.weight,), self._projection_weight)
        # (B, N, 2O) in memory, the layout the compiled kernel gathers from; seen as (B, 2O, N)
        projections = torch.matmul(x.mT, weight).mT
        bn = self.bn
        batch_stats = bn.training or bn.running_mean is None
        out, mean, var = edge_norm_max(projections, idx, bn.weight, bn.bias,
                                       None if batch_stats else bn.running_mean,
                                       None if batch_stats else bn.running_var, bn.eps, self.negative_slope)
        if bn.training and bn.track_running_stats:
            self._update_running_stats(mean, var, idx.numel())
        return out

    @torch.no_grad()
    def _update_running_stats(self, mean: torch.Tensor, var: torch.Tensor, count: int) -> None:
        bn = self.bn
        bn.num_batches_tracked.add_(1)
        momentum = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked)
        bn.running_mean.lerp_(mean.to(bn.running_mean.dtype), momentum)
        bn.running_var.lerp_((var * count / (count - 1)).to(bn.running_var.dtype), momentum)
