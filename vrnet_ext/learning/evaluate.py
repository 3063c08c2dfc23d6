"""Evaluation of a VRNet on ModelNet40 pairs: the paper's table plus consistency metrics."""
from __future__ import annotations

import statistics
import time

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from vrnet_ext.learning.losses import correspondence_loss
from vrnet_ext.geometry.metrics import (chamfer_distance, correct_match_ratio, correspondence_error, euler_zyx_deg,
                               rotation_error_deg, summarize)
from vrnet_ext.geometry.transforms import move
from vrnet_ext.model import VRNet
from vrnet_ext.ops import kabsch, robust_kabsch

PAPER_COLUMNS = ("RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)")


def to_device(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


IRLS_STEPS = 3  # reweighting steps of the "+ IRLS" estimates of a model that has none of its own


def procrustes_estimates(src: torch.Tensor, out, backend: str,
                         config) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Every Procrustes estimate one forward pass offers, for the walk's ablation.

    ``VCP``: Kabsch on source <-> VCPs (DCP-v2); ``RCP``: on source <-> RCPs, unweighted (the paper's
    VRNet); with a confidence head also ``VCP weighted`` / ``RCP weighted`` (the confidences as
    weights). Each also ``+ IRLS``: followed by the reweightings of the model's ``config`` (its
    ``irls_kernel``, ``irls_scale``, ``irls_min_scale`` and ``irls_iterations``, or :data:`IRLS_STEPS`
    where that is 0; :func:`~vrnet_ext.ops.robust_kabsch`), so ``RCP weighted + IRLS`` is
    the model's own estimate when it solves on the RCPs.
    """
    points = {"VCP": (out.vcp, None), "RCP": (out.rcp, None)}
    weights = getattr(out, "weights", None)
    if weights is not None:
        points.update({"VCP weighted": (out.vcp, weights), "RCP weighted": (out.rcp, weights)})
    result = {}
    for name, (tgt, w) in points.items():
        result[name] = kabsch(src, tgt, w, backend=backend)
        result[f"{name} + IRLS"] = robust_kabsch(src, tgt, w, config.irls_iterations or IRLS_STEPS,
                                                 config.irls_kernel, config.irls_scale, config.irls_min_scale,
                                                 backend=backend)
    return result


@torch.no_grad()
def evaluate(model: VRNet, dataset: Dataset, *, batch_size: int = 16, device: str | torch.device = "cpu",
             backend: str | None = None, progress: bool = True, use_rcp: bool = True) -> dict:
    """Runs ``model`` over ``dataset`` and returns the metrics as a flat dict.

    The paper's columns and the isotropic errors describe the model's own estimate, or with
    ``use_rcp=False`` Kabsch on the VCPs (DCP-v2 behaviour, used to select a stage-1 model whose
    correction walk is still untrained). Every estimate of :func:`procrustes_estimates` is also reported as
    ``RMSE(R) [name]`` and ``RE mean [name]``, and the mean distance of VCPs and RCPs from the true
    correspondents over the source points that have one in the target (``inliers``, gt_idx >= 0)
    and over those that do not (``outliers``, only where there are any): what the correction walk
    gains or costs on each kind of point; ``consistency`` (the mean share of RCPs on the estimate) and
    ``second pass`` (the share of pairs whose estimate came from a second pass).
    """
    device = torch.device(device)
    model.eval()
    solver_backend = backend or model.config.backend
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False)
    preds_R, preds_t, gts_R, gts_t = [], [], [], []
    by_estimate: dict[str, list[torch.Tensor]] = {}
    extra: dict[str, list[float]] = {k: [] for k in ("L0", "CD(src,VCP)", "CD(src,RCP)", "CD(src,tgt)",
                                                     "match@0.15(VCP)", "match@0.15(RCP)", "consistency",
                                                     "second pass")}
    point_errors = {f"{name} error ({kind})": [0.0, 0] for name in ("VCP", "RCP") for kind in ("inliers", "outliers")}
    for batch in tqdm(loader, desc="eval", disable=not progress, leave=False):
        batch = to_device(batch, device)
        src, tgt, R_gt, t_gt = batch["src"], batch["tgt"], batch["rotation"], batch["translation"]
        out = model(src, tgt, backend=backend, return_matching=True)  # L0 needs the matrix
        solved = procrustes_estimates(src, out, solver_backend, model.config)
        for name, (R_est, _) in solved.items():
            by_estimate.setdefault(name, []).append(R_est.cpu())
        R, t = (out.rotation, out.translation) if use_rcp else solved["VCP"]
        inliers = batch["gt_idx"] >= 0
        for name, pts in (("VCP", out.vcp), ("RCP", out.rcp)):
            error = correspondence_error(pts, src, R_gt, t_gt)
            for kind, chosen in (("inliers", inliers), ("outliers", ~inliers)):
                point_errors[f"{name} error ({kind})"][0] += float(error[chosen].sum())
                point_errors[f"{name} error ({kind})"][1] += int(chosen.sum())
        preds_R.append(R.cpu()); preds_t.append(t.cpu()); gts_R.append(R_gt.cpu()); gts_t.append(t_gt.cpu())
        aligned = move(src, R_gt, t_gt)
        n = src.shape[0]
        extra["L0"] += [float(correspondence_loss(out.matching, batch["gt_idx"]))] * n
        for name, pts in (("VCP", out.vcp), ("RCP", out.rcp), ("tgt", tgt)):
            key = f"CD(src,{name})"
            extra[key] += chamfer_distance(aligned, pts).tolist()
        extra["match@0.15(VCP)"] += correct_match_ratio(out.vcp, src, R_gt, t_gt).tolist()
        extra["match@0.15(RCP)"] += correct_match_ratio(out.rcp, src, R_gt, t_gt).tolist()
        extra["consistency"] += out.consistency.tolist()
        extra["second pass"] += out.second_pass.float().tolist()
    gt_R = torch.cat(gts_R)
    result = summarize(torch.cat(preds_R).numpy(), gt_R.numpy(), torch.cat(preds_t).numpy(), torch.cat(gts_t).numpy())
    result.update({k: float(np.mean(v)) for k, v in extra.items()})
    result.update({k: total / count for k, (total, count) in point_errors.items() if count})
    for name, rotations in by_estimate.items():
        R_est = torch.cat(rotations)
        euler_error = euler_zyx_deg(R_est) - euler_zyx_deg(gt_R)
        result[f"RMSE(R) [{name}]"] = float(np.sqrt((euler_error ** 2).mean()))
        result[f"RE mean [{name}]"] = float(rotation_error_deg(R_est, gt_R).mean())
    result["pairs"] = len(dataset)
    return result


@torch.no_grad()
def time_inference(model: VRNet, dataset: Dataset, device: str | torch.device = "cpu", pairs: int = 5,
                   warmup: int = 2, backend: str | None = None) -> float:
    """Median seconds of one forward on a single pair (batch 1) after ``warmup`` runs."""
    device = torch.device(device)
    model.eval()
    times = []
    for i in range(warmup + pairs):
        item = dataset[i % len(dataset)]
        src, tgt = item["src"][None].to(device), item["tgt"][None].to(device)
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        model(src, tgt, backend=backend)
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= warmup:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def format_table(result: dict, title: str) -> str:
    """The paper's column layout (RMSE/MAE of Euler angles in degrees and of translation)."""
    head = f"{'':<28}" + "".join(f"{c:>12}" for c in PAPER_COLUMNS)
    row = f"{title:<28}" + "".join(f"{result[c]:>12.4f}" for c in PAPER_COLUMNS)
    rest = "\n".join(f"  {k:<30} {v:.6g}" for k, v in result.items() if k not in PAPER_COLUMNS)
    return f"{head}\n{row}\n{rest}"
