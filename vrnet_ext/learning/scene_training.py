"""Self-supervised training of :class:`~vrnet_ext.model.scene.SceneVRNet` on real scans.

Each step draws a :func:`~vrnet_ext.data.scans.synthetic_pair` from one of the given scans and
minimises

    L = InfoNCE(matching logits, true partner) + log(1 + |RCP - truth| / voxel) + BCE(confidence, RCP right)

where a source point's true partner is the target point nearest its true position (if within
``PARTNER_VOXELS``), the RCP term averages over points with a partner, and "RCP right" means within
``CORRECT_VOXELS`` of the true position. The pair's coordinates are in voxel units throughout.
Checkpoints (model, optimiser, step, generator state) are written every ``checkpoint_every`` steps
and at the end, so a run resumes where it stopped.
"""
from __future__ import annotations

import time
from collections.abc import Callable
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

from vrnet_ext import ops
from vrnet_ext.geometry.atomic import save_atomically
from vrnet_ext.model.checkpoints import read_checkpoint
from vrnet_ext.data.scans import ScanPair, synthetic_pair
from vrnet_ext.model.scene import SCENE_FORMAT, SceneConfig, SceneOutput, SceneVRNet
from vrnet_ext.geometry.preprocessing import coarse_in_float32, voxel_size_for

PARTNER_VOXELS = 1.0
CORRECT_VOXELS = 2.0


@dataclass
class SceneTrainConfig:
    """A scene-model run: Adam steps at ``lr``, views of about ``points`` points, the pair draws'
    ``seed``, and a checkpoint every ``checkpoint_every`` steps."""

    steps: int = 600
    points: int = 3000          # about this many points per training view
    lr: float = 2e-3
    seed: int = 0
    checkpoint_every: int = 50


def pair_tensors(pair: ScanPair) -> dict[str, torch.Tensor]:
    """The network's inputs for one pair (batch of 1) and the true positions of the source points."""
    src, tgt = pair.src.network_points(), pair.tgt.network_points()
    T = torch.as_tensor(pair.T_tgt_src, dtype=torch.float32)
    # T acts on coordinates in the scan's unit; in voxel units the translation scales by 1 / voxel
    truth = src * (pair.src.voxel / pair.tgt.voxel) @ T[:3, :3].T + T[:3, 3] / pair.tgt.voxel
    return {"src": src[None], "tgt": tgt[None], "src_descriptors": pair.src.descriptors[None],
            "tgt_descriptors": pair.tgt.descriptors[None], "truth": truth[None]}


def scene_loss(model: SceneVRNet, out: SceneOutput, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
    """The scene model's loss on one pair (:func:`pair_tensors`): InfoNCE of each source point that has
    a target point within PARTNER_VOXELS against its nearest one, log(1 + error) of its RCP, and the
    confidence's cross-entropy against "RCP within CORRECT_VOXELS". Returns (loss, statistics)."""
    dist2, partner = ops.knn(batch["truth"], batch["tgt"], 1)
    has_partner = dist2[..., 0] <= PARTNER_VOXELS ** 2
    logits = model.scores(out)
    nce = F.cross_entropy(logits[has_partner], partner[..., 0][has_partner]) if has_partner.any() else logits.sum() * 0
    error = (out.rcp - batch["truth"]).norm(dim=-1)
    rectify = torch.log1p(error[has_partner]).mean() if has_partner.any() else error.sum() * 0
    confidence = F.binary_cross_entropy_with_logits(out.confidence_logits, (error < CORRECT_VOXELS).float())
    vcp_error = (out.vcp - batch["truth"]).norm(dim=-1)
    stats = {"nce": float(nce.detach()), "rectify": float(rectify.detach()), "confidence": float(confidence.detach()),
             "partners": float(has_partner.float().mean()),
             "vcp_right": float((vcp_error[has_partner] < CORRECT_VOXELS).float().mean()) if has_partner.any() else 0.0,
             "rcp_right": float((error[has_partner] < CORRECT_VOXELS).float().mean()) if has_partner.any() else 0.0}
    return nce + rectify + confidence, stats


def synthetic_pair_of(name: str, scan: np.ndarray, voxel: float, rng: np.random.Generator) -> ScanPair:
    """The default pair provider of :func:`train_scene_model`: a self-supervised pair cut from the one
    scan ``name`` (:func:`vrnet_ext.data.scans.synthetic_pair`)."""
    return synthetic_pair(scan, voxel, rng)


def _near_origin(name: str, points: np.ndarray) -> np.ndarray:
    """``points`` (N, 3), re-centred on their median when float32 would round them too coarsely."""
    extent = float(np.max(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    if not len(points) or not coarse_in_float32(float(np.abs(points).max()), extent):
        return points
    centre = np.median(points, axis=0)
    warnings.warn(f"{name}: coordinates up to {np.abs(points).max():.3g} lose precision in float32; training on "
                  f"the scan re-centred on its median {np.round(centre, 3).tolist()}", stacklevel=3)
    return points - centre


def train_scene_model(scans: dict[str, np.ndarray], out_path: str | Path, cfg: SceneTrainConfig,
                      model_config: SceneConfig | None = None, progress: bool = True,
                      pairs: Callable[[str, np.ndarray, float, np.random.Generator], ScanPair] = synthetic_pair_of
                      ) -> Path:
    """Trains on pairs drawn from ``scans`` (name -> (N, 3) points, sensor at the origin) and writes
    ``out_path`` (resuming from it when it exists with the same scans). Each step takes the next
    scan's name and asks ``pairs(name, points, voxel, rng)`` for a :class:`ScanPair` (default: a
    self-supervised pair cut from that scan; a provider of real pairs with ground truth can return
    a pair of two scans instead). A scan whose
    coordinates float32 would round too coarsely (georeferenced: :func:`coarse_in_float32`) is
    re-centred on its median first (its views are cut and turned anyway), with a warning."""
    out_path = Path(out_path)
    scans = {name: _near_origin(name, np.asarray(points, dtype=np.float64)) for name, points in scans.items()}
    model = SceneVRNet(model_config)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    names = sorted(scans)
    voxels = {name: voxel_size_for(scans[name], cfg.points) for name in names}
    rng = np.random.default_rng(cfg.seed)
    step, seconds, history = 0, 0.0, []
    if out_path.exists():
        state = read_checkpoint(out_path)
        if state.get("format") != SCENE_FORMAT or state.get("scans") != names:
            raise ValueError(f"{out_path}: not a scene-model run on the scans {names}; choose another out_path")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step, seconds, history = state["step"], state["train_seconds"], state["history"]
        rng.bit_generator.state = state["rng"]

    def save() -> None:
        save_atomically({"format": SCENE_FORMAT, "config": model.config.to_dict(), "model": model.state_dict(),
                         "optimizer": optimizer.state_dict(), "step": step, "train_seconds": seconds,
                         "history": history, "rng": rng.bit_generator.state, "scans": names,
                         "train_config": cfg.__dict__}, out_path)

    model.train()
    bar = tqdm(total=cfg.steps, initial=step, desc="scene model", disable=not progress)
    while step < cfg.steps:
        started = time.perf_counter()
        name = names[step % len(names)]
        batch = pair_tensors(pairs(name, scans[name], voxels[name], rng))
        out = model(batch["src"], batch["src_descriptors"], batch["tgt"], batch["tgt_descriptors"])
        loss, stats = scene_loss(model, out, batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        seconds += time.perf_counter() - started
        history.append(dict(stats, step=step, scan=name))
        bar.update(1)
        bar.set_postfix(nce=f"{stats['nce']:.2f}", rcp_right=f"{stats['rcp_right']:.2f}")
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            save()
    bar.close()
    return out_path
