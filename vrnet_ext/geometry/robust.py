"""Robust weights of residuals for reweighted least squares (the IRLS steps of VRNet's Procrustes
solve, FGR's line process)."""
from __future__ import annotations

import torch

ROBUST_KERNELS = ("cauchy", "geman_mcclure", "welsch")


def robust_weights(kernel: str, scaled_residual: torch.Tensor) -> torch.Tensor:
    """Weight w(u) of residuals in units of the scale (any shape): ``"cauchy"`` 1 / (1 + u^2),
    ``"geman_mcclure"`` 1 / (1 + u^2)^2, ``"welsch"`` exp(-u^2); all 1 at u = 0, each flatter for far
    residuals than the one before."""
    squared = scaled_residual.square()
    if kernel == "cauchy":
        return 1 / (1 + squared)
    if kernel == "geman_mcclure":
        return 1 / (1 + squared).square()
    if kernel == "welsch":
        return torch.exp(-squared)
    raise ValueError(f"kernel must be one of {ROBUST_KERNELS}, got {kernel!r}")
