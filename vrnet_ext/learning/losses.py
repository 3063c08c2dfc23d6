"""VRNet's hybrid loss (paper Sec. III-C): L0 for stage 1, L = l1 L1 + l2 L2 + l3 L3 + l4 L4 for stage 2.

With the walk's gate and confidence heads (``VRNetConfig.walk_gate`` / ``walk_confidence``, not
in the paper) stage 2 adds two binary cross-entropies: LG teaches the gate which VCPs lie farther
than ``correct_within`` from their true position (those need a correction), LC teaches the
confidence which RCPs lie within it (those should carry the Procrustes solve). ``motion`` > 0 adds
LM, the supervised motion loss of DCP (rmse(R^T R_gt, I) + rmse(t, t_gt) of the estimate the network
returns), which trains the confidences through the weighted Procrustes for what is measured.

``rmse(a, b) = sqrt(mean((a - b)^2))`` per pair, then averaged over the batch. Its square root is
taken of ``max(mean, 1e-20)`` so the gradient stays finite at a perfect fit.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F

from vrnet_ext.geometry.metrics import correspondence_error
from vrnet_ext.model.vrnet import VRNetOutput
from vrnet_ext.ops import kabsch, pairwise_distance_loss
from vrnet_ext.geometry.transforms import move


def rmse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, ...) pairs -> (B,) root mean squared difference over all but the batch dim."""
    return (a - b).square().flatten(1).mean(dim=1).clamp_min(1e-20).sqrt()


def correspondence_loss(matching: torch.Tensor, gt_idx: torch.Tensor) -> torch.Tensor:
    """L0 (Eq. 7): -sum_ij m_ij m^gt_ij / sum_ij m^gt_ij, from the index form of the ground truth.

    Args:
        matching: (B, N, M) soft matching.
        gt_idx: (B, N) int64 target row of each source point's counterpart, -1 for outliers.

    Returns:
        scalar: the batch mean (pairs without any inlier contribute 0).
    """
    inlier = gt_idx >= 0
    picked = matching.gather(2, gt_idx.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    per_pair = -(picked * inlier).sum(dim=1) / inlier.sum(dim=1).clamp_min(1)
    return per_pair.mean()


def local_motion_consensus_loss(src: torch.Tensor, rcp: torch.Tensor, rotation: torch.Tensor,
                                translation: torch.Tensor, *, groups: int = 10, subset_size: int = 32,
                                generator: torch.Generator | None = None, backend: str = "ext") -> torch.Tensor:
    """L1 (Eq. 8): mean over G random correspondence subsets of rmse(R_g^T R, I) + rmse(t_g, t).

    All B * G subset problems are solved by one batched ``ops.kabsch`` call.
    """
    B, N, _ = src.shape
    size = min(max(3, subset_size), N)
    scores = torch.rand(B, groups, N, generator=generator, device="cpu").to(src.device)
    subsets = scores.argsort(dim=-1)[..., :size].reshape(B, groups * size, 1).expand(-1, -1, 3)
    sub_src = src.gather(1, subsets).reshape(B * groups, size, 3)
    sub_rcp = rcp.gather(1, subsets).reshape(B * groups, size, 3)
    R_g, t_g = kabsch(sub_src, sub_rcp, backend=backend)
    return motion_difference(R_g, t_g, rotation.repeat_interleave(groups, dim=0),
                             translation.repeat_interleave(groups, dim=0)).mean()


def motion_difference(rotation: torch.Tensor, translation: torch.Tensor, other_rotation: torch.Tensor,
                      other_translation: torch.Tensor, translation_weight: float = 1.0) -> torch.Tensor:
    """(B, 3, 3), (B, 3) twice -> (B,) rmse(R^T R', I) + translation_weight rmse(t, t'): L1's term, and LM's
    against the truth."""
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(rotation)
    return rmse(rotation.mT @ other_rotation, eye) + translation_weight * rmse(translation, other_translation)


def offset_log_loss(rcp: torch.Tensor, truth: torch.Tensor, scale: float) -> torch.Tensor:
    """(B, N, 3) RCPs and true positions -> (B,) mean over points of log(1 + |rcp - truth| / scale).

    Unlike the paper's L4 (an RMSE, whose gradient is carried by the few far-off VCPs) every point
    counts alike: the walk is also taught to refine VCPs that are already nearly right, which is
    where the rotation comes from.
    """
    distance = (rcp - truth).square().sum(dim=-1).clamp_min(1e-20).sqrt()
    return torch.log1p(distance / scale).mean(dim=1)


@dataclass
class HybridLossWeights:
    """Weights and shape of the hybrid loss: L1-L4 as in the paper (``l4_form`` "rmse", the paper's
    L4, or "log", :func:`offset_log_loss` at ``l4_log_scale``), L2's ``groups`` of ``subset_size``
    points, and the walk's gate and confidence terms (``gate``, ``confidence``)."""

    l1: float = 1.0
    l2: float = 1.0
    l3: float = 1.0
    l4: float = 100.0
    l4_form: str = "rmse"  # "rmse": the paper's; "log": offset_log_loss
    groups: int = 10
    subset_size: int = 32
    gate: float = 1.0
    confidence: float = 1.0
    l4_log_scale: float = 0.01
    motion: float = 0.0  # weight of LM (not in the paper)
    motion_translation: float = 1.0  # weight of LM's translation term against its rotation term
    correct_within: float = 0.03  # a VCP / RCP this close to R_gt x + t_gt counts as correct (unit-sphere shapes)


def hybrid_loss(out: VRNetOutput, src: torch.Tensor, gt_rotation: torch.Tensor, gt_translation: torch.Tensor,
                weights: HybridLossWeights | None = None, *, generator: torch.Generator | None = None,
                backend: str = "ext") -> tuple[torch.Tensor, dict[str, float]]:
    """Stage-2 loss L (Eq. 12) [+ LM + LG + LC]. Returns (L, {"L1": .., "L2": .., "L3": .., "L4": .. [, "LM", "LG", "LC"]})."""
    w = weights or HybridLossWeights()
    l1 = local_motion_consensus_loss(src, out.rcp, out.rotation, out.translation, groups=w.groups,
                                     subset_size=w.subset_size, generator=generator, backend=backend)
    l2 = pairwise_distance_loss(src, out.rcp, backend=backend).mean()
    l3 = rmse(move(src, out.rotation, out.translation), out.rcp).mean()
    truth = move(src, gt_rotation, gt_translation)
    l4 = (rmse(truth - out.vcp, out.offset) if w.l4_form == "rmse"
          else offset_log_loss(out.rcp, truth, w.l4_log_scale)).mean()
    total = w.l1 * l1 + w.l2 * l2 + w.l3 * l3 + w.l4 * l4
    parts = {"L1": float(l1.detach()), "L2": float(l2.detach()), "L3": float(l3.detach()), "L4": float(l4.detach())}
    if w.motion > 0:
        lm = motion_difference(out.rotation, out.translation, gt_rotation, gt_translation,
                               w.motion_translation).mean()
        total = total + w.motion * lm
        parts["LM"] = float(lm.detach())
    if out.gate_logits is not None:
        needs_correction = correspondence_error(out.vcp.detach(), src, gt_rotation, gt_translation) > w.correct_within
        lg = F.binary_cross_entropy_with_logits(out.gate_logits.float(), needs_correction.float())
        total = total + w.gate * lg
        parts["LG"] = float(lg.detach())
    if out.confidence_logits is not None:
        correct = correspondence_error(out.rcp.detach(), src, gt_rotation, gt_translation) < w.correct_within
        lc = F.binary_cross_entropy_with_logits(out.confidence_logits.float(), correct.float())
        total = total + w.confidence * lc
        parts["LC"] = float(lc.detach())
    return total, parts
