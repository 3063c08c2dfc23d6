"""Per-point 1x1 convolutions with their BatchNorm folded into the product at inference.

A ``Conv1d(C, O, 1)`` followed by a ``BatchNorm1d(O)`` that uses its running statistics is one
affine map of every point's features: ``W' = diag(s) W`` and ``b' = s (b - mean) + beta`` with
``s = gamma / sqrt(var + eps)``. Applied point-major ((B, N, C) rows times W'^T, one matrix product)
it replaces the convolution, the normalisation and their intermediate tensor. The folded weights
are kept for inference while the parameters and statistics are unchanged
(:mod:`vrnet_ext.nn.inference_cache`), so they always follow them.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext.nn.inference_cache import inference_cached


def folded_affine(conv: nn.Conv1d, bn: nn.BatchNorm1d | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Weight (O, C) and bias (O,) or None of ``bn(conv(x))`` for a 1x1 ``conv`` and an eval-mode
    ``bn`` with running statistics (or no ``bn``)."""
    weight, bias = conv.weight[:, :, 0], conv.bias
    if bn is None:
        return weight, bias
    scale = torch.rsqrt(bn.running_var + bn.eps)
    if bn.weight is not None:
        scale = scale * bn.weight
    shift = -bn.running_mean if bias is None else bias - bn.running_mean
    folded_bias = scale * shift + (bn.bias if bn.bias is not None else 0)
    return weight * scale[:, None], folded_bias


def cached_folded_affine(owner: nn.Module, name: str, conv: nn.Conv1d,
                         bn: nn.BatchNorm1d | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`folded_affine`, kept on ``owner`` under ``name`` for inference while the parameters
    and statistics are unchanged (:func:`vrnet_ext.nn.inference_cache.inference_cached`)."""
    sources = (conv.weight, conv.bias) + ((bn.weight, bn.bias, bn.running_mean, bn.running_var) if bn else ())
    return inference_cached(owner, name, sources, lambda: folded_affine(conv, bn))


def can_fold(bn: nn.BatchNorm1d) -> bool:
    """Whether ``bn`` normalises with running statistics in its current mode."""
    return not bn.training and bn.running_mean is not None and bn.running_var is not None


class PointwiseMLP(nn.Sequential):
    """``Conv1d(1x1) [-> BatchNorm1d] [-> ReLU]`` ... on (B, C, N) features -> (B, O, N).

    In training mode (or with BatchNorm on batch statistics) the layers run as an ``nn.Sequential``;
    in eval mode each convolution and its BatchNorm run as one folded matrix product on the points'
    rows, the same function up to float rounding. The parameters keep the ``Sequential`` layout
    (``0.weight``, ``1.running_mean``, ...), so checkpoints load either way. The eval-mode result is
    a transposed view of a point-major (B, N, O) tensor.
    """

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        layers = list(self)
        if any(isinstance(m, nn.BatchNorm1d) and not can_fold(m) for m in layers):
            return super().forward(features)
        rows = features.transpose(1, 2)  # (B, N, C)
        i = 0
        while i < len(layers):
            conv = layers[i]
            if not isinstance(conv, nn.Conv1d) or conv.kernel_size != (1,) or conv.groups != 1:
                raise TypeError(f"PointwiseMLP expects 1x1 Conv1d layers, found {conv}")
            bn = layers[i + 1] if i + 1 < len(layers) and isinstance(layers[i + 1], nn.BatchNorm1d) else None
            rows = F.linear(rows, *cached_folded_affine(self, f"folded {i}", conv, bn))
            i += 2 if bn is not None else 1
            if i < len(layers) and isinstance(layers[i], nn.ReLU):
                rows = rows.relu_()
                i += 1
        return rows.transpose(1, 2)
