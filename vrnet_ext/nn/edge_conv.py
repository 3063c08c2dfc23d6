"""EdgeConv without the (B, O, N, k) edge tensor.

The layer is ``Conv2d(2C, O, 1, bias=False) -> BatchNorm2d(O) -> LeakyReLU -> max over k`` applied
to ``edge_features(x, idx)``. With W = [W1 W2], the pre-activation of edge (n, j) is
``a[idx[n, j]] + b[n]`` where ``a = W1 x`` and ``b = (W2 - W1) x``. Hence

* BatchNorm's batch statistics follow in closed form from per-point sums: with ``deg[m]`` the
  in-degree of point m, ``sum z = sum_n (sum_j a[idx[n,j]] + k b[n])`` and
  ``sum z^2 = sum_m deg[m] a[m]^2 + 2 sum_n b[n] sum_j a[idx[n,j]] + k sum_n b[n]^2``;
* BatchNorm + LeakyReLU is monotone per channel, so the max over k commutes with it: take the
  max of ``a`` over the neighbours where the BN scale is >= 0 and the min where it is negative.

Only (B, O, N) tensors are stored, and the parameters keep ``Conv2d``/``BatchNorm2d`` layouts, so
``backend="torch"`` runs the materialising layer on the very same weights and buffers.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext.ops import edge_features, gather_reduce


class EdgeConv(nn.Module):
    """DGCNN edge convolution: (B, C, N) features + (B, N, k) graph -> (B, O, N)."""

    def __init__(self, in_channels: int, out_channels: int, negative_slope: float = 0.2,
                 eps: float = 1e-5, momentum: float | None = 0.1) -> None:
        super().__init__()
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

    def _batch_statistics(self, a: torch.Tensor, b: torch.Tensor, idx: torch.Tensor):
        """Per-channel mean and biased variance of z[n, j] = a[idx[n, j]] + b[n] over (B, N, k)."""
        B, N, k = idx.shape
        count = B * N * k
        # Shifting by detached constants leaves the variance (and its gradient) unchanged
        # while avoiding cancellation in E[z^2] - E[z]^2.
        a_shift = a.detach().mean(dim=(0, 2), keepdim=True)
        b_shift = b.detach().mean(dim=(0, 2), keepdim=True)
        a_c, b_c = a - a_shift, b - b_shift
        degree = torch.zeros(B, 1, a.shape[2], dtype=a.dtype, device=a.device)
        degree.scatter_add_(2, idx.reshape(B, 1, N * k), torch.ones(B, 1, N * k, dtype=a.dtype, device=a.device))
        neighbour_sum = gather_reduce(a_c, idx, "sum")
        total = neighbour_sum.sum(dim=(0, 2)) + k * b_c.sum(dim=(0, 2))
        total_sq = ((degree * a_c.square()).sum(dim=(0, 2)) + 2 * (b_c * neighbour_sum).sum(dim=(0, 2))
                    + k * b_c.square().sum(dim=(0, 2)))
        mean_c = total / count
        var = (total_sq / count - mean_c.square()).clamp_min(0)
        return mean_c + (a_shift + b_shift).flatten(), var, count

    def _fused(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        weight = self.conv.weight.flatten(1)
        w_neighbour, w_centre = weight[:, : self.in_channels], weight[:, self.in_channels:]
        a = torch.matmul(w_neighbour, x)
        b = torch.matmul(w_centre - w_neighbour, x)
        bn = self.bn
        if bn.training or bn.running_mean is None:
            mean, var, count = self._batch_statistics(a, b, idx)
            if count <= 1 and bn.training:
                raise ValueError("EdgeConv in training mode needs more than one edge per channel")
            if bn.training and bn.track_running_stats:
                self._update_running_stats(mean.detach(), var.detach(), count)
        else:
            mean, var = bn.running_mean, bn.running_var
        scale = torch.rsqrt(var + bn.eps)
        if bn.affine:
            scale = scale * bn.weight
        shift = -mean * scale
        if bn.affine:
            shift = shift + bn.bias
        # max_k commutes with a monotone map: increasing where scale >= 0, decreasing otherwise.
        direction = torch.where(scale >= 0, 1.0, -1.0).to(a.dtype).detach().view(1, -1, 1)
        extreme = direction * gather_reduce(a * direction, idx, "max")
        z = scale.view(1, -1, 1) * (extreme + b) + shift.view(1, -1, 1)
        return F.leaky_relu(z, self.negative_slope)

    @torch.no_grad()
    def _update_running_stats(self, mean: torch.Tensor, var: torch.Tensor, count: int) -> None:
        bn = self.bn
        bn.num_batches_tracked.add_(1)
        momentum = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked)
        bn.running_mean.lerp_(mean, momentum)
        bn.running_var.lerp_(var * count / (count - 1), momentum)
