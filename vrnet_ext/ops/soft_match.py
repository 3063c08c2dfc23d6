"""Streamed soft matching: ``softmax(query keyᵀ scale) values`` without the N x M matrix.

VRNet's virtual corresponding points are ``M Y`` with ``M = softmax(Φx Φyᵀ / √c)``; for two 50k-point
clouds M alone is 10 GB in float32. The compiled kernel walks over tiles of key points with the
online-softmax recurrence (running row maximum and normaliser, rescaled partial sums), so memory
stays O((N + M)(c + D)); the backward recomputes the tiles from the saved log-normaliser.

On a CUDA device the streamed kernel (one thread per row) runs far behind torch's batched products
(an H200, forward and backward, B = 28, N = M = 768, c = 512: 0.67 s against 3.7 ms), so there the
compiled backend runs the dense products on blocks of query rows of at most
``GPU_DENSE_MAX_SCORES`` scores each (one block for most problems); only a large matching that
needs gradients streams, since autograd would keep every block's matrix.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_same, check_shape, first_order_only,
                                   float32_region, promote_low_precision)


GPU_DENSE_MAX_SCORES = 1 << 26  # 256 MB per float32 copy of the (B, N, M) scores


def streams_on(device: torch.device, batch: int, rows: int, cols: int, needs_grad: bool) -> bool:
    """Whether the compiled backend streams a (batch, rows, cols) score matrix on ``device``: always
    on a CPU; on a GPU only past ``GPU_DENSE_MAX_SCORES`` scores with gradients to keep (else the
    dense products on blocks of query rows are faster)."""
    return device.type != "cuda" or (needs_grad and batch * rows * cols > GPU_DENSE_MAX_SCORES)


class SoftMatch(NamedTuple):
    """What one soft-matching pass yields for query (B, N, c), key (B, M, c), values (B, M, D)."""

    out: torch.Tensor     # (B, N, D) sum_j softmax_j(scale q_i . k_j) v_j
    lse: torch.Tensor     # (B, N) log sum_j exp(scale q_i . k_j): log P_ij = scale q_i . k_j - lse_i
    argmax: torch.Tensor  # (B, N) int64, first j with the largest score (not differentiable)


def validate_soft_match(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor,
                        scale: float | None) -> None:
    """Raise TypeError/ValueError naming the argument (the compiled kernel checks the same)."""
    for name, t in (("query", query), ("key", key), ("values", values)):
        check_float(t, name)
    check_shape(query, "query", 3, "(B, N, c)")
    check_shape(key, "key", 3, "(B, M, c)")
    check_shape(values, "values", 3, "(B, M, D)")
    check_same({"query": query, "key": key, "values": values})
    if not query.shape[0] == key.shape[0] == values.shape[0]:
        raise ValueError(f"query, key and values must have the same batch size, got {query.shape[0]}, "
                         f"{key.shape[0]}, {values.shape[0]}")
    if key.shape[2] != query.shape[2]:
        raise ValueError(f"key must have query's feature size c = {query.shape[2]}, got {tuple(key.shape)}")
    if query.shape[2] < 1:
        raise ValueError(f"query must have at least one feature channel, got {tuple(query.shape)}")
    if key.shape[1] < 1:
        raise ValueError(f"key must hold at least one point (a softmax over nothing), got {tuple(key.shape)}")
    if values.shape[1] != key.shape[1]:
        raise ValueError(f"values must have one row per key point (M = {key.shape[1]}), got {tuple(values.shape)}")
    finite_number = isinstance(scale, (int, float)) and not isinstance(scale, bool) and math.isfinite(scale)
    if scale is not None and not finite_number:
        raise ValueError(f"scale must be a finite number, got {scale!r}")


def soft_match_reference(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float) -> SoftMatch:
    """Dense pure-PyTorch soft matching (builds the (B, N, M) score matrix)."""
    scores = torch.bmm(query, key.transpose(1, 2)) * scale
    lse = torch.logsumexp(scores, dim=-1)
    if not torch.compiler.is_compiling() and not bool(torch.isfinite(lse).all()):
        raise ValueError(f"soft_match scores overflow: scale * query . key is not finite (scale {scale})")
    out = torch.bmm(torch.softmax(scores, dim=-1), values)
    return SoftMatch(out, lse, scores.argmax(dim=-1))


def dense_in_query_blocks(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float,
                          max_scores: int = GPU_DENSE_MAX_SCORES) -> SoftMatch:
    """:func:`soft_match_reference` on blocks of query rows of at most ``max_scores`` scores each
    (at least one row): the same values, with at most one block's (B, rows, M) matrix alive when
    nothing needs a gradient."""
    batch, rows, cols = query.shape[0], query.shape[1], key.shape[1]
    block = max(1, max_scores // max(1, batch * cols))
    if rows <= block:
        return soft_match_reference(query, key, values, scale)
    parts = [soft_match_reference(query[:, start:start + block], key, values, scale)
             for start in range(0, rows, block)]
    return SoftMatch(*(torch.cat(pieces, dim=1) for pieces in zip(*parts)))


def soft_match(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float | None = None,
               backend: str = "ext", return_stats: bool = False) -> torch.Tensor | SoftMatch:
    """``softmax(query keyᵀ scale, dim=-1) values``, streamed over key tiles.

    Args:
        query: (B, N, c) features of the points that look for a match.
        key: (B, M, c) features of the candidates (M >= 1).
        values: (B, M, D) what each candidate contributes (VRNet: ``[Y | Φyᵀ]``).
        scale: score multiplier, default ``1 / sqrt(c)``.
        backend: ``"ext"`` (compiled, streamed; on a GPU dense products on blocks of query rows
            unless a large matching needs gradients, see :func:`streams_on`) or ``"torch"``
            (dense reference).
        return_stats: also return the log-normaliser and the row peak (:class:`SoftMatch`).

    Returns:
        (B, N, D), or :class:`SoftMatch` with ``return_stats``. ``out`` and ``lse`` are
        differentiable in query, key and values. Low-precision inputs are promoted to float32.
    """
    query, key, values = (promote_low_precision(t) for t in (query, key, values))
    validate_soft_match(query, key, values, scale)
    scale = 1.0 / math.sqrt(query.shape[2]) if scale is None else float(scale)
    compiled = use_extension(backend, query.device)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (query, key, values))
    if compiled and streams_on(query.device, *query.shape[:2], key.shape[1], needs_grad):
        result = SoftMatch(*torch.ops.vrnet_ext.soft_match(query, key, values, scale))
    else:
        for name, t in (("query", query), ("key", key), ("values", values)):
            check_finite(t, name)
        with float32_region(query):
            result = (dense_in_query_blocks if compiled else soft_match_reference)(query, key, values, scale)
    return result if return_stats else result.out


if has_extension():

    @torch.library.register_fake("vrnet_ext::soft_match")
    def _soft_match_fake(query, key, values, scale):
        B, N = query.shape[0], query.shape[1]
        return (query.new_empty((B, N, values.shape[2])), query.new_empty((B, N)),
                query.new_empty((B, N), dtype=torch.int64))

    @torch.library.register_fake("vrnet_ext::soft_match_backward")
    def _soft_match_backward_fake(grad_out, grad_lse, query, key, values, out, lse, scale):
        return torch.empty_like(query), torch.empty_like(key), torch.empty_like(values)

    def _soft_match_setup_context(ctx, inputs, output):
        query, key, values, scale = inputs
        out, lse, argmax = output
        ctx.save_for_backward(query, key, values, out, lse)
        ctx.scale = scale
        ctx.mark_non_differentiable(argmax)

    def _soft_match_backward(ctx, grad_out, grad_lse, _grad_argmax):
        query, key, values, out, lse = ctx.saved_tensors
        first_order_only("soft_match", grad_out, grad_lse, query, key, values)
        grad_out = torch.zeros_like(out) if grad_out is None else grad_out
        grad_lse = torch.zeros_like(lse) if grad_lse is None else grad_lse
        grads = torch.ops.vrnet_ext.soft_match_backward(grad_out, grad_lse, query, key, values, out, lse, ctx.scale)
        return (*grads, None)

    torch.library.register_autograd(
        "vrnet_ext::soft_match", _soft_match_backward, setup_context=_soft_match_setup_context
    )
