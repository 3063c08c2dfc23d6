"""Registration metrics: the DCP Euler-angle RMSE/MAE and the scan-level RE/TE/recall family."""
from __future__ import annotations

import numpy as np
import torch

from vrnet_ext.ops import knn
from vrnet_ext.geometry.transforms import move


def euler_zyx_deg(rotation: torch.Tensor | np.ndarray) -> np.ndarray:
    """(B, 3, 3) -> (B, 3) angles (z, y, x) in degrees, scipy 'zyx' as in DCP."""
    matrices = np.asarray(rotation.detach().cpu() if isinstance(rotation, torch.Tensor) else rotation, dtype=np.float64)
    from scipy.spatial.transform import Rotation  # here, not at import: `vrnet register` never needs it

    return Rotation.from_matrix(matrices).as_euler("zyx", degrees=True)


def rotation_error_deg(rotation: torch.Tensor, gt_rotation: torch.Tensor) -> torch.Tensor:
    """(B,) isotropic error in degrees: the angle of R^T R_gt.

    Computed as atan2(sin, cos) from the skew and trace parts of R^T R_gt; unlike
    acos((tr - 1) / 2) it stays accurate for small angles (float32 estimates: acos near 1 turns
    1e-7 of rounding into ~0.02 degrees).
    """
    relative = rotation.double().mT @ gt_rotation.double()
    skew = relative - relative.mT
    sin = 0.5 * torch.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], dim=-1).norm(dim=-1)
    cos = 0.5 * (relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    return torch.rad2deg(torch.atan2(sin, cos))


def turn_deg(rotation: torch.Tensor) -> torch.Tensor:
    """(B,) float64 angle in degrees by which each rotation (B, 3, 3) turns: its distance from the identity."""
    return rotation_error_deg(rotation, torch.eye(3, dtype=torch.float64, device=rotation.device))


def translation_error(translation: torch.Tensor, gt_translation: torch.Tensor) -> torch.Tensor:
    """(B,) Euclidean distance |t - t_gt|."""
    return (translation.double() - gt_translation.double()).norm(dim=-1)


def chamfer_distance(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, N, 3), (B, M, 3) -> (B,) mean squared nearest distance a->b plus b->a (paper Eq. 14)."""
    return knn(a, b, 1)[0].mean(dim=(1, 2)) + knn(b, a, 1)[0].mean(dim=(1, 2))


def correspondence_error(points: torch.Tensor, src: torch.Tensor, gt_rotation: torch.Tensor,
                         gt_translation: torch.Tensor) -> torch.Tensor:
    """(B, N) distance of each predicted correspondent (VCP or RCP) from the true position
    R_gt x_i + t_gt. For RCPs it equals the error of the correction walk's offset,
    |offset_i - (R_gt x_i + t_gt - vcp_i)| (the paper's L4 residual)."""
    truth = move(src, gt_rotation, gt_translation)
    return (points - truth).norm(dim=-1)


def correct_match_ratio(points: torch.Tensor, src: torch.Tensor, gt_rotation: torch.Tensor,
                        gt_translation: torch.Tensor, threshold: float = 0.15) -> torch.Tensor:
    """(B,) share of source points whose predicted correspondent (VCP or RCP) lies within
    ``threshold`` of the true position R_gt x_i + t_gt."""
    return (correspondence_error(points, src, gt_rotation, gt_translation) < threshold).double().mean(dim=1)


def summarize(pred_rotation: np.ndarray, gt_rotation: np.ndarray, pred_translation: np.ndarray,
              gt_translation: np.ndarray, re_thresholds=(1.0, 5.0), te_thresholds=(0.01, 0.1)) -> dict:
    """Paper-layout metrics over a whole test set (arrays stacked over all pairs)."""
    euler_err = euler_zyx_deg(pred_rotation) - euler_zyx_deg(gt_rotation)
    t_err = pred_translation.astype(np.float64) - gt_translation.astype(np.float64)
    re = rotation_error_deg(torch.as_tensor(pred_rotation), torch.as_tensor(gt_rotation)).numpy()
    te = translation_error(torch.as_tensor(pred_translation), torch.as_tensor(gt_translation)).numpy()
    result = {
        "RMSE(R)": float(np.sqrt((euler_err ** 2).mean())),
        "MAE(R)": float(np.abs(euler_err).mean()),
        "RMSE(t)": float(np.sqrt((t_err ** 2).mean())),
        "MAE(t)": float(np.abs(t_err).mean()),
        "RE mean (deg)": float(re.mean()),
        "RE median (deg)": float(np.median(re)),
        "TE mean": float(te.mean()),
        "TE median": float(np.median(te)),
    }
    for r_thr, t_thr in zip(re_thresholds, te_thresholds):
        result[f"recall(RE<{r_thr:g},TE<{t_thr:g})"] = float(((re < r_thr) & (te < t_thr)).mean())
    return result
