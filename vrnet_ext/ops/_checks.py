"""Argument checks shared by every op and its reference: errors name the argument.

Checks that read tensor values (NaN / Inf, index ranges, signs of weights) cost a host
synchronisation on a GPU. They are skipped while ``torch.compile`` traces (a check is a branch on
the data) and inside :func:`trusted_values`, for values that come from checked inputs through the
ops (VRNet's forward checks its clouds once and runs inside). The compiled kernels check CPU
tensors in C++ always (no synchronisation there, and their memory accesses rely on it).
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator

import torch

FLOAT_DTYPES = (torch.float32, torch.float64)
LOW_PRECISION_DTYPES = (torch.bfloat16, torch.float16)


def promote_low_precision(t: torch.Tensor | None) -> torch.Tensor | None:
    """bfloat16 / float16 -> float32; anything else unchanged (None passes through).

    Every op computes in float32 or better: geometry (distances, 3x3 SVDs, centroids) loses far
    too much in 8 or 11 mantissa bits. Low-precision inputs, as autocast produces them from bf16
    matrix products, are promoted on entry, so the op returns float32 (autocast's rule for
    precision-sensitive ops) and its gradient flows back through the cast in the input's dtype.
    """
    if isinstance(t, torch.Tensor) and t.dtype in LOW_PRECISION_DTYPES:
        return t.float()
    return t


def float32_region(t: torch.Tensor) -> torch.autocast:
    """Autocast off on ``t``'s device: the references compute in their inputs' dtype (float32 or
    better), never in a bfloat16 that an enclosing autocast would pick for their matrix products."""
    return torch.autocast(t.device.type, enabled=False)


def check_tensor(value: object, name: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.is_meta:  # (torch.compile's fake tensors are not meta: they pass)
        raise ValueError(f"{name} is a meta tensor (a shape without data); the ops compute on data: move it to a "
                         f"device first")
    return value


def check_float(t: torch.Tensor, name: str) -> None:
    check_tensor(t, name)
    if t.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name} must be float32 or float64, got {t.dtype}")


def check_index(t: torch.Tensor, name: str) -> None:
    check_tensor(t, name)
    if t.dtype != torch.int64:
        raise TypeError(f"{name} must be int64, got {t.dtype}")


def check_shape(t: torch.Tensor, name: str, rank: int, shape: str, last: int | None = None) -> None:
    if t.dim() != rank or (last is not None and t.shape[-1] != last):
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")


def check_same(tensors: dict[str, torch.Tensor]) -> None:
    """All tensors on one device; floating ones share a dtype."""
    names = list(tensors)
    first = tensors[names[0]]
    for name in names[1:]:
        t = tensors[name]
        if t.device != first.device:
            raise ValueError(f"{name} is on {t.device} but {names[0]} is on {first.device}")
        if t.is_floating_point() and first.is_floating_point() and t.dtype != first.dtype:
            raise TypeError(f"{name} has dtype {t.dtype} but {names[0]} has {first.dtype}")


_TRUST = threading.local()  # depth: how many trusted_values() regions this thread is in


def values_checked() -> bool:
    """Whether checks that read tensor values run here: not while compiling, nor inside
    :func:`trusted_values` (in this thread)."""
    return not torch.compiler.is_compiling() and not getattr(_TRUST, "depth", 0)


@contextmanager
def trusted_values(active: bool = True) -> Iterator[None]:
    """Inside (this thread, ``active``): the ops skip the checks that read tensor values (NaN / Inf,
    index ranges, signs of weights), in Python and, on accelerators, in the compiled kernels; on a
    GPU each is a host synchronisation. For tensors that come from checked inputs through the ops
    only: the kernels' memory accesses rely on finite points and indices in range. The backward of
    an op called inside runs trusted too."""
    if not active:
        yield
        return
    from vrnet_ext._extension import has_extension

    compiled = has_extension()
    _TRUST.depth = getattr(_TRUST, "depth", 0) + 1
    if compiled:
        from vrnet_ext import _C

        _C._suspend_value_checks(1)
    try:
        yield
    finally:
        _TRUST.depth -= 1
        if compiled:
            _C._suspend_value_checks(-1)


def check_finite(t: torch.Tensor, name: str) -> None:
    """Eager-mode NaN/Inf check for the references (the compiled kernels check in C++)."""
    if values_checked() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values")


def check_all_finite(tensors: dict[str, torch.Tensor]) -> None:
    """:func:`check_finite` of every tensor with one synchronisation (one fetch of all the flags)."""
    if not values_checked():
        return
    flags = torch.stack([torch.isfinite(t).all() for t in tensors.values()])
    if not bool(flags.all()):
        raise ValueError(f"{next(name for name, finite in zip(tensors, flags.tolist()) if not finite)} contains NaN "
                         f"or Inf values")


def check_index_range(idx: torch.Tensor, upper: int, name: str) -> None:
    if not values_checked() or idx.numel() == 0:
        return
    low, high = torch.aminmax(idx)
    if not bool((low >= 0) & (high < upper)):
        raise ValueError(f"{name} holds indices outside [0, {upper})")


def first_order_only(op: str, *saved: torch.Tensor) -> None:
    """Called by a compiled op's backward formula: its backward kernel has no derivative of its own,
    so a second-order use (``create_graph=True`` through tensors that need gradients) raises here,
    naming the op, instead of silently contributing nothing."""
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in saved):
        raise NotImplementedError(f"vrnet_ext.ops.{op}: the compiled kernel is differentiable once; second-order "
                                  f"gradients (create_graph=True) need backend='torch'")
