"""Shipped weights and how models are found: ``load_pretrained(name=None)``, ``load_model(path or name)``.

The files live in ``vrnet_ext/weights/`` as ``<name>.pt`` (float16 weights in the checkpoint layout
of :mod:`vrnet_ext.model.checkpoints`, plus a ``card`` of the training facts and metrics) with a model
card ``<name>.md`` beside each. Every model takes clouds as :meth:`VRNet.forward` does:
``src (B, N, 3)``, ``tgt (B, M, 3)`` in the frame and scale of ModelNet40's unit-sphere shapes,
and returns ``R src + t ~ tgt``.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from vrnet_ext.model import VRNet
from vrnet_ext.model.checkpoints import CheckpointError, model_from_state, read_checkpoint
from vrnet_ext.model.scene import SCENE_FORMAT, SceneVRNet
from vrnet_ext.names import DEFAULT_MODEL, DEFAULT_SCENE_MODEL, MIXED, SETTINGS

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
FORMAT = "vrnet_ext.pretrained/1"


KINDS = ("vrnet", "scene")


def available(kind: str | None = None) -> list[str]:
    """Names of the shipped models (``vrnet_ext/weights/<name>.pt``); ``kind``: only the ModelNet40
    VRNets (``"vrnet"``) or only the scene models (``"scene"``, :mod:`vrnet_ext.model.scene`)."""
    names = sorted(path.stem for path in WEIGHTS_DIR.glob("*.pt"))
    if kind is None:
        return names
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS} or None, got {kind!r}")

    def is_scene(name: str) -> bool:
        return read_checkpoint(WEIGHTS_DIR / f"{name}.pt").get("format") == SCENE_FORMAT

    return [name for name in names if is_scene(name) == (kind == "scene")]


def cells(name: str) -> list[str]:
    """The ModelNet40 cells ("PV/UPC", "CO/UPC", ...) a shipped VRNet serves: those its card names
    (chosen on validation pairs; none for a model kept as the starting point of others), else the
    setting and split it was trained for; a model trained on every setting (``"mixed"``) serves
    every setting of its split unless its card says otherwise."""
    return _cells_of(read_checkpoint(weights_path(name)))


def _cells_of(state: dict) -> list[str]:
    card = state.get("card", {})
    if "cells" in card:  # chosen on validation; an empty list: a starting point that serves no cell
        return list(card["cells"])
    setting, split = state["config"].get("setting"), state["config"].get("split")
    if setting == MIXED:
        return [f"{s}/{split}" for s in SETTINGS]
    return [f"{setting}/{split}"]


def model_for(setting: str, split: str) -> str | None:
    """The shipped ModelNet40 VRNet that serves (setting, split) (``"PV"``, ``"UPC"``; :func:`cells`),
    one trained for that setting before one trained on every setting, or None."""
    serving = []
    for name in available("vrnet"):
        state = read_checkpoint(WEIGHTS_DIR / f"{name}.pt")  # each file read once
        if f"{setting}/{split}" in _cells_of(state):
            serving.append((state["config"].get("setting") == MIXED, name))
    return min(serving)[1] if serving else None


def weights_path(name: str) -> Path:
    """The file of a shipped model; ValueError listing the names when ``name`` is not one."""
    if name not in available():
        raise ValueError(f"no shipped model named {name!r}; available: {available() or 'none'}")
    return WEIGHTS_DIR / f"{name}.pt"


def load_pretrained(name: str | None = None, device: str | torch.device = "cpu") -> VRNet:
    """A shipped VRNet in eval mode, float32, on ``device``; ``name=None`` is the PV/UPC model.
    A scene model's name (``DEFAULT_SCENE_MODEL``) returns a :class:`~vrnet_ext.model.scene.SceneVRNet`.

    Example::

        model = vrnet_ext.load_pretrained()
        out = model(src, tgt)          # src (B, N, 3), tgt (B, M, 3), e.g. 768-point partial views
        out.rotation, out.translation  # R src + t ~ tgt
    """
    return load_model(weights_path(name or DEFAULT_MODEL), device)[0]


def model_card(name: str | None = None) -> dict:
    """The training facts and metrics stored with a shipped model."""
    return dict(read_checkpoint(weights_path(name or DEFAULT_MODEL)).get("card", {}))


def card_runs_seconds(training: dict) -> float | None:
    """A card's ``training`` section -> the seconds of its runs since its starting point
    (``runs_seconds``, else ``train_seconds`` for cards that predate it); None when it holds no number."""
    runs = training.get("runs_seconds", training.get("train_seconds"))
    if isinstance(runs, bool) or not isinstance(runs, (int, float)):
        return None
    return float(runs)


def training_seconds(name: str) -> float | None:
    """Wall time of all the training behind a shipped model, in seconds: the runs its card counts
    since its starting point (``runs_seconds``) plus the starting point's own total, back to a model
    trained from scratch (``starting_point`` None). None where a card in the chain does not record
    its starting point, names one that is not shipped, or holds no number of seconds."""
    seconds, seen = 0.0, set()
    while name is not None:
        if not isinstance(name, str) or name in seen or name not in available():
            return None
        seen.add(name)
        training = model_card(name).get("training", {})
        runs = card_runs_seconds(training)
        if "starting_point" not in training or runs is None:
            return None
        seconds += runs
        name = training["starting_point"]
    return seconds


def load_model(checkpoint: str | os.PathLike,
               map_location: str | torch.device = "cpu") -> tuple[VRNet | SceneVRNet, dict]:
    """(model in eval mode, checkpoint dict) from a checkpoint path or a shipped name
    (:func:`vrnet_ext.model.pretrained.available`)."""
    path = weights_path(str(checkpoint)) if str(checkpoint) in available() else Path(checkpoint)
    state = read_checkpoint(path, map_location)
    model = model_from_state(state, str(path)).to(map_location)
    return model.eval(), state


def load_vrnet(checkpoint: str | os.PathLike, map_location: str | torch.device = "cpu") -> tuple[VRNet, dict]:
    """:func:`load_model` for commands that need a ModelNet40 :class:`VRNet` (eval, demo, tables):
    a scene model is refused with an error that says where it belongs."""
    model, state = load_model(checkpoint, map_location)
    if isinstance(model, SceneVRNet):
        raise CheckpointError(f"{checkpoint}: a scene model (for `vrnet register`), not a ModelNet40 VRNet")
    return model, state


__all__ = ["DEFAULT_MODEL", "DEFAULT_SCENE_MODEL", "available", "cells", "load_model", "load_pretrained", "load_vrnet",
           "model_card", "model_for", "weights_path"]
