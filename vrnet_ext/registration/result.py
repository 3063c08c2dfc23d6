"""One result type for every registration (:func:`vrnet_ext.registration.register`, one ICP run)."""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from vrnet_ext.geometry.metrics import rotation_error_deg, translation_error
from vrnet_ext.names import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION


@dataclass(kw_only=True)
class RegistrationResult:
    """One registration of a source scan onto a target scan (of :func:`register`, or one ICP run).

    ``T_target_source`` (4, 4) maps source points into the target frame (:mod:`vrnet_ext.geometry.transforms`);
    ``initial`` is the transform the refinement started from. Built by keyword only.
    """
    T_target_source: np.ndarray
    initial: np.ndarray
    method: str             # the global estimate: "vrnet", "fpfh", "fgr" or "icp" (none)
    icp_step: str           # "point_to_point", "point_to_plane" or "gicp"
    iterations: int         # ICP iterations run (0: no refinement)
    converged: bool         # ICP stopped because the transform stopped changing
    fitness: float          # share of the (downsampled) source points with a target point within reach
    inlier_rmse: float      # in the scans' unit, over those points
    correspondences: int    # how many source points those are
    seconds: dict[str, float] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    start: str = ""         # the estimate ICP started from: ``method``, or an estimate it also tried
    consensus: int = 0      # correspondences the global estimate agreed on (RANSAC / spatial-consistency
                            # inliers, pairs a network used; 0 when it has no such count)
    selection: str = ""     # the default ("auto") only, when it tried its other estimators: why, and their fits
    rival_consensus: int = 0  # correspondences consistent with another alignment, none of ``consensus``'s
                              # (spatial consistency's second fit; 0 when none or not measured)

    @classmethod
    def global_estimate(cls, T_target_source, method: str, consensus: int = 0,
                        points: dict[str, int] | None = None, rival_consensus: int = 0) -> "RegistrationResult":
        """A global estimate before any refinement: no ICP (icp_step "none", 0 iterations), fitness and
        inlier RMSE not measured (NaN), ``initial`` the identity."""
        return cls(T_target_source=np.asarray(T_target_source, dtype=np.float64), initial=np.eye(4), method=method,
                   icp_step="none", iterations=0, converged=False, fitness=float("nan"), inlier_rmse=float("nan"),
                   correspondences=0, points=dict(points or {}), start=method, consensus=int(consensus),
                   rival_consensus=int(rival_consensus))

    def to_dict(self) -> dict:
        """Every field, the 4x4 matrices as nested lists (for JSON)."""
        out = asdict(self)
        out["T_target_source"] = self.T_target_source.tolist()
        out["initial"] = self.initial.tolist()
        return out


def is_registered(errors: dict[str, float], rotation_deg: float = SUCCESS_ROTATION_DEG,
                  translation: float = SUCCESS_TRANSLATION) -> bool:
    """Whether :func:`transform_errors` ``errors`` are below both thresholds."""
    return bool(errors["rotation_error_deg"] < rotation_deg and errors["translation_error"] < translation)


def transform_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Rotation error (degrees, isotropic; :func:`vrnet_ext.geometry.metrics.rotation_error_deg`) and
    translation error (same unit as the input) of two 4x4 transforms."""
    est, gt = torch.as_tensor(estimate[None]), torch.as_tensor(truth[None])
    return {"rotation_error_deg": float(rotation_error_deg(est[:, :3, :3], gt[:, :3, :3])),
            "translation_error": float(translation_error(est[:, :3, 3], gt[:, :3, 3]))}


def _old_step_name(result: RegistrationResult) -> str:
    warnings.warn("RegistrationResult.estimator is now RegistrationResult.icp_step; the old name goes in vrnet_ext 0.3",
                  DeprecationWarning, stacklevel=2)
    return result.icp_step


RegistrationResult.estimator = property(_old_step_name)
