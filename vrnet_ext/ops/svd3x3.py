"""Batched 3x3 SVD: ``U, S, V = svd3x3(A)`` with ``A = U diag(S) V^T``.

The compiled kernel runs a one-sided Jacobi SVD in double precision per matrix; singular values
are sorted descending. Its backward damps the 1/(s_k - s_l) and 1/(s_k + s_l) terms, so it stays
finite for repeated or zero singular values (where the true gradient of U, V is unbounded).
"""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_shape, first_order_only, float32_region,
                                   promote_low_precision)


def svd3x3_reference(A: torch.Tensor):
    """``torch.linalg.svd`` returning V instead of V^T."""
    check_finite(A, "A")
    U, S, Vh = torch.linalg.svd(A)
    return U, S, Vh.mT


def svd3x3(A: torch.Tensor, backend: str = "ext"):
    """SVD of a batch of 3x3 matrices.

    Args:
        A: (B, 3, 3) float32/float64 (bfloat16/float16 are promoted to float32).
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        U (B, 3, 3), S (B, 3) descending, V (B, 3, 3) with ``A = U diag(S) V^T``. Singular vectors
        are defined up to the sign of each (u_i, v_i) pair.

    Precision (fuzz suite): U and V orthonormal and ``U diag(S) V^T`` equal to A to ~64 ulps of
    max |A|, for random, rank-deficient, zero and repeated-singular-value matrices at scales
    1e-8..1e8; gradients are damped only relative to the largest singular value (1e-9 S_0).
    """
    A = promote_low_precision(A)
    check_float(A, "A")
    check_shape(A, "A", 3, "(B, 3, 3)", last=3)
    if A.shape[1] != 3:
        raise ValueError(f"A must have shape (B, 3, 3), got {tuple(A.shape)}")
    if use_extension(backend, A.device):
        return torch.ops.vrnet_ext.svd3x3(A)
    with float32_region(A):
        return svd3x3_reference(A)


if has_extension():

    @torch.library.register_fake("vrnet_ext::svd3x3")
    def _svd3x3_fake(A):
        return torch.empty_like(A), A.new_empty(A.shape[:-1]), torch.empty_like(A)

    @torch.library.register_fake("vrnet_ext::svd3x3_backward")
    def _svd3x3_backward_fake(grad_U, grad_S, grad_V, U, S, V):
        return torch.empty_like(U)

    def _svd3x3_setup_context(ctx, inputs, output):
        ctx.save_for_backward(*output)

    def _svd3x3_backward(ctx, grad_U, grad_S, grad_V):
        U, S, V = ctx.saved_tensors
        first_order_only("svd3x3", grad_U, grad_S, grad_V, U, S, V)
        return torch.ops.vrnet_ext.svd3x3_backward(grad_U, grad_S, grad_V, U, S, V)

    torch.library.register_autograd("vrnet_ext::svd3x3", _svd3x3_backward, setup_context=_svd3x3_setup_context)
