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
MULTISTART_POINTS = 128  # multistart_icp: source points (evenly strided) of every start's first steps
MULTISTART_FIRST = 10    # multistart_icp: robust_icp steps of every start on them
MULTISTART_KEEP = 16     # multistart_icp: the starts nearest after them, taken on
MULTISTART_LAST = 40     # multistart_icp: robust_icp steps of those on every source point
MULTISTART_BATCH = 2 ** 20  # multistart_icp: target points held at once (bounds its memory)


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


def multistart_icp(src: torch.Tensor, tgt: torch.Tensor, starts: torch.Tensor,
                   backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A global registration by :func:`robust_icp` alone: for each pair, ICP from every rotation of
    ``starts`` (S, 3, 3) (with the translation that puts the turned source's centroid on the
    target's), :data:`MULTISTART_FIRST` steps on :data:`MULTISTART_POINTS` of the source's points,
    then :data:`MULTISTART_LAST` steps on all of them from the :data:`MULTISTART_KEEP` starts that
    brought the source nearest the target; the nearest of those is each pair's result.

    ICP's reach from a start is a few tens of degrees (less on nearly round shapes, where it
    converges slowly along the axis), so ``starts`` should leave no motion farther than that from
    one of them (:func:`vrnet_ext.geometry.transforms.spread_rotations`). Cost per pair: S x
    MULTISTART_FIRST nearest-neighbour searches of the strided points, S of every point (the ranking)
    and MULTISTART_KEEP x (MULTISTART_LAST + 1) more. Returns R (B, 3, 3), t (B, 3) and their
    :func:`nearest_median` (B,), in src's dtype.
    """
    if starts.dim() != 3 or starts.shape[1:] != (3, 3) or not starts.shape[0]:
        raise ValueError(f"starts must be (S, 3, 3) rotations with S >= 1, got {tuple(starts.shape)}")
    if not src.shape[0]:
        return src.new_zeros(0, 3, 3), src.new_zeros(0, 3), src.new_zeros(0)
    count, points = starts.shape[0], src.shape[1]
    stride = max(1, points // MULTISTART_POINTS)
    keep = min(MULTISTART_KEEP, count)
    results = []
    with torch.autocast(src.device.type, enabled=False):
        starts = starts.to(src.dtype)
        per_batch = max(1, MULTISTART_BATCH // (count * tgt.shape[1]))
        for first in range(0, src.shape[0], per_batch):
            cloud, target = src[first:first + per_batch], tgt[first:first + per_batch].to(src.dtype)
            many = cloud.shape[0]
            turns = starts.repeat(many, 1, 1)  # (pairs x S, 3, 3), start fastest
            every_src = cloud.repeat_interleave(count, dim=0)
            every_tgt = target.repeat_interleave(count, dim=0)
            shift = every_tgt.mean(1) - (turns @ every_src.mean(1, keepdim=True).transpose(1, 2))[..., 0]
            rotation, translation = robust_icp(every_src[:, ::stride][:, :MULTISTART_POINTS], every_tgt, turns,
                                               shift, MULTISTART_FIRST, backend)
            distance = nearest_median(every_src, every_tgt, rotation, translation, backend).view(many, count)
            kept = (distance.topk(keep, dim=1, largest=False).indices
                    + torch.arange(many, device=src.device)[:, None] * count).flatten()
            rotation, translation = robust_icp(every_src[kept], every_tgt[kept], rotation[kept], translation[kept],
                                               MULTISTART_LAST, backend)
            distance = nearest_median(every_src[kept], every_tgt[kept], rotation, translation, backend).view(many, keep)
            best = distance.argmin(dim=1) + torch.arange(many, device=src.device) * keep
            results.append((rotation[best], translation[best], distance.flatten()[best]))
    rotation, translation, distance = (torch.cat(values) for values in zip(*results))
    return rotation, translation, distance
