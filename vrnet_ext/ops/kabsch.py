"""Weighted Kabsch / Procrustes: ``R, t = kabsch(src, tgt, weights)`` with ``R src + t ~ tgt``, and its
robust form ``R, t = robust_kabsch(src, tgt, weights, iterations, kernel, scale)``.

``R, t = argmin_{R in SO(3), t} sum_i w_i |R x_i + t - y_i|^2``: each weight enters once
(weights are normalised to sum 1; they scale points, not squared residuals twice). The compiled
kernel fuses the weighted centroids and covariance, solves each 3x3 SVD in double precision and
fixes reflections (det R = +1). Degenerate inputs (collinear or duplicate points, rank-deficient
covariance) give one of the minimising rotations and a finite backward.

``robust_kabsch`` follows the weighted solve with iteratively reweighted steps (IRLS): each point's
weight is multiplied by a robust weight of its residual under the current estimate (:func:`robust_weights`)
and the problem is solved again. The compiled kernel runs every step of a problem in one pass (no
tensor op per step); it has no backward, so where a gradient is needed the steps run as
differentiable ``kabsch`` calls.
"""
from __future__ import annotations

import math

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (check_finite, check_float, check_same, check_shape, first_order_only,
                                   float32_region, promote_low_precision, values_checked)

ROBUST_KERNELS = ("cauchy", "geman_mcclure", "welsch")
MAX_ROBUST_ITERATIONS = 1000  # the compiled op's kMaxRobustIterations


def robust_weights(kernel: str, scaled_residual: torch.Tensor) -> torch.Tensor:
    """Weight w(u) of residuals in units of the scale (any shape): ``"cauchy"`` 1 / (1 + u^2),
    ``"geman_mcclure"`` 1 / (1 + u^2)^2, ``"welsch"`` exp(-u^2); all 1 at u = 0, each flatter for far
    residuals than the one before (the IRLS steps of :func:`robust_kabsch`, FGR's line process)."""
    squared = scaled_residual.square()
    if kernel == "cauchy":
        return 1 / (1 + squared)
    if kernel == "geman_mcclure":
        return 1 / (1 + squared).square()
    if kernel == "welsch":
        return torch.exp(-squared)
    raise ValueError(f"kernel must be one of {ROBUST_KERNELS}, got {kernel!r}")


def _validate(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None) -> None:
    check_float(src, "src")
    check_float(tgt, "tgt")
    check_shape(src, "src", 3, "(B, N, 3)", last=3)
    if tgt.shape != src.shape:
        raise ValueError(f"tgt must have the shape of src {tuple(src.shape)}, got {tuple(tgt.shape)}")
    tensors = {"src": src, "tgt": tgt}
    if weights is not None:
        check_float(weights, "weights")
        if weights.shape != src.shape[:2]:
            raise ValueError(f"weights must have shape (B, N) = {tuple(src.shape[:2])}, got {tuple(weights.shape)}")
        tensors["weights"] = weights
    check_same(tensors)
    if src.shape[1] < 3:
        raise ValueError(f"src needs at least 3 points per cloud, got {src.shape[1]}")


def kabsch_reference(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None):
    """Pure-PyTorch weighted Procrustes through ``torch.linalg.svd`` with the reflection fix."""
    check_finite(src, "src")
    check_finite(tgt, "tgt")
    if weights is None:
        weights = torch.ones(src.shape[:2], dtype=src.dtype, device=src.device)
    check_finite(weights, "weights")
    if values_checked():
        if bool((weights < 0).any()):
            raise ValueError("weights must be non-negative")
        if bool((weights.sum(1) <= 0).any()):
            raise ValueError("weights sum to zero for some batch: at least one point needs a positive weight")
    w = (weights / weights.sum(dim=1, keepdim=True)).unsqueeze(-1)
    src_centroid = (w * src).sum(dim=1)
    tgt_centroid = (w * tgt).sum(dim=1)
    H = (w * (src - src_centroid.unsqueeze(1))).mT @ (tgt - tgt_centroid.unsqueeze(1))
    U, _, Vh = torch.linalg.svd(H)
    V = Vh.mT
    d = torch.sign(torch.linalg.det(V @ U.mT))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = V @ D @ U.mT
    t = tgt_centroid - (R @ src_centroid.unsqueeze(-1)).squeeze(-1)
    return R, t


def kabsch(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None, backend: str = "ext"):
    """Rigid transform aligning ``src`` to ``tgt`` (row i of each corresponds).

    Args:
        src: (B, N, 3) source points, N >= 3 (float32/float64; bfloat16/float16 inputs are
            promoted to float32, as under autocast).
        tgt: (B, N, 3) corresponding target points.
        weights: optional (B, N) non-negative weights (not all zero per batch); None = uniform.
        backend: ``"ext"`` or ``"torch"``.

    Returns:
        R (B, 3, 3) proper rotations and t (B, 3) with ``R @ src_i + t ~ tgt_i``.

    Precision (fuzz suite, against float64): R is orthonormal to ~64 ulps with det +1, and the
    weighted cost it reaches is the minimum to within ~1e3 ulps of the squared extent of the
    clouds; degenerate inputs (collinear, coincident) return one of their minimisers. Weights are
    scale-free (any positive scale up to the dtype's maximum gives the same result).
    """
    src, tgt, weights = (promote_low_precision(t) for t in (src, tgt, weights))
    _validate(src, tgt, weights)
    if use_extension(backend, src.device):
        if weights is None:
            weights = torch.ones(src.shape[:2], dtype=src.dtype, device=src.device)
        return torch.ops.vrnet_ext.kabsch(src, tgt, weights)
    with float32_region(src):
        return kabsch_reference(src, tgt, weights)


def _validate_robust(iterations: int, kernel: str, scale: float, min_scale: float) -> None:
    if isinstance(iterations, bool) or not isinstance(iterations, int) or not 0 <= iterations <= MAX_ROBUST_ITERATIONS:
        raise ValueError(f"iterations must be an integer in [0, {MAX_ROBUST_ITERATIONS}], got {iterations!r}")
    if kernel not in ROBUST_KERNELS:
        raise ValueError(f"kernel must be one of {ROBUST_KERNELS}, got {kernel!r}")
    for name, value in (("scale", scale), ("min_scale", min_scale)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def reweighting_steps(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None, iterations: int,
                      kernel: str, scale: float, min_scale: float, backend: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The steps of :func:`robust_kabsch` as tensor ops around :func:`kabsch` (differentiable)."""
    R, t = kabsch(src, tgt, weights, backend=backend)
    base = torch.ones(src.shape[:2], dtype=torch.float64, device=src.device) if weights is None else weights.double()
    for _ in range(iterations):
        residual = (src.double() @ R.double().mT + t.double().unsqueeze(1) - tgt.double()).norm(dim=-1)
        pair_scale = (scale * residual.median(dim=1, keepdim=True).values).clamp_min(min_scale)
        step = base * robust_weights(kernel, residual / pair_scale)
        largest = step.amax(dim=1, keepdim=True)
        alive = largest > 0
        step = torch.where(alive, step / largest.clamp_min(torch.finfo(torch.float64).tiny), base)
        R_next, t_next = kabsch(src, tgt, step.to(src.dtype), backend=backend)
        R, t = torch.where(alive.unsqueeze(-1), R_next, R), torch.where(alive, t_next, t)
    return R, t


def robust_kabsch_reference(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None,
                            iterations: int = 3, kernel: str = "cauchy", scale: float = 3.0,
                            min_scale: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Pure PyTorch: :func:`kabsch_reference` and its reweighting steps as tensor ops."""
    src, tgt, weights = (promote_low_precision(t) for t in (src, tgt, weights))
    _validate(src, tgt, weights)
    _validate_robust(iterations, kernel, scale, min_scale)
    return reweighting_steps(src, tgt, weights, iterations, kernel, scale, min_scale, "torch")


def robust_kabsch(src: torch.Tensor, tgt: torch.Tensor, weights: torch.Tensor | None = None, iterations: int = 3,
                  kernel: str = "cauchy", scale: float = 3.0, min_scale: float = 1e-3,
                  backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted Procrustes, then ``iterations`` robust reweighting steps (IRLS).

    Step k: r_i = |R x_i + t - y_i| under the current estimate, s = max(``scale`` x the pair's median
    r_i (the lower median), ``min_scale``); the weights become ``weights`` x w(r_i / s) with w the
    robust weight of ``kernel`` (:func:`robust_weights`), computed in float64; the problem is solved
    again. Correspondences far off the consensus of the rest lose their say. A pair whose weights
    all vanish (Welsch far in its tail) keeps its estimate.

    Args:
        src, tgt, weights, backend: as :func:`kabsch`.
        iterations: reweighting steps, 0 to :data:`MAX_ROBUST_ITERATIONS` (0: :func:`kabsch`).
        kernel: one of :data:`ROBUST_KERNELS`.
        scale: the scale in medians of the pair's residuals (> 0).
        min_scale: the smallest scale, in the units of the points (> 0).

    Returns:
        R (B, 3, 3) and t (B, 3) with ``R @ src_i + t ~ tgt_i``. Differentiable (through the
        ``kabsch`` steps; the compiled single-pass kernel runs where no gradient is needed).
    """
    src, tgt, weights = (promote_low_precision(t) for t in (src, tgt, weights))
    _validate(src, tgt, weights)
    _validate_robust(iterations, kernel, scale, min_scale)
    needs_grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (src, tgt, weights))
    if use_extension(backend, src.device) and not needs_grad:
        if weights is None:
            weights = torch.ones(src.shape[:2], dtype=src.dtype, device=src.device)
        return torch.ops.vrnet_ext.robust_kabsch(src, tgt, weights, iterations, kernel, float(scale), float(min_scale))
    return reweighting_steps(src, tgt, weights, iterations, kernel, scale, min_scale, backend)


if has_extension():

    @torch.library.register_fake("vrnet_ext::kabsch")
    def _kabsch_fake(src, tgt, weights):
        return src.new_empty((src.shape[0], 3, 3)), src.new_empty((src.shape[0], 3))

    @torch.library.register_fake("vrnet_ext::robust_kabsch")
    def _robust_kabsch_fake(src, tgt, weights, iterations, kernel, scale, min_scale):
        return src.new_empty((src.shape[0], 3, 3)), src.new_empty((src.shape[0], 3))

    @torch.library.register_fake("vrnet_ext::kabsch_backward")
    def _kabsch_backward_fake(grad_R, grad_t, src, tgt, weights):
        return torch.empty_like(src), torch.empty_like(tgt), torch.empty_like(weights)

    def _kabsch_setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs)

    def _kabsch_backward(ctx, grad_R, grad_t):
        src, tgt, weights = ctx.saved_tensors
        first_order_only("kabsch", grad_R, grad_t, src, tgt, weights)
        return torch.ops.vrnet_ext.kabsch_backward(grad_R, grad_t, src, tgt, weights)

    torch.library.register_autograd("vrnet_ext::kabsch", _kabsch_backward, setup_context=_kabsch_setup_context)
