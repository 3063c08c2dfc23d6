"""Correction-walk module: a shared per-point MLP predicting the offsets that rectify VCPs."""
from __future__ import annotations

import torch
from torch import nn


class CorrectionWalk(nn.Module):
    """Seeds (B, in_channels, N) -> offsets (B, 3, N).

    1x1 convs with the widths of ``channels``; BatchNorm + ReLU after every layer but the last,
    which is a plain linear layer with bias so an offset can take any sign. ``zero_init`` starts
    that layer at zero: every offset is 0 until training moves it.
    """

    def __init__(self, in_channels: int, channels: tuple[int, ...], zero_init: bool = True) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_channels
        for out in channels[:-1]:
            layers += [nn.Conv1d(width, out, 1, bias=False), nn.BatchNorm1d(out), nn.ReLU()]
            width = out
        last = nn.Conv1d(width, channels[-1], 1, bias=True)
        if zero_init:
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        layers.append(last)
        self.net = nn.Sequential(*layers)

    def forward(self, seeds: torch.Tensor) -> torch.Tensor:
        return self.net(seeds)
