"""How near an estimate brings two clouds, and a robust point-to-point ICP that brings them nearer.

Batched over pairs: src (B, N, 3), tgt (B, M, 3), an estimate R (B, 3, 3), t (B, 3) with
R src + t ~ tgt (:mod:`vrnet_ext.geometry.transforms`). Neither needs correspondences: each moved
source point is compared with its nearest target point.
"""
from __future__ import annotations

import torch

from vrnet_ext.geometry.transforms import move
from vrnet_ext.ops import knn, robust_kabsch

ICP_KERNEL = "cauchy"  # robust_icp: the robust weight of a nearest-point residual
ICP_SCALE = 1.0        # robust_icp: its scale, in medians of the pair's nearest-point distances
ICP_REWEIGHTING = 3    # robust_icp: reweighting steps of each Procrustes solve


def nearest_median(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
                   backend: str = "ext") -> torch.Tensor:
    """(B,) the median distance from each point of R src + t to its nearest target point: how close
    an estimate brings the clouds, whatever correspondences say (robust to up to half the source
    without a counterpart). ``backend``: that of :func:`vrnet_ext.ops.knn`."""
    with torch.autocast(src.device.type, enabled=False):
        moved = move(src, rotation, translation).contiguous()
    dist2, _ = knn(moved, tgt.to(moved.dtype).contiguous(), 1, backend=backend)
    return dist2[..., 0].median(dim=1).values.sqrt()


def robust_icp(src: torch.Tensor, tgt: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor,
               steps: int, backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor]:
    """``steps`` steps of robust point-to-point ICP from (R, t), every pair at once: each step pairs
    every moved source point with its nearest target point and solves a Procrustes on those pairs
    followed by :data:`ICP_REWEIGHTING` reweighting steps (:func:`vrnet_ext.ops.robust_kabsch`:
    :data:`ICP_KERNEL` weights at :data:`ICP_SCALE` x the pair's median residual), so that the
    source points without a counterpart (a partial view's cut, noise) lose their say.

    ICP converges to the nearest local minimum: it polishes an estimate that is nearly right (a few
    degrees off), and does not rescue one that is far off. Returns R (B, 3, 3), t (B, 3) in src's dtype.
    ``backend``: that of the ops (:func:`vrnet_ext.ops.knn`, :func:`vrnet_ext.ops.robust_kabsch`).
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    with torch.autocast(src.device.type, enabled=False):
        src, tgt = src.contiguous(), tgt.to(src.dtype).contiguous()
        for _ in range(steps):
            moved = move(src, rotation, translation).contiguous()
            _, nearest = knn(moved, tgt, 1, backend=backend)
            matched = tgt.gather(1, nearest.expand(-1, -1, 3))
            rotation, translation = robust_kabsch(src, matched, None, iterations=ICP_REWEIGHTING, kernel=ICP_KERNEL,
                                                  scale=ICP_SCALE, backend=backend)
    return rotation, translation
