"""Reading VRNet checkpoints and shipped weights: bounded, validated, with errors naming the file.

A checkpoint is untrusted input. It is unpickled with ``weights_only=True`` (tensors and plain
values only, no code), its model configuration is checked against :data:`MODEL_LIMITS` before
anything is built (a file asking for ``iterations = 10**6`` or ``emb_dims = 8192`` would otherwise
hang or exhaust the machine), and its weights must match that configuration exactly. Every
failure is a :class:`CheckpointError` that names the file and says what is wrong; none of them
suggests ``weights_only=False``, which would let the file run code.

Two kinds of file are read:

* a training checkpoint (``last.pt``, ``best.pt`` of ``vrnet train``): ``model``, ``config``
  (the :class:`~vrnet_ext.learning.train.TrainConfig` as a dict, ``config["model"]`` the model's), the
  optimizer state and progress counters;
* shipped weights (``vrnet_ext/weights/*.pt``, see :mod:`vrnet_ext.model.pretrained`): the same
  ``model`` and ``config`` keys with float16 tensors, plus a ``card`` of metrics.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import torch

from vrnet_ext.model import VRNet, VRNetConfig
from vrnet_ext.model.config import training_rotations_centre
from vrnet_ext.names import DEFAULT_MAX_ANGLE, DEFAULT_ROTATION_RANGE
from vrnet_ext.model.scene import SCENE_FORMAT, SceneConfig, SceneVRNet

# Inclusive (low, high) bounds on the model configuration a file may ask for. The paper's model
# (k 20, emb 512, ff 1024, widths <= 512, one encoder and decoder layer) is far inside them.
MODEL_LIMITS = {
    "k": (1, 128),
    "emb_dims": (1, 2048),
    "heads": (1, 64),
    "ff_dims": (1, 8192),
    "encoder_layers": (0, 12),
    "decoder_layers": (0, 12),
    "iterations": (1, 20),
    "irls_iterations": (0, 100),
}
WIDTH_LIMIT = 2048   # every DGCNN / walk layer width
DEPTH_LIMIT = 16     # layers in dgcnn_channels / walk_channels


class CheckpointError(ValueError):
    """A file that is not a usable VRNet checkpoint (the message names the file and the reason)."""


def read_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """The dict stored in ``path`` (weights-only unpickling), with ``model`` and ``config`` present."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings():
            # torch warns about a raw pickle's protocol before refusing it; the error below says it all
            warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
            state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types here; none of its advice applies to untrusted files
        raise CheckpointError(f"{path}: not a vrnet checkpoint (it cannot be read as a weights-only torch "
                              f"file: {type(exc).__name__})") from None
    if not isinstance(state, dict) or not isinstance(state.get("model"), dict) \
            or not isinstance(state.get("config"), dict):
        raise CheckpointError(f"{path}: not a vrnet checkpoint (it lacks the 'model' weights or the 'config')")
    if state.get("format") != SCENE_FORMAT and not isinstance(state["config"].get("model"), dict):
        raise CheckpointError(f"{path}: not a vrnet checkpoint (its 'config' has no 'model' section)")
    return state


def model_values(config: dict, source: str = "config") -> dict:
    """The model configuration of a training config (a checkpoint's ``config``), with the rotation
    search's centre (``VRNetConfig.rotation_search_centre``) set from the rotations its training
    pairs were drawn from (``rotation_range``, ``train_max_angle``) where the model configuration
    does not name one (a run of ``vrnet train`` leaves it to its rotations; files written before
    that field)."""
    values = dict(config["model"])
    if "rotation_search_centre" not in values:
        drawn = config.get("rotation_range", DEFAULT_ROTATION_RANGE)
        largest = config.get("train_max_angle", DEFAULT_MAX_ANGLE)
        if not isinstance(largest, (int, float)) or isinstance(largest, bool) or not 0 < largest <= 180:
            raise CheckpointError(f"{source}: train_max_angle = {largest!r} is outside (0, 180] degrees")
        try:
            values["rotation_search_centre"] = list(training_rotations_centre(drawn, largest))
        except ValueError as exc:
            raise CheckpointError(f"{source}: {exc}") from None
    return values


def validate_model_config(values: dict, source: str = "config") -> VRNetConfig:
    """A :class:`VRNetConfig` from untrusted ``values``, every size checked against the limits."""
    try:
        config = VRNetConfig.from_dict(values)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{source}: invalid model configuration: {exc}") from None
    for name, (low, high) in MODEL_LIMITS.items():
        value = getattr(config, name)
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            raise CheckpointError(f"{source}: model {name} = {value!r} is outside [{low}, {high}]")
    for name in ("dgcnn_channels", "walk_channels"):
        widths = getattr(config, name)
        if not 1 <= len(widths) <= DEPTH_LIMIT or not all(1 <= w <= WIDTH_LIMIT for w in widths):
            raise CheckpointError(f"{source}: model {name} = {list(widths)} needs 1-{DEPTH_LIMIT} widths "
                                  f"in [1, {WIDTH_LIMIT}]")
    if not isinstance(config.negative_slope, (int, float)) or not 0 <= config.negative_slope < 1:
        raise CheckpointError(f"{source}: model negative_slope = {config.negative_slope!r} is outside [0, 1)")
    return config


def model_from_state(state: dict, source: str) -> VRNet | SceneVRNet:
    """The float32 model described by a checkpoint dict (float16 shipped weights are widened): a
    :class:`SceneVRNet` for a scene-model file (``format`` SCENE_FORMAT), else a :class:`VRNet`."""
    if state.get("format") == SCENE_FORMAT:
        try:
            model = SceneVRNet(SceneConfig.from_dict(state["config"]))
        except (TypeError, ValueError) as exc:
            raise CheckpointError(f"{source}: invalid scene-model configuration: {exc}") from None
    else:
        model = VRNet(validate_model_config(model_values(state["config"], source), source))
    weights = {k: v.float() if v.dtype == torch.float16 else v
               for k, v in checked_weights(state["model"], model.state_dict(), source).items()}
    try:
        model.load_state_dict(weights)
    except (RuntimeError, TypeError, ValueError) as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{source}: its weights do not match its model configuration ({first_line})") from None
    return model


FLOATS = (torch.float16, torch.float32)  # what a file's floating-point weights may be stored as


def checked_weights(weights: dict, expected: dict[str, torch.Tensor], source: str) -> dict[str, torch.Tensor]:
    """``weights`` of an untrusted file, each checked against ``expected`` (the model's own state
    dict) before anything is computed from it: the same names, every value a dense tensor of the
    expected shape (so widening float16 to float32 allocates no more than the model itself, however
    the file's shapes and strides were crafted), a floating-point weight stored as float16 or
    float32, any other one in its own dtype. CheckpointError names the file and the weight."""
    missing, unexpected = sorted(expected.keys() - weights.keys()), sorted(weights.keys() - expected.keys())
    if missing or unexpected:
        raise CheckpointError(f"{source}: its weights do not match its model configuration (missing: "
                              f"{missing[:3] or 'none'}, unexpected: {unexpected[:3] or 'none'})")
    for name, value in weights.items():
        want = expected[name]
        if not isinstance(value, torch.Tensor) or value.layout != torch.strided or value.is_meta:
            raise CheckpointError(f"{source}: weight {name} is not a dense tensor")
        if value.shape != want.shape:
            raise CheckpointError(f"{source}: its weights do not match its model configuration (weight {name} "
                                  f"has shape {tuple(value.shape)}, the configuration needs {tuple(want.shape)})")
        allowed = FLOATS if want.is_floating_point() else (want.dtype,)
        if value.dtype not in allowed:
            raise CheckpointError(f"{source}: weight {name} is stored as {value.dtype}, not as one of "
                                  f"{[str(d) for d in allowed]}")
    return weights


__all__ = ["CheckpointError", "checked_weights", "MODEL_LIMITS", "model_from_state", "model_values", "read_checkpoint",
           "validate_model_config"]
