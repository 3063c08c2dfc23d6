"""Parameters cast once for autocast inference instead of on every forward.

Under ``torch.autocast`` a matrix product casts its float32 weight to the low-precision dtype on
every call; for a model applied pair after pair that is a fresh copy of every weight per forward.
:func:`autocast_parameter` keeps the cast copy (:func:`vrnet_ext.nn.inference_cache.inference_cached`)
and otherwise returns the parameter itself, which autocast then casts as usual. The cast is the one
autocast makes (``Tensor.to``), so results are the same bit for bit.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vrnet_ext.nn.inference_cache import inference_cached


def autocast_parameter(module: nn.Module, name: str) -> torch.Tensor | None:
    """``module.<name>``, or its cached cast to the autocast dtype of its device (see module doc)."""
    param = getattr(module, name)
    if param is None or torch.is_grad_enabled() or not param.is_floating_point() or torch.compiler.is_compiling():
        return param  # a compiled graph casts (and fuses) on its own
    device_type = param.device.type
    if not torch.is_autocast_enabled(device_type):
        return param
    dtype = torch.get_autocast_dtype(device_type)
    if param.dtype == dtype:
        return param
    return inference_cached(module, f"autocast {name} {dtype}", (param,), lambda: param.detach().to(dtype))


class AutocastLinear(nn.Linear):
    """``nn.Linear`` (same parameters and state dict) whose weight and bias are cast once for
    autocast inference (:func:`autocast_parameter`)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, autocast_parameter(self, "weight"), autocast_parameter(self, "bias"))
