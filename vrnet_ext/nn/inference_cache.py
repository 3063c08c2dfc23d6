"""Tensors derived from parameters, computed once for inference instead of on every forward.

A module applied pair after pair in eval mode recomputes, on every call, tensors that depend on its
parameters and buffers alone: the bfloat16 casts autocast makes of its weights, BatchNorm folded
into a 1x1 convolution, an EdgeConv's combined weight. Each is a handful of small kernel calls, and
a forward makes dozens of them. :func:`inference_cached` keeps such a tensor on the module and hands
it out again while every tensor it was derived from is unchanged (same storage, same in-place
version counter) and no gradient is being recorded, outside ``torch.compile``; otherwise it
computes it afresh. The cached value is the one the computation gives, so results are the same bit
for bit.
"""
from __future__ import annotations

from typing import Callable, TypeVar

import torch
from torch import nn

T = TypeVar("T")


def inference_cached(module: nn.Module, name: str, sources: tuple[torch.Tensor | None, ...],
                     compute: Callable[[], T]) -> T:
    """``compute()``, kept on ``module`` under ``name`` while ``sources`` are unchanged (see the
    module doc)."""
    if torch.is_grad_enabled() or torch.compiler.is_compiling():
        return compute()  # autograd needs the graph; a compiled graph folds constants on its own
    key = tuple(None if t is None else (t.data_ptr(), t._version, t.dtype) for t in sources)
    cache = module.__dict__.setdefault("_inference_cache", {})
    entry = cache.get(name)
    if entry is None or entry[0] != key:
        # The entry holds the sources too, so no later tensor can reuse their addresses.
        entry = cache[name] = (key, compute(), tuple(None if t is None else t.detach() for t in sources))
    return entry[1]
