"""Shipped weights from training runs: ``vrnet export`` (float16 weights, the training config without
local paths, a card of training facts and metrics, and the model card beside them)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from vrnet_ext.geometry.atomic import save_atomically, write_text_atomically
from vrnet_ext.learning.lineage import Lineage, lineage_of, run_seconds
from vrnet_ext.model.checkpoints import model_from_state, model_values, read_checkpoint, validate_model_config
from vrnet_ext.model.pretrained import (DEFAULT_MODEL, FORMAT, available, card_runs_seconds, model_card,
                                        training_seconds)
from vrnet_ext.model.scene import SCENE_FORMAT
from vrnet_ext.names import DEFAULT_MAX_ANGLE, DEFAULT_ROTATION_RANGE


# Model-config fields an export may change: they choose how the estimate is solved, not the weights.
INFERENCE_FIELDS = ("procrustes_points", "irls_iterations", "irls_kernel", "irls_scale", "second_pass_below",
                    "rotation_search_below", "rotation_search_centre", "rotation_search_polish",
                    "rotation_search_icp_starts", "rotation_search_icp_slides", "rotation_search_icp",
                    "max_rotation", "rotation_search_turn_penalty", "polish_iterations", "consistency_radius")
# Inference-time fields that act only inside the rotation search: moot where a file does not search.
SEARCH_ONLY_FIELDS = ("rotation_search_centre", "rotation_search_polish", "rotation_search_icp_starts",
                      "rotation_search_icp_slides", "rotation_search_icp", "max_rotation",
                      "rotation_search_turn_penalty")
# How a card names the rotations of the ranges without a largest angle.
UNIFORM_ROTATIONS = {"so3": "so3: uniform over all rotations",
                     "cube_residual": "cube_residual: uniform over all rotations, each turned back by the cube "
                                      "rotation nearest it (at most 62.8 degrees)"}


def affecting(values: dict, served: dict) -> dict:
    """Those of ``values`` (inference-time fields: an export's overrides, a measurement's recorded
    solve) that affect the estimates of a model solving as ``served``: all of them, but the rotation
    search's own fields (:data:`SEARCH_ONLY_FIELDS`) where it does not search (``rotation_search_below``
    0), so that a card's test table or a measurement taken without the search still holds."""
    if served.get("rotation_search_below", 0) == 0:
        return {key: value for key, value in values.items() if key not in SEARCH_ONLY_FIELDS}
    return dict(values)


def training_facts(checkpoint: str | os.PathLike, name: str | None = None) -> dict:
    """What a model card says about training, read from a ``vrnet train`` checkpoint and the
    ``metrics.jsonl`` beside it: setting, split, preset, the rotations of its training pairs (how
    drawn, the largest angle; unused for ``so3`` and ``cube_residual``), the selected epoch, steps,
    wall time, the shipped model its warm starts began from and the wall time of the runs since
    (:mod:`vrnet_ext.learning.lineage`), and that epoch's validation metrics.

    ``name``: the name the model will be shipped under. When it is the name of the model the chain
    began from (a model replacing its own start), the card takes over that model's starting point and
    adds its time, as its card stood when the chain began (as it stands now for runs that predate the
    record)."""

    state = read_checkpoint(checkpoint)
    config = state["config"]
    facts = {key: config.get(key) for key in ("preset", "setting", "split", "num_points", "num_subsampled",
                                              "batch_size", "stage1_epochs", "stage2_epochs", "precision",
                                              "max_train_items", "val_fraction", "seed")}
    drawn = config.get("rotation_range", DEFAULT_ROTATION_RANGE)
    largest = config.get("train_max_angle", DEFAULT_MAX_ANGLE)
    lowest = -largest if drawn == "symmetric" else 0
    facts["rotations"] = UNIFORM_ROTATIONS.get(drawn, f"{drawn}: each Euler angle in [{lowest:g}, {largest:g}] degrees")
    starting_point, runs_seconds = _starting_point(lineage_of(state, str(checkpoint)), name)
    facts.update(stage=state.get("stage"), epoch=(state.get("epoch") or 0) + 1, step=state.get("step"),
                 train_seconds=round(run_seconds(state), 1), starting_point=starting_point,
                 runs_seconds=round(runs_seconds, 1))
    metrics = Path(checkpoint).with_name("metrics.jsonl")
    if metrics.exists():
        records = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
        mine = [r for r in records if r.get("step") == state.get("step")]
        if mine:
            facts["validation"] = {k[4:]: v for k, v in mine[-1].items() if k.startswith("val_")}
    return facts


def _starting_point(lineage: Lineage, name: str | None) -> tuple[str | None, float]:
    """(starting point, seconds since) of a card, the start's own history folded in when the model
    is shipped under its starting point's name."""
    if name is None or lineage.starting_point != name:
        return lineage.starting_point, lineage.seconds
    earlier = lineage.start_training
    if earlier is None:
        if name not in available():
            return lineage.starting_point, lineage.seconds
        earlier = model_card(name).get("training", {})
    return (earlier.get("starting_point", f"an earlier {name}"),
            lineage.seconds + (card_runs_seconds(earlier) or 0.0))


def export_pretrained(checkpoint: str | os.PathLike, out_path: str | os.PathLike, card: dict,
                      model_overrides: dict | None = None) -> Path:
    """Writes a training checkpoint's model as shipped weights: float16 tensors (integer buffers as
    they are), the training config without local paths, and ``card`` (plain JSON values); and the
    model card ``<out_path>.md`` beside it (:func:`model_card_markdown`). ``model_overrides`` change
    inference-time fields of the model config (:data:`INFERENCE_FIELDS`)."""

    state = read_checkpoint(checkpoint)
    model_from_state(state, str(checkpoint))  # its configuration within the limits, its weights matching it
    weights = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    local = ("data_dir", "out_dir", "resume", "features_from", "walk_from")
    config = {k: v for k, v in state["config"].items() if k not in local}
    overrides = dict(model_overrides or {})
    if set(overrides) - set(INFERENCE_FIELDS):
        raise ValueError(f"model_overrides may set {', '.join(INFERENCE_FIELDS)} only, got {sorted(overrides)}")
    config["model"] = validate_model_config(dict(model_values(config, str(checkpoint)), **overrides),
                                            "model_overrides").to_dict()
    card = json.loads(json.dumps(card))
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_atomically({"format": FORMAT, "model": weights, "config": config, "card": card}, out_path)
    write_text_atomically(out_path.with_suffix(".md"), model_card_markdown(out_path.stem, config, card))
    return out_path


def export_scene_model(run: str | os.PathLike, out_path: str | os.PathLike, card: dict) -> Path:
    """Writes a ``vrnet train-scene`` run as shipped weights (float16, the run's facts in the card)
    and its model card ``<out_path>.md``."""

    state = read_checkpoint(run)
    if state.get("format") != SCENE_FORMAT:
        raise ValueError(f"{run}: not a scene-model run of `vrnet train-scene`")
    model_from_state(state, str(run))  # the weights match the configuration
    training = {"scans": ", ".join(state.get("scans", [])), "steps": state.get("step"),
                "train_seconds": round(run_seconds(state), 1)}
    training.update({k: v for k, v in (state.get("train_config") or {}).items() if k != "checkpoint_every"})
    card = json.loads(json.dumps(dict(card, training=dict(training, **card.get("training", {})))))
    weights = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_atomically({"format": SCENE_FORMAT, "model": weights, "config": state["config"], "card": card}, out_path)
    lines = [f"# Model card: `{out_path.stem}`", "", card.get("summary", ""), "", "```bash",
             f"vrnet register SOURCE TARGET --method vrnet --checkpoint {out_path.stem}", "```", "", "## Model", ""]
    lines += [f"- {key}: `{value}`" for key, value in state["config"].items()]
    lines += ["", "## Training", ""] + [f"- {key}: {value}" for key, value in card["training"].items()]
    if "results" in card:
        lines += ["", "## Results", "", card.get("results_note", ""), ""] + card["results"]
    lines += ["", "## Notes", ""] + [f"- {note}" for note in card.get("notes", [])]
    write_text_atomically(out_path.with_suffix(".md"), "\n".join(lines) + "\n")
    return out_path


def _table(values: dict) -> list[str]:
    rows = ["| metric | value |", "|---|---:|"]
    for key, value in values.items():
        if isinstance(value, float):
            rows.append(f"| {key} | {value:.4g} |")
        elif isinstance(value, int):
            rows.append(f"| {key} | {value} |")
    return rows


def model_card_markdown(name: str, config: dict, card: dict) -> str:
    """The model card of a shipped model: what it is, how it was trained and how well it does."""
    model = config.get("model", {})
    lines = [f"# Model card: `{name}`", "", card.get("summary", ""), "",
             "```python", "import vrnet_ext", f"model = vrnet_ext.load_pretrained({name!r})"
             + ("" if name != DEFAULT_MODEL else "  # the default: load_pretrained()"),
             "out = model(src, tgt)  # src (B, N, 3), tgt (B, M, 3) in the unit sphere; R src + t ~ tgt", "```", "",
             "## Model", ""]
    lines += [f"- {key}: `{value}`" for key, value in model.items()
              if key not in ("backend", "transformer_precision")]  # run-time choices, not the model
    if card.get("cells"):
        lines += ["", "Serves the ModelNet40 cells " + ", ".join(card["cells"])
                  + " (`vrnet eval --setting S --split P` picks it for them)."]
    elif "cells" in card:
        lines += ["", "Serves no ModelNet40 cell (`vrnet eval` picks other models by default); it is the "
                  "starting point of models that do, and loads by name."]
    lines += ["", "## Training", ""]
    training = card.get("training", {})
    lines += [f"- {key}: {value}" for key, value in training.items() if not isinstance(value, dict)]
    if "starting_point" in training:
        start = training["starting_point"]
        before = 0.0 if start is None else training_seconds(start)
        runs = card_runs_seconds(training)
        if before is not None and runs is not None:
            total = runs + before
            lines.append(f"- training in all: {total:,.0f} s (runs_seconds plus the training of the starting point "
                         "and of every model before it)")
    if "validation" in training:
        lines += ["", "Validation (pairs held out of the training split) at the selected epoch:", ""]
        lines += _table(card["training"]["validation"])
    if "test" in card:
        lines += ["", "## Test", "", card.get("test_note", ""), ""] + _table(card["test"])
    for cell, metrics in card.get("tests", {}).items():
        lines += ["", f"## Test: {cell}", "", card.get("tests_note", ""), ""] + _table(metrics)
    lines += ["", "## Notes", ""] + [f"- {note}" for note in card.get("notes", [])]
    return "\n".join(lines) + "\n"
