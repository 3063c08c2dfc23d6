"""DGCNN feature extractor (paper Eq. 1) on fused EdgeConv layers and ``ops.knn``."""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext.nn import EdgeConv
from vrnet_ext.nn.pointwise import cached_folded_affine, can_fold
from vrnet_ext.ops import knn
from vrnet_ext.ops.knn import on_tensor_cores


def graph_backend(device: torch.device, dtype: torch.dtype, channels: int, k: int, backend: str) -> str:
    """The kNN backend for a graph of k neighbours over features of ``channels`` values on ``device``.

    On a GPU the compiled kNN of C > 3 searches on the tensor cores where :func:`ops.knn.on_tensor_cores`
    says so; elsewhere on a GPU it trails ``cdist`` + ``topk`` (H200, B = 28, N = 1024, C = 64: 8.9
    against 2.9 ms), and since a graph of learned features needs only the indices, not exact distances
    at any offset from the origin, the reference builds it there. Elsewhere, and for the points
    themselves, ``backend``."""
    if device.type == "cuda" and channels > 3 and not on_tensor_cores(device, dtype, channels, k):
        return "torch"
    return backend


class DGCNN(nn.Module):
    """Dynamic-graph CNN: (B, N, 3) points -> (B, emb_dims, N) features.

    Each EdgeConv layer rebuilds the kNN graph (k neighbours, the point itself included as in
    DGCNN) in the feature space of its input; the layer outputs are concatenated and projected
    to ``emb_dims`` by a 1x1 conv + BatchNorm + LeakyReLU.
    """

    def __init__(self, channels: tuple[int, ...], emb_dims: int, k: int, negative_slope: float) -> None:
        super().__init__()
        self.k = k
        self.negative_slope = negative_slope
        widths = (3,) + tuple(channels)
        self.layers = nn.ModuleList(
            EdgeConv(c_in, c_out, negative_slope=negative_slope) for c_in, c_out in zip(widths[:-1], widths[1:])
        )
        self.projection = nn.Conv1d(sum(channels), emb_dims, kernel_size=1, bias=False)
        self.projection_bn = nn.BatchNorm1d(emb_dims)

    def forward(self, points: torch.Tensor, backend: str = "ext") -> torch.Tensor:
        """points (B, N, 3) -> features (B, emb_dims, N)."""
        if points.shape[1] < self.k:
            raise ValueError(f"DGCNN needs at least k={self.k} points per cloud, got {points.shape[1]}")
        x = points.transpose(1, 2)
        outputs = []
        for layer in self.layers:
            features = x.transpose(1, 2).detach()
            graph = graph_backend(features.device, features.dtype, features.shape[-1], self.k, backend)
            idx = knn(features, features, self.k, backend=graph)[1]
            x = layer(x, idx, backend=backend)
            outputs.append(x)
        if can_fold(self.projection_bn):  # eval: conv + BatchNorm as one product on the points' rows
            # The layers' outputs are point-major in memory: joined along channels as (B, N, sum C)
            # rows, they feed the product without a transposing copy.
            rows = torch.cat([output.transpose(1, 2) for output in outputs], dim=-1)
            rows = F.linear(rows, *cached_folded_affine(self, "folded projection", self.projection, self.projection_bn))
            return F.leaky_relu(rows, self.negative_slope).transpose(1, 2)
        z = self.projection_bn(self.projection(torch.cat(outputs, dim=1)))
        return F.leaky_relu(z, self.negative_slope)
