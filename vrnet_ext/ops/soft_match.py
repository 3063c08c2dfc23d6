"""Streamed soft matching: ``softmax(query keyᵀ scale) values`` without the N x M matrix.

VRNet's virtual corresponding points are ``M Y`` with ``M = softmax(Φx Φyᵀ / √c)``; for two 50k-point
clouds M alone is 10 GB in float32. On a CPU the compiled kernel walks over tiles of key points with
the online-softmax recurrence (running row maximum and normaliser, rescaled partial sums), so memory
stays O((N + M)(c + D)); the backward recomputes the tiles from the saved log-normaliser.

On other devices (a GPU) the compiled backend runs torch's batched products on blocks of query rows
of at most ``DENSE_BLOCK_MAX_SCORES`` scores each (one block for most problems), and a backward
through more than one block recomputes each block's scores from the saved log-normaliser, as flash
attention does: memory stays that of one block. (A streamed CUDA kernel of one thread per query
row measured two orders of magnitude behind those products on an H200.)
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_same, check_shape, first_order_only,
                                   float32_region, promote_low_precision, values_checked)


DENSE_BLOCK_MAX_SCORES = 1 << 26  # scores per dense block off the CPU: 256 MB per float32 copy


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
    if values_checked() and not bool(torch.isfinite(lse).all()):
        raise ValueError(f"soft_match scores overflow: scale * query . key is not finite (scale {scale})")
    out = torch.bmm(torch.softmax(scores, dim=-1), values)
    return SoftMatch(out, lse, scores.argmax(dim=-1))


class _SoftMatchInBlocks(torch.autograd.Function):
    """:func:`soft_match_reference` on blocks of ``block`` query rows; the backward recomputes each
    block's probabilities from the saved log-normaliser, so at most one block's (B, block, M)
    matrices are alive in either pass. The backward is made of differentiable products, so
    second-order gradients flow through it."""

    @staticmethod
    def forward(ctx, query, key, values, scale: float, block: int):
        parts = [soft_match_reference(query[:, start:start + block], key, values, scale)
                 for start in range(0, query.shape[1], block)]
        out, lse, argmax = (torch.cat(pieces, dim=1) for pieces in zip(*parts))
        ctx.save_for_backward(query, key, values, out, lse)
        ctx.scale, ctx.block = scale, block
        ctx.mark_non_differentiable(argmax)
        return out, lse, argmax

    @staticmethod
    def backward(ctx, grad_out, grad_lse, _grad_argmax):
        # With P = exp(scale Q Kᵀ - lse): dScores = P (dO Vᵀ + shift), shift_i = dlse_i - dO_i . O_i.
        query, key, values, out, lse = ctx.saved_tensors
        scale, block = ctx.scale, ctx.block
        with float32_region(query):
            shift = grad_lse - (grad_out * out).sum(-1)
            grad_query, grad_key, grad_values = [], torch.zeros_like(key), torch.zeros_like(values)
            for start in range(0, query.shape[1], block):
                rows = slice(start, start + block)
                probs = torch.exp(torch.bmm(query[:, rows], key.mT) * scale - lse[:, rows, None])
                grad_scores = probs * (torch.bmm(grad_out[:, rows], values.mT) + shift[:, rows, None])
                grad_query.append(torch.bmm(grad_scores, key) * scale)
                grad_key = grad_key + torch.bmm(grad_scores.mT, query[:, rows]) * scale
                grad_values = grad_values + torch.bmm(probs.mT, grad_out[:, rows])
        return torch.cat(grad_query, dim=1), grad_key, grad_values, None, None


def dense_in_query_blocks(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float,
                          max_scores: int = DENSE_BLOCK_MAX_SCORES) -> SoftMatch:
    """:func:`soft_match_reference` on blocks of query rows of at most ``max_scores`` scores each
    (at least one row): the same values and gradients, with at most one block's (B, rows, M)
    matrices alive in the forward and in the backward (which then recomputes each block)."""
    batch, rows, cols = query.shape[0], query.shape[1], key.shape[1]
    block = max(1, max_scores // max(1, batch * cols))
    if rows <= block:
        return soft_match_reference(query, key, values, scale)
    return SoftMatch(*_SoftMatchInBlocks.apply(query, key, values, scale, block))


def soft_match(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float | None = None,
               backend: str = "ext", return_stats: bool = False) -> torch.Tensor | SoftMatch:
    """``softmax(query keyᵀ scale, dim=-1) values`` without the (B, N, M) matrix on the compiled backend.

    Args:
        query: (B, N, c) features of the points that look for a match.
        key: (B, M, c) features of the candidates (M >= 1).
        values: (B, M, D) what each candidate contributes (VRNet: ``[Y | Φyᵀ]``).
        scale: score multiplier, default ``1 / sqrt(c)``.
        backend: ``"ext"`` (on a CPU the compiled streamed kernel; elsewhere dense products on
            blocks of query rows, :func:`dense_in_query_blocks`) or ``"torch"`` (dense reference).
        return_stats: also return the log-normaliser and the row peak (:class:`SoftMatch`).

    Returns:
        (B, N, D), or :class:`SoftMatch` with ``return_stats``. ``out`` and ``lse`` are
        differentiable in query, key and values. Low-precision inputs are promoted to float32.
    """
    query, key, values = (promote_low_precision(t) for t in (query, key, values))
    validate_soft_match(query, key, values, scale)
    scale = 1.0 / math.sqrt(query.shape[2]) if scale is None else float(scale)
    if use_extension(backend, query.device) and query.device.type == "cpu":
        result = SoftMatch(*torch.ops.vrnet_ext.soft_match(query, key, values, scale))
    else:
        for name, t in (("query", query), ("key", key), ("values", values)):
            check_finite(t, name)
        with float32_region(query):
            result = (dense_in_query_blocks if backend == "ext" else soft_match_reference)(query, key, values, scale)
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
