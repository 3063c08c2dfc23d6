"""Correction-walk module: a shared per-point MLP predicting the offsets that rectify VCPs."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vrnet_ext.nn import PointwiseMLP


@dataclass
class WalkOutput:
    """Per-point outputs of the walk for N source points.

    ``offset`` (B, N, 3) is what is added to the VCPs (already gated); ``gate_logits`` (B, N) or None:
    the logit of "this VCP needs a correction", the gate being its sigmoid; ``confidence_logits``
    (B, N) or None: the logit of "this RCP lies near the true correspondent", whose sigmoid weights
    the Procrustes solve.
    """

    offset: torch.Tensor
    gate_logits: torch.Tensor | None
    confidence_logits: torch.Tensor | None


GATE_CLOSED = -4.0  # initial gate logit: sigmoid(-4) = 0.018


class CorrectionWalk(nn.Module):
    """Seeds (B, in_channels, N) -> :class:`WalkOutput`.

    1x1 convs with the widths of ``channels`` (ending in 3, the xyz offset); BatchNorm + ReLU after
    every layer but the last, which is a plain linear layer with bias so an offset can take any
    sign. ``gate`` and ``confidence`` each add one output channel to that layer (``confidence_trunk``:
    the confidence comes from a second MLP of the same widths instead). ``zero_init``
    starts the last layer at zero: every offset is 0 (RCP = VCP) and every confidence 0.5 until
    training moves them, and the gate starts nearly closed (bias ``GATE_CLOSED``, sigmoid 0.018), so
    that the walk opens it only where moving a VCP pays.

    Why the gate: an MLP cannot output an exact zero, but the VCPs of well-matched points are
    already nearly exact (median error ~2e-4 of the shape's radius on ModelNet40 partial views), so
    an ungated walk adds noise to exactly the points the rotation depends on. With
    ``offset = sigmoid(gate) * raw_offset`` a saturated gate leaves them untouched.
    """

    def __init__(self, in_channels: int, channels: tuple[int, ...], zero_init: bool = True, gate: bool = False,
                 confidence: bool = False, confidence_trunk: bool = False) -> None:
        super().__init__()
        if confidence_trunk and not confidence:
            raise ValueError("confidence_trunk needs confidence=True")
        self.gate = gate
        self.confidence = confidence
        shared_confidence = confidence and not confidence_trunk
        self.net = _mlp(in_channels, channels, channels[-1] + int(gate) + int(shared_confidence), zero_init,
                        GATE_CLOSED if gate else None, channels[-1])
        # ``walk_confidence_trunk``: the confidence's own MLP, so L4 on the offsets does not shape it
        self.confidence_net = _mlp(in_channels, channels, 1, zero_init) if confidence_trunk else None

    def forward(self, seeds: torch.Tensor) -> WalkOutput:
        out = self.net(seeds).transpose(1, 2)  # (B, N, 3 [+ gate] [+ confidence])
        offset, extra = out[..., :3], out[..., 3:]
        gate_logits = confidence_logits = None
        if self.gate:
            gate_logits, extra = extra[..., 0], extra[..., 1:]
            offset = torch.sigmoid(gate_logits).unsqueeze(-1) * offset
        if self.confidence_net is not None:
            confidence_logits = self.confidence_net(seeds)[:, 0]
        elif self.confidence:
            confidence_logits = extra[..., 0]
        return WalkOutput(offset, gate_logits, confidence_logits)


def _mlp(in_channels: int, channels: tuple[int, ...], outputs: int, zero_init: bool, gate_bias: float | None = None,
         gate_channel: int = 0) -> PointwiseMLP:
    """1x1 convs of the widths ``channels[:-1]`` (BatchNorm + ReLU), then a linear layer with
    ``outputs`` channels; ``zero_init`` zeroes that layer, and ``gate_bias`` then sets the bias of
    its channel ``gate_channel``."""
    layers: list[nn.Module] = []
    width = in_channels
    for out in channels[:-1]:
        layers += [nn.Conv1d(width, out, 1, bias=False), nn.BatchNorm1d(out), nn.ReLU()]
        width = out
    last = nn.Conv1d(width, outputs, 1, bias=True)
    if zero_init:
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        if gate_bias is not None:
            nn.init.constant_(last.bias[gate_channel:gate_channel + 1], gate_bias)
    layers.append(last)
    return PointwiseMLP(*layers)
