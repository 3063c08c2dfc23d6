"""How far a registered scene (:func:`~vrnet_ext.registration.multiway.register_scene`) is from
ground-truth poses: per scan (absolute: each pose against the truth, both expressed in the first
placed scan's frame), their RMSE, and for every registered pair the relative pose before (the
pairwise registration) and after (the optimised poses) the pose graph, with the share of pairs
registered (:func:`~vrnet_ext.registration.result.is_registered`)."""
from __future__ import annotations

import numpy as np

from vrnet_ext.names import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION
from vrnet_ext.registration.multiway import SceneResult
from vrnet_ext.registration.result import is_registered, transform_errors


def _summary(errors: list[dict]) -> dict[str, float]:
    """RMSE and largest of the rotation errors (degrees) and translation errors of scans."""
    rotation = np.array([e["rotation_error_deg"] for e in errors])
    translation = np.array([e["translation_error"] for e in errors])
    return {"rmse_rotation_deg": float(np.sqrt(np.mean(rotation ** 2))), "max_rotation_deg": float(rotation.max()),
            "rmse_translation": float(np.sqrt(np.mean(translation ** 2))), "max_translation": float(translation.max())}


def _absolute(poses: np.ndarray, truth: np.ndarray, placed: list[int]) -> list[dict]:
    return [transform_errors(poses[i], truth[i]) for i in placed]


def scene_errors(result: SceneResult, truth: np.ndarray, *, success_rotation_deg: float = SUCCESS_ROTATION_DEG,
                 success_translation: float = SUCCESS_TRANSLATION) -> dict:
    """truth (P, 4, 4): each scan's ground-truth pose in any one frame (``T_world_scan``) ->
    ``scans``: per scan its name and errors (None when not placed) for the optimised poses;
    ``optimised`` and ``initial`` (the spanning-tree chain): the RMSE and largest over placed scans of
    the rotation error (degrees) and translation error (the scans' unit); ``pairs``: per registered pair,
    the errors of the pairwise transform (``before``) and of the optimised poses' (``after``), and
    ``recall_before`` / ``recall_after``: the share of those pairs registered."""
    truth = np.asarray(truth, dtype=np.float64)
    if truth.shape != result.poses.shape:
        raise ValueError(f"truth must hold one 4x4 pose per scan, shape {result.poses.shape}, got {truth.shape}")
    placed = np.flatnonzero(result.placed).tolist()
    reference = placed[0]
    truth = np.linalg.inv(truth[reference]) @ truth  # in the reference scan's frame, as the poses
    optimised = _absolute(result.poses, truth, placed)
    initial = _absolute(result.initial_poses, truth, placed)
    errors = dict(zip(placed, optimised))
    scans = [{"name": name, **errors[i]} if i in errors else {"name": name, "rotation_error_deg": None,
                                                                "translation_error": None}
             for i, name in enumerate(result.names)]
    pairs, registered = [], {"before": [], "after": []}
    for edge in result.edges:
        relative = np.linalg.inv(truth[edge.target]) @ truth[edge.source]
        optimised_relative = np.linalg.inv(result.poses[edge.target]) @ result.poses[edge.source]
        record = {"source": result.names[edge.source], "target": result.names[edge.target], "kept": edge.kept,
                  "before": transform_errors(edge.T_target_source, relative),
                  "after": transform_errors(optimised_relative, relative)}
        pairs.append(record)
        for when in ("before", "after"):
            registered[when].append(is_registered(record[when], success_rotation_deg, success_translation))
    return {"scans": scans, "optimised": _summary(optimised), "initial": _summary(initial), "pairs": pairs,
            "recall_before": float(np.mean(registered["before"])) if pairs else float("nan"),
            "recall_after": float(np.mean(registered["after"])) if pairs else float("nan")}


__all__ = ["scene_errors"]
