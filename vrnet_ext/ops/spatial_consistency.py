"""Robust rigid fit by spatial consistency: ``T, inliers = ops.spatial_consistency(src, tgt, tol, thr)``.

Putative correspondences (p_i, q_i) (rows of ``src`` and ``tgt``, (K, 3)) are compatible when the
distances they span agree: ``| |p_i - p_j| - |q_i - q_j| | < tolerance``. The inliers of the true
motion are compatible with each other; outliers rarely are. Following SC^2-PCR (Chen et al.,
CVPR 2022):

1. the compatibility graph (K x K bits; decided in float32 when the points span at most
   ``FLOAT_GRAPH_EXTENT`` tolerances, which moves its boundary by under 1 % of the tolerance,
   else in float64);
2. ``seeds`` correspondences of highest degree, none within ``tolerance`` of another on the source
   side;
3. for each seed, the second-order score of each compatible j (how many correspondences are
   compatible with both) picks its ``consensus`` best neighbours; a Kabsch fit on the seed and
   those scores the correspondences it maps within ``inlier_threshold``;
4. the best fit (most inliers; ties: the earlier seed, in order of degree) is refitted on its
   inliers while they grow.

Identical correspondences count once (copies would support each other and capture the fit;
each copy gets its original's inlier flag). Returns the (4, 4) float64 transform taking ``src``
onto ``tgt`` and the (K,) bool inlier mask, both on the inputs' device (no inliers when no fit
has 3). Deterministic; not differentiable. The compiled op keeps the graph as a bitset (K^2 / 8
bytes; at most 32,768 correspondences), on the CPU and, for CUDA tensors, on the GPU, where every
step runs on the device (the graph, the seeds and each seed's fit are the CPU op's; the final
refits sum in another order, so the transform may differ from the CPU's in its last bits); the
reference builds dense matrices on the CPU (for tests).
"""
from __future__ import annotations

import math

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import check_finite, check_tensor
from vrnet_ext.ops.kabsch import kabsch_reference

MAX_CORRESPONDENCES = 1 << 15
FLOAT_GRAPH_EXTENT = 128  # the compiled op's kFloatGraphExtent
# One number per correspondence (K, 6) @ ROW_KEY: copies get equal keys, so K distinct keys mean no
# copies; distinct rows rarely share one (then the full row comparison decides).
ROW_KEY = torch.tensor([1.0, math.pi, math.e, math.sqrt(2.0), math.sqrt(3.0), math.sqrt(5.0)], dtype=torch.float64)


def _validate(src: torch.Tensor, tgt: torch.Tensor, tolerance: float, inlier_threshold: float, seeds: int,
              consensus: int) -> None:
    for name, t in (("src", src), ("tgt", tgt)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if not t.is_floating_point():
            raise TypeError(f"{name} must be a floating tensor, got {t.dtype}")
        check_tensor(t, name)
    if src.dim() != 2 or src.shape[1] != 3:
        raise ValueError(f"src must have shape (K, 3), got {tuple(src.shape)}")
    if tgt.shape != src.shape:
        raise ValueError(f"tgt must have the shape of src {tuple(src.shape)}, got {tuple(tgt.shape)}")
    if not 3 <= src.shape[0] <= MAX_CORRESPONDENCES:
        raise ValueError(f"src must hold 3 to {MAX_CORRESPONDENCES} correspondences, got {src.shape[0]}")
    for name, value in (("tolerance", tolerance), ("inlier_threshold", inlier_threshold)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    for name, value, smallest in (("seeds", seeds, 1), ("consensus", consensus, 2)):
        if isinstance(value, bool) or not isinstance(value, int) or value < smallest:
            raise ValueError(f"{name} must be an integer >= {smallest}, got {value!r}")


def _kabsch(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Unweighted Procrustes (the kabsch op's reference) -> (4, 4) float64."""
    R, t = kabsch_reference(p[None], q[None])
    T = torch.eye(4, dtype=p.dtype)
    T[:3, :3], T[:3, 3] = R[0], t[0]
    return T


def _inliers(T: torch.Tensor, p: torch.Tensor, q: torch.Tensor, threshold: float) -> torch.Tensor:
    return ((p @ T[:3, :3].T + T[:3, 3] - q).square().sum(1) < threshold * threshold)


def _squared_distances(x: torch.Tensor) -> torch.Tensor:
    """(K, 3) -> (K, K): [i, j] = |x_j - x_i|^2, summed x, y, z in that order (as the compiled op)."""
    d = x[None] - x[:, None]
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def _compatibility(p: torch.Tensor, q: torch.Tensor, tolerance: float) -> torch.Tensor:
    """(K, K) bool: | |p_i - p_j| - |q_i - q_j| | < tolerance, decided as the compiled op decides it:
    without square roots, in float32 on coordinates relative to the first correspondence when the
    points span at most FLOAT_GRAPH_EXTENT tolerances, else in float64; False on the diagonal."""
    extent = float(torch.cat([p.amax(0) - p.amin(0), q.amax(0) - q.amin(0)]).max())
    dtype = torch.float32 if extent <= FLOAT_GRAPH_EXTENT * tolerance else torch.float64
    if dtype == torch.float32:
        p, q = (p - p[0]).float(), (q - q[0]).float()
    a, b = _squared_distances(p), _squared_distances(q)
    s = a + b - torch.tensor(tolerance * tolerance, dtype=dtype)
    compatible = (s < 0) | (s * s < 4 * a * b)
    compatible.fill_diagonal_(False)
    return compatible


def spatial_consistency_reference(src: torch.Tensor, tgt: torch.Tensor, tolerance: float, inlier_threshold: float,
                                  seeds: int = 100, consensus: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """Pure PyTorch, dense K x K matrices (the same steps and tie-breaking as the compiled op)."""
    p, q = src.double().cpu(), tgt.double().cpu()
    check_finite(p, "src")
    check_finite(q, "tgt")
    K = p.shape[0]
    compatible = _compatibility(p, q, tolerance)
    degree = compatible.sum(1)
    order = torch.sort(-degree, stable=True).indices
    chosen: list[int] = []
    for i in order.tolist():
        if len(chosen) >= seeds or int(degree[i]) < 2:
            break
        if all(float((p[i] - p[s]).norm()) >= tolerance for s in chosen):
            chosen.append(i)
    best_T, best_count = torch.eye(4, dtype=torch.float64), -1
    for s in chosen:
        neighbours = compatible[s].nonzero().flatten()
        score = (compatible[neighbours] & compatible[s]).sum(1)
        keep = neighbours[torch.sort(-score, stable=True).indices[:consensus]]
        members = torch.cat([torch.tensor([s]), keep])
        if members.numel() < 3:
            continue
        T = _kabsch(p[members], q[members])
        count = int(_inliers(T, p, q, inlier_threshold).sum())
        if count > best_count:
            best_T, best_count = T, count
    mask = _inliers(best_T, p, q, inlier_threshold) if best_count >= 3 else torch.zeros(K, dtype=torch.bool)
    for _ in range(10):
        if int(mask.sum()) < 3:
            break
        T = _kabsch(p[mask], q[mask])
        grown = _inliers(T, p, q, inlier_threshold)
        if int(grown.sum()) < int(mask.sum()):
            break
        same = bool(torch.equal(grown, mask))
        best_T, mask = T, grown
        if same:
            break
    return best_T, mask


def spatial_consistency(src: torch.Tensor, tgt: torch.Tensor, tolerance: float, inlier_threshold: float,
                        seeds: int = 100, consensus: int = 30,
                        backend: str = "ext") -> tuple[torch.Tensor, torch.Tensor]:
    """src, tgt (K, 3): putative correspondences -> ((4, 4) float64 transform, (K,) bool inliers).

    tolerance: how much the distances spanned by two correspondences may differ for them to be
    compatible; inlier_threshold: the residual within which a correspondence counts as an inlier
    (both in the points' unit); seeds: at most this many fits; consensus: neighbours per fit.
    """
    _validate(src, tgt, tolerance, inlier_threshold, seeds, consensus)
    rows = torch.cat([src.detach(), tgt.detach()], 1).double()
    if len(torch.unique(rows @ ROW_KEY.to(rows.device))) < len(rows):  # equal keys: compare the rows themselves
        first, inverse = _first_occurrences(rows)
        if len(first) < 3:  # copies of one or two correspondences: no fit
            return (torch.eye(4, dtype=torch.float64, device=rows.device),
                    torch.zeros(len(rows), dtype=torch.bool, device=rows.device))
        if len(first) < len(rows):
            T, inliers = _fit(rows[first, :3], rows[first, 3:], backend, tolerance, inlier_threshold, seeds, consensus)
            return T, inliers[inverse]
    return _fit(rows[:, :3], rows[:, 3:], backend, tolerance, inlier_threshold, seeds, consensus)


def _first_occurrences(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """rows (K, 6) -> (the index of each distinct row's first occurrence, in their order (U,); for each
    row, its distinct row's position in that list (K,)). Copies of a correspondence are one
    correspondence: counted as many, they would be each other's support and capture the fit."""
    _, inverse = torch.unique(rows, dim=0, return_inverse=True)
    indices = torch.arange(len(rows), device=rows.device)
    first = torch.full((int(inverse.max()) + 1,), len(rows), dtype=torch.long, device=rows.device)
    first.scatter_reduce_(0, inverse, indices, reduce="amin")
    order = torch.argsort(first)
    position = torch.empty_like(order)
    position[order] = indices[:len(order)]
    return first[order], position[inverse]


def _fit(p: torch.Tensor, q: torch.Tensor, backend: str, tolerance: float, inlier_threshold: float, seeds: int,
         consensus: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The op on distinct correspondences p, q (K, 3) float64, on their device."""
    if use_extension(backend, p.device):
        return torch.ops.vrnet_ext.spatial_consistency(p.contiguous(), q.contiguous(), float(tolerance),
                                                       float(inlier_threshold), int(seeds), int(consensus))
    T, inliers = spatial_consistency_reference(p, q, float(tolerance), float(inlier_threshold), int(seeds),
                                               int(consensus))
    return T.to(p.device), inliers.to(p.device)


if has_extension():

    @torch.library.register_fake("vrnet_ext::spatial_consistency")
    def _spatial_consistency_fake(src, tgt, tolerance, inlier_threshold, seeds, consensus):
        return src.new_empty((4, 4)), src.new_empty((src.shape[0],), dtype=torch.bool)
