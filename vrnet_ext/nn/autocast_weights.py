"""Parameters cast once for autocast inference instead of on every forward.

Under ``torch.autocast`` a matrix product casts its float32 weight to the low-precision dtype on
every call; for a model applied pair after pair that is a fresh copy of every weight per forward.
:func:`autocast_parameter` keeps the cast copy on the module and hands it out again while the
parameter is unchanged (same storage, same in-place version counter) and no gradient is being
recorded, outside ``torch.compile``; otherwise it returns the parameter itself and autocast casts it
as usual. The cast is the one autocast makes (``Tensor.to``), so results are the same bit for bit.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


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
    key = (param.data_ptr(), param._version, dtype)
    cache = module.__dict__.setdefault("_autocast_parameters", {})
    entry = cache.get(name)
    if entry is None or entry[0] != key:
        # The entry holds the source storage too, so no later storage can reuse its address.
        source = param.detach()
        entry = cache[name] = (key, source.to(dtype), source)
    return entry[1]


class AutocastLinear(nn.Linear):
    """``nn.Linear`` (same parameters and state dict) whose weight and bias are cast once for
    autocast inference (:func:`autocast_parameter`)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, autocast_parameter(self, "weight"), autocast_parameter(self, "bias"))
