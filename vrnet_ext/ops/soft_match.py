"""Streamed soft matching: ``softmax(query keyᵀ scale) values`` without the N x M matrix.

VRNet's virtual corresponding points are ``M Y`` with ``M = softmax(Φx Φyᵀ / √c)``; for two 50k-point
clouds M alone is 10 GB in float32. On a CPU the compiled kernel walks over tiles of key points with
the online-softmax recurrence (running row maximum and normaliser, rescaled partial sums), so memory
stays O((N + M)(c + D)); the backward recomputes the tiles from the saved log-normaliser.

On a GPU, float32 problems whose feature size c and value width D are at most ``FLASH_MAX_WIDTH``
run a flash-style CUDA kernel on the TF32 tensor cores (tiles of queries and keys, the same online
softmax, no N x M matrix): each float32 operand split into two TF32 parts, three products each (about
float32's accuracy; torch's default), one TF32 product each where torch allows TF32 in float32 CUDA
matmuls (:func:`flash_passes`; ~1e-3 relative error in the scores); it needs compute capability 8.0
or later. Its backward kernels recompute the probabilities tile by tile from the saved
log-normaliser with the forward's arithmetic (dK and dV per block of keys, dQ per block of queries:
no atomics); a backward that is itself differentiated runs torch's products on blocks of query rows
instead. Other problems run torch's batched products on blocks of query rows of at most
``DENSE_BLOCK_MAX_SCORES`` scores each (one block for most problems), and a backward through more
than one block recomputes each block's scores, as flash attention does: memory stays that of one
block.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_same, check_shape, first_order_only,
                                   float32_region, promote_low_precision, values_checked)
from vrnet_ext.runtime import cuda_has_tensor_cores, cuda_matmul_allows_tf32, cuda_multiprocessors


DENSE_BLOCK_MAX_SCORES = 1 << 26  # scores per dense block off the CPU: 256 MB per float32 copy
FLASH_MAX_WIDTH = 64  # largest c and D of the CUDA flash kernel (its shared-memory tiles)
# Blocks per multiprocessor the flash forward aims for: few query rows split the keys into parts until
# the GPU holds about this many blocks each (its registers and shared memory allow three or four).
FLASH_BLOCKS_PER_MULTIPROCESSOR = 4


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
    check_lse_finite(lse, scale)
    out = torch.bmm(torch.softmax(scores, dim=-1), values)
    return SoftMatch(out, lse, scores.argmax(dim=-1))


class _SoftMatchInBlocks(torch.autograd.Function):
    """:func:`soft_match_reference` on blocks of ``block`` query rows; the backward recomputes each
    block's probabilities (:func:`recomputed_gradients`), so at most one block's (B, block, M)
    matrices are alive in either pass. The backward is made of differentiable products, so
    second-order gradients flow through it."""

    @staticmethod
    def forward(ctx, query, key, values, scale: float, block: int):
        parts = [soft_match_reference(query[:, start:start + block], key, values, scale)
                 for start in range(0, query.shape[1], block)]
        out, lse, argmax = (torch.cat(pieces, dim=1) for pieces in zip(*parts))
        ctx.save_for_backward(query, key, values)
        ctx.scale, ctx.block = scale, block
        ctx.mark_non_differentiable(argmax)
        return out, lse, argmax

    @staticmethod
    def backward(ctx, grad_out, grad_lse, _grad_argmax):
        grads = recomputed_gradients(*ctx.saved_tensors, grad_out, grad_lse, ctx.scale, ctx.block)
        return (*grads, None, None)


def recomputed_gradients(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, grad_out: torch.Tensor,
                         grad_lse: torch.Tensor, scale: float, block: int
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of a soft matching in query, key and values, the probabilities recomputed by torch's
    products for blocks of ``block`` query rows (each block holds its rows' every score, so its
    softmax is complete): the dense formula's gradients in the inputs' precision, whatever rounding
    produced the forward's outputs, and differentiable again. With P = softmax(scale Q Kᵀ) and
    dP = dO Vᵀ: dScores = P ∘ (dP - rowsum(P ∘ dP) + dlse)."""
    with float32_region(query):
        grad_query, grad_key, grad_values = [], torch.zeros_like(key), torch.zeros_like(values)
        for start in range(0, query.shape[1], block):
            rows = slice(start, start + block)
            probs = torch.softmax(torch.bmm(query[:, rows], key.mT) * scale, dim=-1)
            grad_probs = torch.bmm(grad_out[:, rows], values.mT)
            shift = grad_lse[:, rows] - (probs * grad_probs).sum(-1)
            grad_scores = probs * (grad_probs + shift[..., None])
            grad_query.append(torch.bmm(grad_scores, key) * scale)
            grad_key = grad_key + torch.bmm(grad_scores.mT, query[:, rows]) * scale
            grad_values = grad_values + torch.bmm(probs.mT, grad_out[:, rows])
    return torch.cat(grad_query, dim=1), grad_key, grad_values


def query_block(batch: int, cols: int, max_scores: int = DENSE_BLOCK_MAX_SCORES) -> int:
    """Query rows per dense block: at most ``max_scores`` scores (B·rows·M), at least one row."""
    return max(1, max_scores // max(1, batch * cols))


def flash_passes() -> int:
    """Tensor-core products per operand pair of the CUDA flash kernel: 1 (TF32) where torch allows
    TF32 in float32 CUDA matmuls (:func:`vrnet_ext.runtime.cuda_matmul_allows_tf32`), else 3 (split
    TF32, about float32's accuracy; torch's default)."""
    return 1 if cuda_matmul_allows_tf32() else 3


def flash_fits(query: torch.Tensor, values: torch.Tensor) -> bool:
    """Whether the CUDA flash kernel takes this problem: float32 on a GPU with TF32 tensor cores, c and
    D at most FLASH_MAX_WIDTH."""
    return (query.device.type == "cuda" and query.dtype == torch.float32
            and query.shape[2] <= FLASH_MAX_WIDTH and values.shape[2] <= FLASH_MAX_WIDTH
            and cuda_has_tensor_cores(query.device))


class _SoftMatchFlash(torch.autograd.Function):
    """The CUDA flash kernels (``passes`` 1 or 3): the forward (its keys split into parts where fewer
    than ``target_blocks`` blocks would hold the query rows), and the backward recomputing the
    probabilities tile by tile from the saved log-normaliser with the forward's arithmetic. Where the
    backward itself is differentiated (``create_graph``), :func:`recomputed_gradients` instead."""

    @staticmethod
    def forward(ctx, query, key, values, scale: float, passes: int, target_blocks: int):
        out, lse, argmax = torch.ops.vrnet_ext.soft_match_flash(query, key, values, scale, passes, target_blocks)
        ctx.save_for_backward(query, key, values, out, lse)
        ctx.scale, ctx.passes = scale, passes
        ctx.mark_non_differentiable(argmax)
        return out, lse, argmax

    @staticmethod
    def backward(ctx, grad_out, grad_lse, _grad_argmax):
        query, key, values, out, lse = ctx.saved_tensors
        if torch.is_grad_enabled():  # a graph of the backward is asked for: differentiable products
            block = query_block(query.shape[0], key.shape[1])
            grads = recomputed_gradients(query, key, values, grad_out, grad_lse, ctx.scale, block)
        else:
            grads = torch.ops.vrnet_ext.soft_match_flash_backward(grad_out, grad_lse, query, key, values, out, lse,
                                                                 ctx.scale, ctx.passes)
        return (*grads, None, None, None)


def check_lse_finite(lse: torch.Tensor, scale: float) -> None:
    """Raise ValueError when a row's scores overflowed (where values are checked)."""
    if values_checked() and not bool(torch.isfinite(lse).all()):
        raise ValueError(f"soft_match scores overflow: scale * query . key is not finite (scale {scale})")


def dense_in_query_blocks(query: torch.Tensor, key: torch.Tensor, values: torch.Tensor, scale: float,
                          max_scores: int = DENSE_BLOCK_MAX_SCORES) -> SoftMatch:
    """:func:`soft_match_reference` on blocks of query rows of at most ``max_scores`` scores each
    (at least one row): the same values and gradients, with at most one block's (B, rows, M)
    matrices alive in the forward and in the backward (which then recomputes each block)."""
    rows, block = query.shape[1], query_block(query.shape[0], key.shape[1], max_scores)
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
        backend: ``"ext"`` (on a CPU the compiled streamed kernel; on a GPU the flash kernel
            where :func:`flash_fits`, else dense products on blocks of query rows,
            :func:`dense_in_query_blocks`) or ``"torch"`` (dense reference).
        return_stats: also return the log-normaliser and the row peak (:class:`SoftMatch`).

    Returns:
        (B, N, D), or :class:`SoftMatch` with ``return_stats``. ``out`` and ``lse`` are
        differentiable in query, key and values. Low-precision inputs are promoted to float32.
    """
    query, key, values = (promote_low_precision(t) for t in (query, key, values))
    validate_soft_match(query, key, values, scale)
    scale = 1.0 / math.sqrt(query.shape[2]) if scale is None else float(scale)
    compiled = use_extension(backend, query.device)
    if compiled and query.device.type == "cpu":
        result = SoftMatch(*torch.ops.vrnet_ext.soft_match(query, key, values, scale))
    else:
        for name, t in (("query", query), ("key", key), ("values", values)):
            check_finite(t, name)
        if compiled and flash_fits(query, values):
            target_blocks = FLASH_BLOCKS_PER_MULTIPROCESSOR * cuda_multiprocessors(query.device)
            result = SoftMatch(*_SoftMatchFlash.apply(query, key, values, scale, flash_passes(), target_blocks))
            check_lse_finite(result.lse, scale)
        else:
            with float32_region(query):
                result = (dense_in_query_blocks if backend == "ext" else soft_match_reference)(query, key, values,
                                                                                               scale)
    return result if return_stats else result.out


if has_extension():

    @torch.library.register_fake("vrnet_ext::soft_match")
    def _soft_match_fake(query, key, values, scale):
        B, N = query.shape[0], query.shape[1]
        return (query.new_empty((B, N, values.shape[2])), query.new_empty((B, N)),
                query.new_empty((B, N), dtype=torch.int64))

    @torch.library.register_fake("vrnet_ext::soft_match_flash")
    def _soft_match_flash_fake(query, key, values, scale, passes, target_blocks):
        return _soft_match_fake(query, key, values, scale)

    @torch.library.register_fake("vrnet_ext::soft_match_flash_backward")
    def _soft_match_flash_backward_fake(grad_out, grad_lse, query, key, values, out, lse, scale, passes):
        return torch.empty_like(query), torch.empty_like(key), torch.empty_like(values)

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
