"""Multi-head scaled dot-product attention: ``out = ops.attention(q, k, v)``.

``q`` (B, H, N, D), ``k`` and ``v`` (B, H, M, D) -> (B, H, N, D),
``out[b, h, i] = softmax_j(scale q[b, h, i] . k[b, h, j]) v[b, h, j]`` (``scale`` default 1 / sqrt(D)).
The reference is ``F.scaled_dot_product_attention``. The compiled CPU kernel serves inference on
bfloat16 heads (the Transformer's attention under its bfloat16 autocast) where its two products run
on AMX tiles (:func:`products_on_amx`: an AMX CPU, heads of 16, 32, 48 or 64 channels): scores,
exponentials and sums in float32, the softmax weights rounded to bfloat16 for their product with
``v`` (as torch's fused CPU kernel does), a softmax on AVX-512 with a base-2 exponential.
Every other call (float32 or float64 heads, a gradient to record, dropout, more than ``MAX_KEYS``
keys, a CPU without AMX or a head size the tiles do not take, where the kernel's products are plain
loops, ~15x slower than torch's kernel, a device without the kernel) runs the reference, which is
differentiable.
The result's memory is (B, N, H, D) either way (a point's heads form one row).
"""
from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_tensor

MAX_KEYS = 1 << 16  # the kernel keeps 64 x M float32 scores per thread; longer key sets stream in torch's kernel


def _validate(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float | None, dropout_p: float) -> None:
    for name, t in (("q", q), ("k", k), ("v", v)):
        check_tensor(t, name)
        if not t.is_floating_point():
            raise TypeError(f"{name} must be a floating tensor, got {t.dtype}")
        if t.dim() != 4:
            raise ValueError(f"{name} must have shape (B, H, L, D), got {tuple(t.shape)}")
        if t.dtype != q.dtype:
            raise TypeError(f"q, k and v must share a dtype, got {q.dtype} and {t.dtype} ({name})")
        if t.device != q.device:
            raise ValueError(f"{name} is on {t.device} but q is on {q.device}")
    B, H, _, D = q.shape
    if k.shape[0] != B or k.shape[1] != H or k.shape[3] != D:
        raise ValueError(f"k must have shape (B, H, M, D) = ({B}, {H}, M, {D}), got {tuple(k.shape)}")
    if v.shape != k.shape:
        raise ValueError(f"v must have k's shape {tuple(k.shape)}, got {tuple(v.shape)}")
    if D < 1:
        raise ValueError(f"q must have at least one channel per head, got {tuple(q.shape)}")
    if k.shape[2] < 1:
        raise ValueError(f"k must hold at least one key (a softmax over nothing), got {tuple(k.shape)}")
    if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float))
                              or not math.isfinite(scale) or scale <= 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale!r}")
    if isinstance(dropout_p, bool) or not isinstance(dropout_p, (int, float)) or not 0 <= dropout_p < 1:
        raise ValueError(f"dropout_p must be a number in [0, 1), got {dropout_p!r}")


def attention_reference(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float | None = None,
                        dropout_p: float = 0.0) -> torch.Tensor:
    """``F.scaled_dot_product_attention`` (torch's fused kernel), differentiable."""
    return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout_p, scale=scale)


_ON_AMX: dict[int, bool] = {}  # head channels -> the kernel's answer, asked once per size


@torch.compiler.assume_constant_result
def products_on_amx(head_channels: int) -> bool:
    """Whether the compiled kernel multiplies heads of ``head_channels`` channels on AMX tiles (the
    kernel's own answer; False without the extension). A constant for ``torch.compile``."""
    if head_channels not in _ON_AMX:
        _ON_AMX[head_channels] = has_extension() and bool(torch.ops.vrnet_ext.attention_on_amx(head_channels))
    return _ON_AMX[head_channels]


def _kernel_serves(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, dropout_p: float, backend: str) -> bool:
    records_gradient = torch.is_grad_enabled() and (q.requires_grad or k.requires_grad or v.requires_grad)
    return (use_extension(backend, q.device) and q.device.type == "cpu" and q.dtype == torch.bfloat16
            and dropout_p == 0 and not records_gradient and k.shape[2] <= MAX_KEYS and products_on_amx(q.shape[3]))


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float | None = None,
              dropout_p: float = 0.0, backend: str = "ext") -> torch.Tensor:
    """softmax(q kᵀ scale) v for every batch and head.

    Args:
        q: (B, H, N, D) queries.
        k: (B, H, M, D) keys (M >= 1).
        v: (B, H, M, D) values.
        scale: score multiplier, default ``1 / sqrt(D)``.
        dropout_p: dropout on the attention weights (training; the reference then runs).
        backend: ``"ext"`` (the compiled kernel where it serves, see the module) or ``"torch"``.

    Returns:
        (B, H, N, D) in q's dtype. The kernel raises ValueError on NaN or Inf inputs; the reference
        propagates them as torch's kernel does (a finiteness pass over bfloat16 heads would cost
        the reference more than its attention).
    """
    _validate(q, k, v, scale, dropout_p)
    if _kernel_serves(q, k, v, dropout_p, backend):
        return torch.ops.vrnet_ext.attention(q, k, v, 1.0 / math.sqrt(q.shape[3]) if scale is None else float(scale))
    return attention_reference(q, k, v, scale, dropout_p)


if has_extension():

    @torch.library.register_fake("vrnet_ext::attention")
    def _attention_fake(q, k, v, scale):
        B, H, N, D = q.shape
        return q.new_empty((B, N, H, D)).permute(0, 2, 1, 3)
