"""Fast Global Registration (Zhou, Park & Koltun, ECCV 2016) on this package's ops.

No sampling: one robust objective over feature correspondences, optimised by Gauss-Newton with
graduated non-convexity.

1. Correspondences: each source point's nearest target descriptor and each target point's nearest
   source descriptor (``ops.knn`` in the 33-d FPFH space), pooled.
2. Tuple test: random triples of correspondences are kept when every edge length agrees between
   the two scans within ``tuple_scale`` (0.95); up to ``max_tuples`` (1000) triples are drawn from
   at most 100 attempts per correspondence, in one vectorised batch per round.
3. Both scans are centred and scaled by the same factor (the largest distance from the centroids),
   then sum_i rho(|T x_i - y_i|) with the scaled Geman-McClure penalty rho(r) = mu r^2 / (mu + r^2)
   is minimised by reweighted Gauss-Newton: weights (mu / (mu + r^2))^2 (the line process), one
   step per iteration, mu divided by 1.4 every 4 iterations while it exceeds ``max_distance``
   (0.025 of the scale), ``iterations`` (64) in all.

Options and defaults are those of the authors' code and Open3D's ``FastGlobalRegistrationOption``.
"""
from __future__ import annotations

import math

import torch

from vrnet_ext.geometry.features import nearest_both_ways
from vrnet_ext.ops.kabsch import robust_weights
from vrnet_ext.geometry.lie import skew
from vrnet_ext.registration.icp_steps import gauss_newton_step
from vrnet_ext.geometry.transforms import apply, from_normalised


def feature_correspondences(src_features: torch.Tensor, tgt_features: torch.Tensor) -> torch.Tensor:
    """(N, F), (M, F) descriptors -> (C, 2) unique (source, target) pairs: nearest in both directions."""
    forward, backward = nearest_both_ways(src_features, tgt_features)
    src_idx = torch.arange(src_features.shape[0], device=src_features.device)
    tgt_idx = torch.arange(tgt_features.shape[0], device=src_features.device)
    pairs = torch.cat([torch.stack([src_idx, forward], 1), torch.stack([backward, tgt_idx], 1)])
    return torch.unique(pairs, dim=0)


def tuple_test(src: torch.Tensor, tgt: torch.Tensor, pairs: torch.Tensor, tuple_scale: float = 0.95,
               max_tuples: int = 1000, generator: torch.Generator | None = None) -> torch.Tensor:
    """Correspondences (C, 2) -> those of up to ``max_tuples`` random triples whose three edge
    lengths agree between src and tgt within the ratio ``tuple_scale`` (all of them when fewer
    than 3 pairs pass)."""
    count = pairs.shape[0]
    if count < 3:
        return pairs
    attempts = 100 * count
    picked = []
    for start in range(0, attempts, 65536):
        draw = torch.randint(0, count, (min(65536, attempts - start), 3), generator=generator).to(pairs.device)
        p, q = src[pairs[draw, 0]], tgt[pairs[draw, 1]]  # (T, 3, 3)
        edges_p = (p - p.roll(1, dims=1)).norm(dim=-1)
        edges_q = (q - q.roll(1, dims=1)).norm(dim=-1)
        ratio = edges_p / edges_q.clamp_min(1e-12)
        ok = ((ratio > tuple_scale) & (ratio < 1 / tuple_scale)).all(1)
        picked.append(draw[ok])
        if sum(len(x) for x in picked) >= max_tuples:
            break
    tuples = torch.cat(picked)[:max_tuples]
    if len(tuples) == 0:
        return pairs
    return pairs[tuples.reshape(-1)]


def fast_global_registration(src: torch.Tensor, tgt: torch.Tensor, src_features: torch.Tensor,
                             tgt_features: torch.Tensor, *, max_distance: float = 0.025, iterations: int = 64,
                             division_factor: float = 1.4, tuple_scale: float = 0.95, max_tuples: int = 1000,
                             seed: int = 0) -> torch.Tensor:
    """src (N, 3), tgt (M, 3) float64 with descriptors (N | M, F) -> (4, 4) T_target_source."""
    if src.shape[0] < 3 or tgt.shape[0] < 3:
        raise ValueError(f"src and tgt need at least 3 points each, got {src.shape[0]} and {tgt.shape[0]}")
    generator = torch.Generator().manual_seed(seed)
    pairs = tuple_test(src, tgt, feature_correspondences(src_features, tgt_features), tuple_scale, max_tuples,
                       generator)
    src_centre, tgt_centre = src.mean(0), tgt.mean(0)
    scale = torch.maximum((src - src_centre).norm(dim=1).max(), (tgt - tgt_centre).norm(dim=1).max()).clamp_min(1e-12)
    x = (src[pairs[:, 0]] - src_centre) / scale
    y = (tgt[pairs[:, 1]] - tgt_centre) / scale
    T = torch.eye(4, dtype=src.dtype, device=src.device)
    mu = 1.0
    eye = torch.eye(3, dtype=src.dtype, device=src.device).expand(len(x), 3, 3)
    for iteration in range(iterations):
        if iteration % 4 == 0 and mu > max_distance:
            mu /= division_factor
        moved = apply(T, x)
        residual = moved - y
        weights = robust_weights("geman_mcclure", residual.norm(dim=-1) / math.sqrt(mu))  # (mu / (mu + r^2))^2
        J = torch.cat([-skew(moved), eye], -1)  # (C, 3, 6)
        T = gauss_newton_step(J, residual, weights, T)
    R, t = from_normalised(T[:3, :3], T[:3, 3], src_centre, tgt_centre, scale)
    out = torch.eye(4, dtype=src.dtype, device=src.device)
    out[:3, :3], out[:3, 3] = R, t
    return out
