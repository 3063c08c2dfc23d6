"""Fast Point Feature Histograms: ``features = ops.fpfh(points, normals, radius)`` -> (N, 33).

Rusu et al. 2009, in Open3D's layout (``open3d.pipelines.registration.compute_fpfh_feature`` with
the same radius and neighbour cap gives the same bins): the SPFH of each point over the other points
within ``radius`` (at most ``max_neighbours`` neighbours; duplicates of the point are skipped) is
three 11-bin histograms of the Darboux-frame angles (theta in [-pi, pi], alpha and phi in [-1, 1]),
each scaled to sum 100; then FPFH_i = SPFH_i + the neighbours' SPFH weighted by 1 / distance^2 and
scaled to sum 100 per block, so each block of the result sums 200. The frame sits on the point whose
normal is closer to the joining line d (near-ties keep the order), with v = d x u and w = u x v; a
normal along d gives the angles (0, 0, 0). Unit-free: scaling points and radius together leaves the
features unchanged. Normals must be unit vectors. Not differentiable.
"""
from __future__ import annotations

import math

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_finite, check_float, check_same, check_shape, float32_region, \
    promote_low_precision
from vrnet_ext.ops.normals import neighbourhood

BINS = 11


def _pair_features(p_s: torch.Tensor, n_s: torch.Tensor, p_t: torch.Tensor, n_t: torch.Tensor) -> torch.Tensor:
    """The Darboux-frame angles of points p_s (n, 1, 3) with normals n_s and their neighbours
    p_t (n, K, 3) with normals n_t -> (n, K, 3) (theta, alpha, phi); pairs at distance 0 give
    undefined values (the callers skip them)."""
    delta = p_t - p_s
    direction = delta / delta.norm(dim=-1, keepdim=True)
    swap = ((n_s * direction).sum(-1).abs() < (n_t * direction).sum(-1).abs() - 1e-9).unsqueeze(-1)
    u = torch.where(swap, n_t, n_s)
    other = torch.where(swap, n_s, n_t)
    direction = torch.where(swap, -direction, direction)
    v = torch.linalg.cross(direction, u)
    v_length = v.norm(dim=-1, keepdim=True)
    v = torch.where(v_length > 0, v / v_length, torch.zeros_like(v))
    w = torch.linalg.cross(u, v)
    theta = torch.atan2((w * other).sum(-1), (u * other).sum(-1))
    alpha = (v * other).sum(-1)
    phi = torch.where(v_length.squeeze(-1) > 0, (u * direction).sum(-1), torch.zeros_like(alpha))
    return torch.stack([theta, alpha, phi], dim=-1)


def _scale_each_histogram(counts: torch.Tensor) -> torch.Tensor:
    """Each 11-bin block of ``counts`` (N, 33) scaled to sum 100 (an empty block stays 0)."""
    parts = counts.view(-1, 3, BINS)
    sums = parts.sum(-1, keepdim=True)
    return torch.where(sums > 0, parts * 100.0 / torch.where(sums > 0, sums, 1.0), parts).view(-1, 3 * BINS)


def _histograms(angles: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """angles (N, K, 3), valid (N, K) -> (N, 33) scaled histograms (zeros without a valid neighbour)."""
    lows = angles.new_tensor([-math.pi, -1.0, -1.0])
    spans = angles.new_tensor([2 * math.pi, 2.0, 2.0])
    angles = torch.where(valid.unsqueeze(-1), angles, torch.zeros_like(angles))
    bins = ((angles - lows) / spans * BINS).floor().long().clamp(0, BINS - 1)
    bins = bins + torch.arange(3, device=angles.device) * BINS
    counts = angles.new_zeros(angles.shape[0], 3 * BINS)
    counts.scatter_add_(1, bins.flatten(1), valid.unsqueeze(-1).expand_as(bins).flatten(1).to(angles.dtype))
    return _scale_each_histogram(counts)


def fpfh_reference(points: torch.Tensor, normals: torch.Tensor, idx: torch.Tensor, dist2: torch.Tensor,
                   radius: float) -> torch.Tensor:
    """Pure PyTorch, 2048 points at a time (memory O(N * k))."""
    valid = (dist2 <= radius * radius) & (dist2 > 0)
    spfh = torch.cat([_histograms(_pair_features(points[rows, None], normals[rows, None], points[idx[rows]],
                                                 normals[idx[rows]]), valid[rows])
                      for rows in torch.arange(points.shape[0], device=points.device).split(2048)])
    nearest = torch.where(valid, dist2, torch.full_like(dist2, math.inf)).amin(1, keepdim=True)
    weights = torch.where(valid, nearest / torch.where(valid, dist2, 1.0), torch.zeros_like(dist2))
    neighbourhood_sum = torch.zeros_like(spfh)
    for slot in range(idx.shape[1]):
        neighbourhood_sum.addcmul_(weights[:, slot, None], spfh[idx[:, slot]])
    return spfh + _scale_each_histogram(neighbourhood_sum)


UNIT_TOLERANCE = 1e-2  # a normal's length may differ from 1 by this much (float16 round trips)


def _check_unit(normals: torch.Tensor) -> None:
    """ValueError unless every row of ``normals`` (N, 3) has length 1 (within UNIT_TOLERANCE): the
    angles of the features assume unit normals, and a zero one has no direction."""
    lengths = torch.linalg.vector_norm(normals.detach().double(), dim=1)
    bad = (lengths - 1.0).abs() > UNIT_TOLERANCE
    if bool(bad.any()):
        row = int(torch.nonzero(bad)[0])
        raise ValueError(f"normals must be unit vectors: {int(bad.sum())} of {len(normals)} are not (first: row "
                         f"{row}, length {float(lengths[row]):.3g})")


def fpfh(points: torch.Tensor, normals: torch.Tensor, radius: float, max_neighbours: int = 100,
         backend: str = "ext") -> torch.Tensor:
    """points, normals (N, 3) -> FPFH (N, 33) over neighbours within ``radius`` (see the module)."""
    points, normals = promote_low_precision(points), promote_low_precision(normals)
    check_float(points, "points")
    check_float(normals, "normals")
    check_shape(points, "points", 2, "(N, 3)", last=3)
    check_shape(normals, "normals", 2, "(N, 3)", last=3)
    check_same({"points": points, "normals": normals})
    if normals.shape != points.shape:
        raise ValueError(f"normals must have the shape of points {tuple(points.shape)}, got {tuple(normals.shape)}")
    if isinstance(radius, bool) or not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a finite number > 0, got {radius!r}")
    if isinstance(max_neighbours, bool) or not isinstance(max_neighbours, int) or max_neighbours < 2:
        raise ValueError(f"max_neighbours must be an integer >= 2, got {max_neighbours!r}")
    check_finite(points, "points")
    check_finite(normals, "normals")
    _check_unit(normals)
    dist2, idx = neighbourhood(points, max_neighbours)
    if use_extension(backend, points.device):
        return torch.ops.vrnet_ext.fpfh(points, normals, idx, dist2, float(radius))
    with float32_region(points):
        return fpfh_reference(points, normals, idx, dist2, float(radius))


if has_extension():

    @torch.library.register_fake("vrnet_ext::fpfh")
    def _fpfh_fake(points, normals, idx, dist2, radius):
        return points.new_empty((points.shape[0], 3 * BINS))
