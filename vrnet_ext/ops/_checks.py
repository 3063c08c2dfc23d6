"""Argument checks shared by every op and its reference: errors name the argument."""
from __future__ import annotations

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


def check_finite(t: torch.Tensor, name: str) -> None:
    """Eager-mode NaN/Inf check for the references (the compiled kernels check in C++)."""
    if torch.compiler.is_compiling():
        return
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values")


def check_index_range(idx: torch.Tensor, upper: int, name: str) -> None:
    if torch.compiler.is_compiling() or idx.numel() == 0:
        return
    if int(idx.min()) < 0 or int(idx.max()) >= upper:
        raise ValueError(f"{name} holds indices outside [0, {upper})")


def first_order_only(op: str, *saved: torch.Tensor) -> None:
    """Called by a compiled op's backward formula: its backward kernel has no derivative of its own,
    so a second-order use (``create_graph=True`` through tensors that need gradients) raises here,
    naming the op, instead of silently contributing nothing."""
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in saved):
        raise NotImplementedError(f"vrnet_ext.ops.{op}: the compiled kernel is differentiable once; second-order "
                                  f"gradients (create_graph=True) need backend='torch'")
