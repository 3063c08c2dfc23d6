"""Warm starts of a training run from another run's checkpoint: its feature extractor
(``--features-from``) and its correction walk (``--walk-from``).

A walk whose confidence shares the offsets' MLP (``walk_confidence_trunk=False``: the confidence is
the last channel of that MLP's last layer) can start a run whose confidence has its own MLP
(``walk_confidence_trunk=True``): both MLPs start as copies of the shared one, the offset MLP keeping
the offset (and gate) channels of its last layer and the confidence MLP the confidence channel, so
the new walk computes exactly what the old one did until training moves it.
"""
from __future__ import annotations

from vrnet_ext.model.checkpoints import read_checkpoint, validate_model_config
from vrnet_ext.model import VRNet, VRNetConfig

FEATURE_FIELDS = ("k", "dgcnn_channels", "emb_dims", "negative_slope", "heads", "ff_dims", "encoder_layers",
                  "decoder_layers")
WALK_FIELDS = ("emb_dims", "walk_channels", "walk_coordinates", "walk_gate", "walk_confidence", "walk_match_stats",
               "correction_walk")


def _saved_config(path: str, argument: str, fields: tuple[str, ...], model: VRNet) -> tuple[dict, VRNetConfig]:
    state = read_checkpoint(path)
    if not isinstance(state["config"].get("model"), dict):
        raise ValueError(f"{argument}: {path} is not a VRNet checkpoint (a scene model of `vrnet train-scene` has "
                         f"other layers)")
    saved = validate_model_config(state["config"]["model"], path)
    differing = [k for k in fields if getattr(saved, k) != getattr(model.config, k)]
    if differing:
        raise ValueError(f"{argument}: {path} has other settings ({', '.join(differing)}) than this run")
    return state["model"], saved


def init_features_from(model: VRNet, path: str) -> None:
    """Copies the feature extractor (DGCNN + Transformer, weights and BatchNorm statistics) of
    another run's checkpoint into ``model``: stage 2 (or an ablation arm) on trained stage-1
    features, whatever that run's correction walk was."""
    saved_state, _ = _saved_config(path, "features_from", FEATURE_FIELDS, model)
    prefixes = ("features.", "transformer.")
    features = {k: v for k, v in saved_state.items() if k.startswith(prefixes)}
    own = {k for k in model.state_dict() if k.startswith(prefixes)}
    if set(features) != own:
        raise ValueError(f"features_from: {path} does not hold this model's feature extractor")
    model.load_state_dict(features, strict=False)


def init_walk_from(model: VRNet, path: str) -> None:
    """Copies the correction walk (weights and BatchNorm statistics) of another run's checkpoint
    into ``model``, splitting a shared-trunk walk into offset and confidence MLPs when ``model``
    has ``walk_confidence_trunk`` (see the module docstring)."""
    saved_state, saved = _saved_config(path, "walk_from", WALK_FIELDS, model)
    if not model.config.correction_walk:
        raise ValueError("walk_from: this run has no correction walk")
    walk = {k[len("walk."):]: v for k, v in saved_state.items() if k.startswith("walk.")}
    if saved.walk_confidence_trunk == model.config.walk_confidence_trunk:
        model.walk.load_state_dict(walk)
        return
    if saved.walk_confidence_trunk:
        raise ValueError(f"walk_from: {path} has a confidence MLP of its own; it cannot start a shared-trunk walk")
    last = len(model.walk.net) - 1
    shared = {k[len("net."):]: v for k, v in walk.items() if k.startswith("net.")}
    offset_channels = model.walk.net[last].out_channels  # 3 [+ gate]; the confidence is the shared layer's last
    offset_state, confidence_state = dict(shared), dict(shared)
    for name in ("weight", "bias"):
        key = f"{last}.{name}"
        offset_state[key] = shared[key][:offset_channels]
        confidence_state[key] = shared[key][offset_channels:]
    model.walk.net.load_state_dict(offset_state)
    model.walk.confidence_net.load_state_dict(confidence_state)
