"""Shipped VRNet weights: ``load_pretrained(name=None)`` and the export that makes them.

The files live in ``vrnet_ext/weights/`` as ``<name>.pt`` (float16 weights in the checkpoint layout
of :mod:`vrnet_ext.checkpoints`, plus a ``card`` of the training facts and metrics) with a model
card ``<name>.md`` beside each. Every model takes clouds as :meth:`VRNet.forward` does:
``src (B, N, 3)``, ``tgt (B, M, 3)`` in the frame and scale of ModelNet40's unit-sphere shapes,
and returns ``R src + t ~ tgt``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from vrnet_ext.model import VRNet

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_MODEL = "vrnet-pv-upc"
FORMAT = "vrnet_ext.pretrained/1"


def available() -> list[str]:
    """Names of the shipped models (``vrnet_ext/weights/<name>.pt``)."""
    return sorted(path.stem for path in WEIGHTS_DIR.glob("*.pt"))


def weights_path(name: str) -> Path:
    """The file of a shipped model; ValueError listing the names when ``name`` is not one."""
    if name not in available():
        raise ValueError(f"no shipped model named {name!r}; available: {available() or 'none'}")
    return WEIGHTS_DIR / f"{name}.pt"


def load_pretrained(name: str | None = None, device: str | torch.device = "cpu") -> VRNet:
    """A shipped VRNet in eval mode, float32, on ``device``; ``name=None`` is the PV/UPC model.

    Example::

        model = vrnet_ext.load_pretrained()
        out = model(src, tgt)          # src (B, N, 3), tgt (B, M, 3), e.g. 768-point partial views
        out.rotation, out.translation  # R src + t ~ tgt
    """
    from vrnet_ext.checkpoints import load_model

    return load_model(name or DEFAULT_MODEL, device)[0]


def model_card(name: str | None = None) -> dict:
    """The training facts and metrics stored with a shipped model."""
    from vrnet_ext.checkpoints import read_checkpoint

    return dict(read_checkpoint(weights_path(name or DEFAULT_MODEL)).get("card", {}))


def export_pretrained(checkpoint: str | os.PathLike, out_path: str | os.PathLike, card: dict) -> Path:
    """Writes a training checkpoint's model as shipped weights: float16 tensors (integer buffers as
    they are), the training config without local paths, and ``card`` (plain JSON values)."""
    from vrnet_ext.checkpoints import read_checkpoint

    state = read_checkpoint(checkpoint)
    weights = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    config = {k: v for k, v in state["config"].items() if k not in ("data_dir", "out_dir", "resume")}
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": FORMAT, "model": weights, "config": config, "card": json.loads(json.dumps(card))}, out_path)
    return out_path


__all__ = ["DEFAULT_MODEL", "available", "export_pretrained", "load_pretrained", "model_card", "weights_path"]
