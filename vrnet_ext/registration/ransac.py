"""Global registration without an initial estimate: FPFH features matched across the scans, then
RANSAC over the matches (the recipe of Open3D's ``registration_ransac_based_on_feature_matching``
and of PCL's FPFH), built on this package's ops: ``ops.knn`` for neighbourhoods and for matching
33-d features, ``ops.normals`` and ``ops.fpfh`` for the descriptors, one batched ``ops.kabsch``
call per round of hypotheses.

Choices (documented, not tuned per dataset): normals from the 30 nearest neighbours, turned towards
``viewpoint`` (the sensor: the origin of a 3DMatch fragment or a LiDAR scan); neighbourhoods of at
most ``max_neighbours`` points within the radius; FPFH as in Rusu et al. 2009, in Open3D's layout
(:func:`vrnet_ext.ops.fpfh`); mutual nearest-neighbour matches;
hypotheses from 3 matches whose pairwise distances agree within 10 % (Open3D's edge-length check),
scored by the number of matches within ``inlier_distance``; the best one refined by Kabsch on its
inliers.
"""
from __future__ import annotations

import math

import torch

from vrnet_ext import ops
from vrnet_ext.geometry.features import mutual_matches, voxel_fpfh
from vrnet_ext.geometry.transforms import move


def _enough_hypotheses(inlier_ratio: float, confidence: float) -> float:
    """Hypotheses after which one all-inlier sample of 3 was drawn with probability ``confidence``."""
    all_inliers = inlier_ratio ** 3
    if confidence >= 1.0 or all_inliers <= 0.0:
        return math.inf
    if all_inliers >= 1.0:
        return 0.0
    return math.log(1.0 - confidence) / math.log(1.0 - all_inliers)


HYPOTHESES = 1_000_000  # enough for 3 % inliers: log(0.001) / log(1 - 0.03^3) = 256,000 hypotheses
SCORED_AT_ONCE = 1 << 18  # hypothesis x match residuals scored at a time
# The scoring's transient, in MB: the moved matches and their offsets (float64 x 3 each) and the residuals.
SCORING_MB = SCORED_AT_ONCE * (3 * 8 + 3 * 8 + 8) / 2 ** 20


def ransac(src: torch.Tensor, tgt: torch.Tensor, matches: torch.Tensor, inlier_distance: float, *,
           iterations: int = HYPOTHESES, confidence: float = 0.999, batch: int = 8192,
           seed: int = 0) -> tuple[torch.Tensor, int]:
    """Rigid transform from putative matches (C, 2) between src (N, 3) and tgt (M, 3).

    Up to ``iterations`` hypotheses from 3 random matches each, ``batch`` at a time (one Kabsch
    call per batch for those passing the edge-length check), stopping early as Open3D's RANSAC does
    once the best inlier ratio w says an all-inlier sample has been drawn with probability
    ``confidence`` (after log(1 - confidence) / log(1 - w^3) hypotheses; 1.0 never stops early).
    The cap matters on low-overlap scans, where 2-4 % of FPFH matches are right: the early stop
    ends easy pairs after a few thousand hypotheses. Returns (4x4 transform refined on the best
    hypothesis' inliers, its inlier count).
    """
    if matches.shape[0] < 3:
        raise ValueError(f"matches: RANSAC needs at least 3 putative matches, got {matches.shape[0]}")
    if not 0.0 < confidence <= 1.0:
        raise ValueError(f"confidence must be in (0, 1], got {confidence}")
    generator = torch.Generator().manual_seed(seed)
    p, q = src[matches[:, 0]], tgt[matches[:, 1]]
    best_count, best = -1, None
    for start in range(0, iterations, batch):
        size = min(batch, iterations - start)
        pick = torch.randint(0, p.shape[0], (size, 3), generator=generator).to(p.device)
        hp, hq = p[pick], q[pick]
        edges_p, edges_q = torch.cdist(hp, hp), torch.cdist(hq, hq)
        agree = ((edges_p - edges_q).abs() <= 0.1 * torch.maximum(edges_p, edges_q)).flatten(1).all(1)
        agree &= edges_p[:, [0, 0, 1], [1, 2, 2]].amin(1) > inlier_distance  # no near-duplicate samples
        if not bool(agree.any()):
            continue
        R, t = ops.kabsch(hp[agree], hq[agree])
        chunk = max(1, SCORED_AT_ONCE // p.shape[0])
        for first in range(0, R.shape[0], chunk):
            residual = (move(p[None], R[first:first + chunk], t[first:first + chunk]) - q[None]).norm(dim=-1)  # (H, C)
            counts = (residual <= inlier_distance).sum(1)
            top = int(counts.argmax())
            if int(counts[top]) > best_count:
                best_count, best = int(counts[top]), residual[top] <= inlier_distance
        if start + size >= _enough_hypotheses(best_count / p.shape[0], confidence):
            break
    if best is None or best_count < 3:
        raise ValueError("RANSAC found no hypothesis with 3 or more inliers: the features do not match "
                         "(try another global_points)")
    R, t = ops.kabsch(p[best][None], q[best][None])
    transform = torch.eye(4, dtype=src.dtype, device=src.device)
    transform[:3, :3], transform[:3, 3] = R[0], t[0]
    return transform, best_count


def fpfh_ransac(src: torch.Tensor, tgt: torch.Tensor, voxel_size: float, iterations: int = HYPOTHESES,
                seed: int = 0) -> tuple[torch.Tensor, int]:
    """Initial estimate for two voxel-downsampled scans src (N, 3), tgt (M, 3) (same unit) ->
    (4x4 transform taking src onto tgt, RANSAC inlier count): :func:`voxel_fpfh` features,
    mutual matches, inliers within 1.5 voxels (Open3D's global registration tutorial)."""
    return feature_ransac(src, tgt, voxel_fpfh(src, voxel_size), voxel_fpfh(tgt, voxel_size), voxel_size,
                          iterations=iterations, seed=seed)


def feature_ransac(src: torch.Tensor, tgt: torch.Tensor, src_features: torch.Tensor, tgt_features: torch.Tensor,
                   voxel_size: float, *, iterations: int = HYPOTHESES, seed: int = 0) -> tuple[torch.Tensor, int]:
    """:func:`fpfh_ransac` with the descriptors (N, F), (M, F) already computed."""
    matches = mutual_matches(src_features, tgt_features)
    return ransac(src, tgt, matches, 1.5 * voxel_size, iterations=iterations, seed=seed)
