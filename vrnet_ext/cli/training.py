"""``vrnet train``, ``vrnet eval``, ``vrnet plot``, ``vrnet export`` and ``vrnet train-scene``."""
from __future__ import annotations

import argparse
import json
import typing
from dataclasses import fields
from pathlib import Path

from vrnet_ext.cli.common import (DATA_DIR_HELP, MAX_VIEW_POINTS, DefaultsHelpFormatter, Switch,
                                  checkpoint_or_shipped, device_or_auto, existing_folder, json_output, nonnegative_int,
                                  output_folder, positive_float, positive_int, report_to, unit_interval, view_points,
                                  writable_path, write_json)
from vrnet_ext.data.protocol import FAR_POINTS
from vrnet_ext.names import (ANY_ROTATION, AUTO_DEVICE, BACKENDS, DEFAULT_BACKEND, DEFAULT_ROTATION_RANGE,
                             DEFAULT_SETTING, DEFAULT_SPLIT, MAX_SEARCH_ICP_SLIDES, MAX_TURN_PENALTY, MIXED,
                             PROCRUSTES_POINTS, ROTATION_RANGES, SEARCH_ICP_SLIDE_REACH, SEARCH_ICPS, SETTINGS,
                             SPLITS, TRANSFORMER_PRECISIONS)


ROTATION_RANGE_HELP = ("the pairs' rotations: protocol = each Euler angle in [0, 45] degrees (the paper's); "
                       "symmetric = in [-45, 45]; so3 = uniform over all rotations; cube_residual = a uniform "
                       "rotation turned back by the cube rotation nearest it (what the rotation search's "
                       "nearest start leaves)")
EVAL_PARTITIONS = ("test", "val")  # vrnet eval --partition (ModelNet40Pairs partitions a model is measured on)
# The estimate's inference-time options: the robust solve, the second pass, the rotation search and the polish.
SOLVE_KEYS = ("irls_iterations", "irls_kernel", "irls_scale", "second_pass_below", "rotation_search_below",
              "rotation_search_centre", "rotation_search_polish", "rotation_search_icp_starts",
              "rotation_search_icp_slides", "rotation_search_icp", "max_rotation", "rotation_search_turn_penalty",
              "polish_iterations", "consistency_radius")


def polish_steps(text: str) -> int:
    """An argparse type: ``--polish-iterations`` and ``--rotation-search-polish``, an integer in
    [0, MAX_POLISH_ITERATIONS]."""
    from vrnet_ext.model.config import MAX_POLISH_ITERATIONS

    value = nonnegative_int(text)
    if value > MAX_POLISH_ITERATIONS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_POLISH_ITERATIONS} steps, got {value}")
    return value


def icp_starts(text: str) -> int:
    """An argparse type: ``--rotation-search-icp-starts``, an integer in [0, MAX_ICP_STARTS]."""
    from vrnet_ext.model.config import MAX_ICP_STARTS

    value = nonnegative_int(text)
    if value > MAX_ICP_STARTS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_ICP_STARTS} starts, got {value}")
    return value


def icp_slides(text: str) -> int:
    """An argparse type: ``--rotation-search-icp-slides``, an integer in [1, MAX_SEARCH_ICP_SLIDES]."""
    value = positive_int(text)
    if value > MAX_SEARCH_ICP_SLIDES:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_SEARCH_ICP_SLIDES} slides, got {value}")
    return value


def turn_bound(text: str) -> float:
    """An argparse type: ``--max-rotation``, degrees in (0, ANY_ROTATION]."""
    value = positive_float(text)
    if value > ANY_ROTATION:
        raise argparse.ArgumentTypeError(f"expected at most {ANY_ROTATION:g} degrees, got {value:g}")
    return value


def turn_penalty(text: str) -> float:
    """An argparse type: ``--rotation-search-turn-penalty``, in [0, MAX_TURN_PENALTY]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, {MAX_TURN_PENALTY:g}], got {text!r}") from None
    if not 0 <= value <= MAX_TURN_PENALTY:
        raise argparse.ArgumentTypeError(f"expected a number in [0, {MAX_TURN_PENALTY:g}], got {text}")
    return value


def add_solve_options(parser, default: str) -> None:
    """``--irls-iterations``, ``--irls-kernel``, ``--irls-scale``, ``--second-pass-below``,
    ``--rotation-search-below``, ``--rotation-search-centre``, ``--rotation-search-polish``,
    ``--rotation-search-icp-starts``, ``--rotation-search-icp-slides``, ``--rotation-search-icp``,
    ``--max-rotation``, ``--rotation-search-turn-penalty``, ``--polish-iterations``, ``--consistency-radius``
    (VRNetConfig's fields of these names); ``default`` says what applies when a flag is not given."""
    from vrnet_ext.model.config import IRLS_KERNELS

    parser.add_argument("--irls-iterations", type=nonnegative_int, default=None,
                        help=f"robust reweighting steps after the Procrustes solve, 0: none (default: {default})")
    parser.add_argument("--irls-kernel", choices=IRLS_KERNELS, default=None,
                        help=f"the reweighting's robust weight of a residual (default: {default})")
    parser.add_argument("--irls-scale", type=positive_float, default=None,
                        help=f"the reweighting's scale in medians of a pair's residuals (default: {default})")
    parser.add_argument("--second-pass-below", type=unit_interval, default=None,
                        help="register a pair once more from the moved source when fewer than this share of its "
                             "RCPs agree with its estimate, and keep the pass whose RCPs agree more; 0: never "
                             f"(default: {default})")
    parser.add_argument("--rotation-search-below", type=unit_interval, default=None,
                        help="register a pair again from its source turned by each of the 23 other rotations of a "
                             "cube (and 24 more about --rotation-search-centre) when fewer than this share of its "
                             "RCPs agree with its estimate (after the second pass), and keep the start whose estimate "
                             "brings the source nearest the target (the median distance to the nearest target "
                             "point): any rotation, at 46 more passes per searched pair (a pass and a second look "
                             f"per start; 94 with a centre); 0: never (default: {default})")
    parser.add_argument("--rotation-search-centre", type=float, nargs=3, default=None, metavar=("Z", "Y", "X"),
                        help="Euler angles (degrees, scipy's 'zyx') of the centre of the rotations the model was "
                             "trained on: where not 0 0 0, the search also starts from the 24 cube rotations "
                             "turned so that one leaves a motion near it (24 more starts); a model file sets it "
                             "from its training rotations (protocol: 22.5 22.5 22.5) "
                             f"(default: {default})")
    parser.add_argument("--rotation-search-polish", type=polish_steps, default=None,
                        help="in the rotation search, this many steps of the polish (below) from every start's "
                             "estimate and from the pair's own before the nearest is kept: finds the motion the "
                             "network leaves 10-15 degrees off from its best start where the clouds' points have "
                             "exact counterparts (noise-free pairs); under noise a polished flip of a round shape "
                             f"can win; 0: none (default: {default})")
    parser.add_argument("--rotation-search-icp-starts", type=icp_starts, default=None,
                        help="after the rotation search and the polish, register each pair the search took on by "
                             "ICP alone (--rotation-search-icp) from this many rotations spread over all rotations, "
                             "and keep its result where it brings the source clearly nearer the target (its median distance "
                             "below 0.85 of the estimate's): for nearly round shapes no "
                             f"start of the network registers (512: about 0.3-1.2 s per searched pair on one core); "
                             f"0: never (default: {default})")
    parser.add_argument("--rotation-search-icp-slides", type=icp_slides, default=None,
                        help="the ICP search's translations per rotation: 1, the one that puts the centroids "
                             f"together; more, also spread along the target's longest axis (+-{SEARCH_ICP_SLIDE_REACH:g} "
                             "standard deviations of its points): for partial views cut from different sides; the "
                             f"ICP search's cost grows with them (default: {default})")
    parser.add_argument("--rotation-search-icp", choices=SEARCH_ICPS, default=None,
                        help="the ICP search's ICP: robust (Cauchy weights, the polish's) or trimmed (each step on "
                             "the nearer half of the nearest-point pairs: holds the truth of noisy partial views "
                             f"where robust ICP drifts) (default: {default})")
    parser.add_argument("--max-rotation", type=turn_bound, default=None, metavar="DEGREES",
                        help="a bound you know on the motion: the angle by which it turns the source (each Euler "
                             "angle within 45 degrees: at most 85.8); with the rotation search, an estimate turning "
                             "further is searched and the search keeps only estimates within it (a flip of a nearly "
                             f"round shape is then not taken); {ANY_ROTATION:g}: no bound (default: {default})")
    parser.add_argument("--rotation-search-turn-penalty", type=turn_penalty, default=None, metavar="P",
                        help="the rotation search and its ICP search count an estimate's distance (1 + P x turn / "
                             "180) times as far, the turn in degrees: of two estimates the geometry can hardly tell "
                             "apart (a flip of a nearly round shape under noise) the smaller motion is kept, one "
                             f"clearly nearer still wins; not a bound; 0: every turn alike (default: {default})")
    parser.add_argument("--polish-iterations", type=polish_steps, default=None,
                        help="last, this many steps of a robust point-to-point ICP from each pair's estimate (each "
                             "source point paired with its nearest target point), kept where they bring the source "
                             "nearer the target: sharpens an estimate a few degrees off, never rescues one far "
                             f"off; 0: never (default: {default})")
    parser.add_argument("--consistency-radius", type=positive_float, default=None,
                        help=f"how near its estimate an RCP must lie to agree with it, in the clouds' units "
                             f"(default: {default})")


def solve_overrides(args) -> dict:
    """The solve fields given on the command line."""
    return {k: getattr(args, k) for k in SOLVE_KEYS if getattr(args, k) is not None}


def add_train(sub) -> None:
    from vrnet_ext.learning.config import PRESETS, SECTIONS

    p = sub.add_parser("train", help="two-stage training on ModelNet40 (DDP under torchrun)",
                       description="Two-stage VRNet training. Start from a preset; any flag overrides it. "
                                   "Under `torchrun --nproc_per_node N` the same command trains with DDP.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("--preset", choices=sorted(PRESETS), default="small",
                   help="paper: batch 28, 100+100 epochs (GPU); cpu: the small model on the full training split at the paper's 768-point views (the shipped model; hours per session on a CPU); small: minutes on a CPU; tiny: seconds (smoke test)")
    for name, section in SECTIONS.items():
        _add_section(p.add_argument_group(f"{name} options"), section)
    model = p.add_argument_group("model options (stored in the checkpoint)")
    unset = "the preset's, else VRNetConfig's"
    preset_default = f" (default: {unset})"
    model.add_argument("--emb-dims", type=int, default=None, help="model embedding size c" + preset_default)
    model.add_argument("--k", type=int, default=None, help="DGCNN neighbours" + preset_default)
    model.add_argument("--iterations", type=int, default=None, help="ICP-like passes at evaluation" + preset_default)
    model.add_argument("--walk-gate", action=Switch, values=True, default=None,
                       help="the walk's offsets are gated per point (right VCPs stay exact); off: the paper's walk"
                            + preset_default)
    model.add_argument("--walk-confidence", action=Switch, values=True, default=None,
                       help="the walk also predicts per-point confidences that weight the Procrustes; "
                            "off: unweighted" + preset_default)
    model.add_argument("--walk-match-stats", action=Switch, values=True, default=None,
                       help="the walk also sees each point's largest matching weight and matching entropy"
                            + preset_default)
    model.add_argument("--walk-confidence-trunk", action=Switch, values=True, default=None,
                       help="the confidence has its own MLP (the offsets' loss L4 does not shape it)"
                            + preset_default)
    add_solve_options(model, unset)


def _add_section(group, section) -> None:
    """One flag per field of a training options section (``--name-with-dashes``), each read as its type
    and described with every preset's value."""
    from vrnet_ext.learning.config import FIELD_HELP, L4_FORMS, PRECISIONS, preset_values

    special = {"classes": {"type": int, "nargs": "+"}, "lr_milestones": {"type": int, "nargs": "+"},
               "setting": {"choices": SETTINGS + (MIXED,)}, "split": {"choices": SPLITS},
               "data_dir": {"type": str}, "out_dir": {"type": output_folder}, "device": {"type": device_or_auto},
               "precision": {"choices": PRECISIONS}, "backend": {"choices": BACKENDS},
               "loss_l4_form": {"choices": L4_FORMS}, "far_points": {"choices": FAR_POINTS},
               "rotation_range": {"choices": ROTATION_RANGES},
               "features_from": {"type": checkpoint_or_shipped}, "walk_from": {"type": checkpoint_or_shipped}}
    hints = typing.get_type_hints(section)
    for f in fields(section):
        add = group.add_argument
        kind = hints[f.name]
        flag = "--" + f.name.replace("_", "-")
        spelled = {True: flag, False: "--no-" + flag[2:]}  # a switch's value as its spelling
        values = {preset: spelled[v] if isinstance(v, bool) else v for preset, v in preset_values(f.name).items()}
        shown = {str(v) for v in values.values()}
        default = (f"default: {next(iter(shown))}" if len(shown) == 1
                   else "default: " + ", ".join(f"{k} {v}" for k, v in values.items()))
        description = FIELD_HELP.get(f.name, f.name) + ("" if shown == {"None"} else f" ({default})")
        reading = special.get(f.name) or ({"action": Switch, "values": True} if kind is bool
                                          else {"type": _value_type(kind)})
        add(flag, default=None, help=DATA_DIR_HELP if f.name == "data_dir" else description, **reading)


def build_train_config(args):
    """TrainConfig from parsed ``vrnet train`` flags: the preset, then every flag given."""
    from vrnet_ext.learning.config import PRESETS, TrainConfig

    model_keys = ("emb_dims", "k", "iterations", "walk_gate", "walk_confidence", "walk_match_stats",
                  "walk_confidence_trunk") + SOLVE_KEYS
    overrides = {k: v for k, v in vars(args).items() if k not in ("command", "preset") + model_keys}
    model = dict(PRESETS[args.preset]["model"])
    for key in model_keys:
        if getattr(args, key) is not None:
            model[key] = getattr(args, key)
    return TrainConfig.from_preset(args.preset, model=model, **overrides)


def run_train(args) -> int:
    from vrnet_ext.learning.train import train

    cfg = build_train_config(args)
    record = train(cfg)
    out_dir = Path(cfg.runtime.out_dir)
    if record.get("stopped"):  # saved and resumable, but not finished: the shell's status of that signal
        return 128 + record.get("signal", 0) if record.get("signal") else 1
    if record:
        summary = ", ".join(f"{k} {record[k]:.4g}" for k in ("val_RMSE(R)", "val_MAE(R)", "val_RMSE(t)") if k in record)
        print(f"last epoch (stage {record['stage']}, epoch {record['epoch']}): {summary}")
    roles = {"last.pt": "last.pt (to --resume)", "best.pt": "best.pt (lowest validation RMSE(R))"}
    written = [roles.get(name, name) for name in ("last.pt", "best.pt", "best_stage1.pt", "best_stage2.pt",
                                                  "metrics.jsonl", "metrics.csv", "curves.png")
               if (out_dir / name).exists()]
    if not record and cfg.start.resume:  # every epoch was already done in the checkpoint: nothing trained
        schedule = cfg.schedule
        print(f"{cfg.start.resume} holds a finished run ({schedule.stage1_epochs} + {schedule.stage2_epochs} epochs): "
              f"nothing to train (give more --stage2-epochs to continue it)")
        print(f"evaluate with: vrnet eval --checkpoint {Path(cfg.start.resume).with_name('best.pt')}")
        return 0
    print(f"wrote {out_dir}/: {', '.join(written)}")
    print(f"evaluate with: vrnet eval --checkpoint {out_dir / 'best.pt'}")
    return 0


def _value_type(hint) -> type:
    """The type a training option's values are read as, from its annotation: ``int``, ``float`` or
    ``str``, also inside ``X | None`` (an annotation the parser does not read is an error here, not a
    silent ``str``)."""
    if hint in (int, float, str):
        return hint
    inner = [arg for arg in typing.get_args(hint) if arg is not type(None)]
    if len(inner) == 1 and inner[0] in (int, float, str):
        return inner[0]
    raise TypeError(f"no command-line type for the annotation {hint!r}")


def add_eval(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a checkpoint on the ModelNet40 test pairs",
                       description="Prints the paper's table (RMSE/MAE of Euler angles and translation) "
                                   "plus isotropic errors, recall, Chamfer distances and match ratios; writes JSON.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="a shipped model name (e.g. vrnet-pv-upc-rcp) or best.pt / last.pt written by `vrnet train` "
                        "(default: the shipped model trained for --setting / --split)")
    p.add_argument("--setting", choices=SETTINGS, default=None,
                   help=f"default: the checkpoint's, else {DEFAULT_SETTING}")
    p.add_argument("--split", choices=SPLITS, default=None, help=f"default: the checkpoint's, else {DEFAULT_SPLIT}")
    p.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    p.add_argument("--batch-size", type=positive_int, default=16, help="pairs per forward")
    p.add_argument("--partition", choices=EVAL_PARTITIONS, default="test",
                   help="test: the test split's pairs (what a paper reports); val: the shapes `vrnet train` holds "
                        "out of the train split to choose checkpoints by (the same pairs as its validation): compare "
                        "fine-tunes and settings there, never on test")
    p.add_argument("--max-items", type=positive_int, default=None,
                   help="evaluate N shapes of --partition spread evenly over it (its classes in proportion; "
                        "default: all of it)")
    p.add_argument("--iterations", type=positive_int, default=None,
                   help="ICP-like passes (paper Table 'with iteration') (default: the model's)")
    add_solve_options(p, "the model's")
    p.add_argument("--far-points", choices=FAR_POINTS, default="prnet",
                   help="partial views: prnet = the paper's: one far point near the diagonal cuts both clouds; "
                        "sphere = in a random direction for each cloud; mixed = one of the two per pair; "
                        "symmetric = the target's far point mirrors the source's (the paper's ablations)")
    p.add_argument("--rotation-range", choices=ROTATION_RANGES, default=None,
                   help=ROTATION_RANGE_HELP + f" (default: the checkpoint's, else {DEFAULT_ROTATION_RANGE})")
    p.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND,
                   help="ext: the compiled kernels; torch: the pure-PyTorch references")
    p.add_argument("--transformer-precision", choices=TRANSFORMER_PRECISIONS, default=TRANSFORMER_PRECISIONS[0],
                   help="the Transformer's products: auto = bfloat16 on a CPU with native bf16 (AVX512-BF16 / AMX), "
                        "else float32 (default: auto)")
    p.add_argument("--device", type=device_or_auto, default=AUTO_DEVICE,
                   help="torch device to run on: auto (cuda when there is one, else cpu), cpu, cuda, cuda:1")
    p.add_argument("--progress", action=Switch, default=True, help="progress bars")
    p.add_argument("--json", type=json_output, default=None,
                   help="output JSON path, - for standard output (default: eval_SETTING_SPLIT.json, "
                        "eval_val_SETTING_SPLIT.json for --partition val, beside a "
                        "checkpoint file, or in the working folder for a shipped model)")


def run_eval(args) -> int:
    with report_to(args.json):
        result, out = _evaluate_and_report(args)
    write_json(out, result)
    return 0


def _evaluate_and_report(args) -> tuple[dict, Path | str]:
    """Evaluates, prints the table -> (the JSON record, where it goes)."""
    from vrnet_ext.data import ModelNet40Pairs, PairSpec
    from vrnet_ext.learning.evaluate import evaluate, format_table, time_inference
    from vrnet_ext.learning.train import resolve_device
    from vrnet_ext.model.pretrained import load_vrnet

    if args.checkpoint is None:
        from vrnet_ext.model.pretrained import model_for

        wanted = (args.setting or DEFAULT_SETTING, args.split or DEFAULT_SPLIT)
        args.checkpoint = model_for(*wanted)
        if args.checkpoint is None:
            raise ValueError(f"no shipped model is trained for setting {wanted[0]} / split {wanted[1]}; "
                             f"give --checkpoint")
    args.device = resolve_device(args.device)
    model, state = load_vrnet(args.checkpoint, args.device)
    cfg = state["config"]
    if args.iterations:
        model.config.iterations = args.iterations
    for key, value in solve_overrides(args).items():
        setattr(model.config, key, value)
    model.config.transformer_precision = args.transformer_precision
    # the paper's protocol unless the checkpoint says otherwise (shipped weights carry no data path)
    setting = args.setting or cfg.get("setting", DEFAULT_SETTING)
    split = args.split or cfg.get("split", DEFAULT_SPLIT)
    if setting == MIXED:
        raise ValueError(f"{args.checkpoint} was trained on every setting: give --setting ({' | '.join(SETTINGS)})")
    rotations = args.rotation_range or cfg.get("rotation_range", DEFAULT_ROTATION_RANGE)
    spec = PairSpec(num_points=cfg.get("num_points", 1024), num_subsampled=cfg.get("num_subsampled", 768),
                    far_points=args.far_points, rotation_range=rotations)
    data = ModelNet40Pairs(args.data_dir or cfg.get("data_dir"), partition=args.partition, setting=setting,
                           split=split, max_items=args.max_items, spec=spec,
                           val_fraction=cfg.get("val_fraction", 0.1))
    model.to(args.device)
    result = evaluate(model, data, batch_size=args.batch_size, device=args.device, backend=args.backend,
                      progress=args.progress)
    result["inference_seconds_per_pair"] = time_inference(model, data, args.device, backend=args.backend)
    result.update(partition=args.partition, setting=setting, split=split, far_points=args.far_points,
                  rotations=rotations,
                  checkpoint=str(args.checkpoint),
                  iterations=model.config.iterations, **{k: getattr(model.config, k) for k in SOLVE_KEYS},
                  transformer_precision=args.transformer_precision,
                  transformer_bf16=model.eval().transformer_in_bf16(data[0]["src"].to(args.device)))
    title = f"VRNet {setting} {split}" + (", validation pairs" if args.partition == "val" else "")
    print(format_table({k: v for k, v in result.items() if isinstance(v, (int, float))}, title))
    prefix = "eval_val" if args.partition == "val" else "eval"
    out = args.json or Path(args.checkpoint).with_name(f"{prefix}_{setting}_{split}.json".replace("+", ""))
    return result, out


def add_plot(sub) -> None:
    p = sub.add_parser("plot", help="plot a training run's curves to RUN_DIR/curves.png",
                       description="Draws the losses and validation errors of every epoch of a `vrnet train` run "
                                   "(its metrics.jsonl) into RUN_DIR/curves.png. Training draws it itself at the end; "
                                   "this redraws it during or after a run.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("run_dir", help="the --out-dir of `vrnet train`")


def run_plot(args) -> int:
    from vrnet_ext.learning.curves import plot_metrics

    print(f"wrote {plot_metrics(args.run_dir)}")
    return 0


def add_export(sub) -> None:
    p = sub.add_parser("export", help="write a checkpoint as shipped float16 weights with a model card",
                       description="Writes OUT_DIR/NAME.pt (float16 weights, the training config without local "
                                   "paths, a card of training facts and metrics) and OUT_DIR/NAME.md (the model "
                                   "card). load_pretrained(NAME) then finds it when OUT_DIR is vrnet_ext/weights.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("checkpoint", help="best.pt / last.pt of `vrnet train` (metrics.jsonl beside it is read too), or "
                                      "shipped weights, whose card is kept and amended by the flags given")
    p.add_argument("name", help="model name, e.g. vrnet-pv-upc-rcp")
    p.add_argument("--out-dir", type=output_folder, default=None,
                   help="folder to write to (default: the package's weights folder)")
    p.add_argument("--test-json", action="append", default=None,
                   help="`vrnet eval --json` output on the test split, or a cell's file of `modelnet40_tables.py "
                        "--card-json-dir` (a VRNet; repeat it for each cell a "
                        "mixed-setting model serves), or a Markdown results table (a scene model), for the card")
    p.add_argument("--summary", default="", help="one paragraph: what the model is for")
    p.add_argument("--cells", nargs="+", default=None, metavar="SETTING/SPLIT",
                   help="the ModelNet40 cells the model serves, chosen on validation pairs (e.g. RS/UPC "
                        "PV+RS/UPC; default: the setting and split it was trained for)")
    p.add_argument("--machine", default=None, help="where it was trained (for the card)")
    p.add_argument("--sessions", type=positive_int, default=None, help="how many sessions the training took")
    p.add_argument("--note", action="append", default=[], help="a note for the card (repeatable)")
    p.add_argument("--drop-notes", action="append", default=[], metavar="PREFIX",
                   help="shipped weights: remove the card's notes that begin with PREFIX, e.g. 'Rotations:', "
                        "before adding the --note ones (repeatable)")
    p.add_argument("--procrustes-points", choices=PROCRUSTES_POINTS, default=None,
                   help="set the exported model's final Procrustes points (an inference-time choice; default: as trained)")
    add_solve_options(p, "as trained")


def _cells(values: list[str]) -> list[str]:
    """``--cells`` values checked: SETTING/SPLIT with a paper setting and split."""
    for value in values:
        setting, _, split = value.partition("/")
        if setting not in SETTINGS or split not in SPLITS:
            raise ValueError(f"--cells {value!r}: give SETTING/SPLIT with SETTING in {SETTINGS} and SPLIT in "
                             f"{SPLITS}")
    return values


def _read_eval_json(path: str) -> dict:
    try:
        test = json.loads(_read_test_results(path))
    except json.JSONDecodeError as exc:
        raise ValueError(f"--test-json {path}: not the JSON of `vrnet eval` ({exc})") from None
    if not isinstance(test, dict):
        raise ValueError(f"--test-json {path}: not the JSON of `vrnet eval` (no object of metrics)")
    return test


def _read_test_results(path: str) -> str:
    try:
        return Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--test-json {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None


def run_export(args) -> int:
    from vrnet_ext.model.checkpoints import model_values, read_checkpoint
    from vrnet_ext.model.config import VRNetConfig
    from vrnet_ext.model.scene import SCENE_FORMAT
    from vrnet_ext.learning.export import affecting, export_pretrained, export_scene_model
    from vrnet_ext.model.pretrained import WEIGHTS_DIR

    out = Path(args.out_dir) if args.out_dir else WEIGHTS_DIR
    state = read_checkpoint(args.checkpoint)
    if state.get("format") == SCENE_FORMAT:
        card = {"summary": args.summary, "notes": args.note,
                "training": {k: v for k, v in (("machine", args.machine), ("sessions", args.sessions)) if v}}
        if args.test_json:
            card["results"] = [line for path in args.test_json for line in _read_test_results(path).splitlines()]
            card["results_note"] = f"From {', '.join(Path(path).name for path in args.test_json)}."
        path = export_scene_model(args.checkpoint, out / f"{args.name}.pt", card)
        print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.md')}")
        return 0
    overrides = solve_overrides(args)
    if args.procrustes_points is not None:
        overrides["procrustes_points"] = args.procrustes_points
    # older files name fewer fields
    served = {**VRNetConfig().to_dict(), **model_values(state["config"], args.checkpoint), **overrides}
    card = _base_card(args, state, affecting(overrides, served))
    if args.cells:
        card["cells"] = _cells(args.cells)
    tests = [_read_eval_json(path) for path in args.test_json or []]
    for path, test in zip(args.test_json or [], tests):
        if test.get("partition", "test") != "test":
            raise ValueError(f"--test-json {path}: measured on the {test['partition']} pairs; a card's test table "
                             f"holds the test split's")
        if test.get("rotations", DEFAULT_ROTATION_RANGE) != DEFAULT_ROTATION_RANGE:
            raise ValueError(f"--test-json {path}: measured on {test['rotations']} rotations; a card's test table "
                             f"holds the paper's protocol ({DEFAULT_ROTATION_RANGE})")
        differing = [k for k in SOLVE_KEYS if k in test and test[k] != served.get(k)]
        if differing:
            raise ValueError(f"--test-json {path}: measured with {', '.join(f'{k} {test[k]}' for k in differing)}, "
                             f"the exported model solves with {', '.join(f'{k} {served.get(k)}' for k in differing)}")
    for test in tests:
        cell = f"{test.get('setting')}/{test.get('split')}"
        metrics = {k: v for k, v in test.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        card.setdefault("tests", {})[cell] = metrics
    if len(tests) == 1:
        test = tests[0]
        card["test"] = card.pop("tests")[f"{test.get('setting')}/{test.get('split')}"]
        card["test_note"] = (f"`{test.get('measured_by', 'vrnet eval')}` on {test.get('pairs')} ModelNet40 test pairs "
                             f"({test.get('setting')} / {test.get('split')}, the whole official test split unless "
                             f"fewer are stated).")
    elif tests:
        card["tests_note"] = ("`vrnet eval` on the ModelNet40 test pairs of each cell (the whole official test split "
                              "unless fewer are stated).")
    path = export_pretrained(args.checkpoint, out / f"{args.name}.pt", card, overrides)
    print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.md')}")
    return 0


def _base_card(args, state: dict, changing: dict) -> dict:
    """The card before test results: from a training run, its facts and the flags; from shipped
    weights (a file with a card), that card, the flags given changing or adding to it (``--drop-notes``
    removing notes first). Shipped weights given inference options that change their estimates
    (``changing``: :func:`vrnet_ext.learning.export.affecting`) need test results measured with them (``--test-json``)."""
    from vrnet_ext.learning.export import training_facts

    if "card" not in state:
        training = training_facts(args.checkpoint, args.name)
        card = {"summary": args.summary, "training": training, "notes": list(args.note)}
    else:
        if changing and not args.test_json:
            raise ValueError("--test-json: shipped weights exported with other inference options need test results "
                             "measured with them (`vrnet eval --json` with the same --irls-* flags)")
        card = {k: v for k, v in state["card"].items() if not (args.test_json and k.startswith("test"))}
        card["summary"] = args.summary or card.get("summary", "")
        kept = [note for note in card.get("notes", []) if not note.startswith(tuple(args.drop_notes))]
        card["notes"] = kept + list(args.note)
        training = card.setdefault("training", {})
    if args.machine:
        training["machine"] = args.machine
    if args.sessions:
        training["sessions"] = args.sessions
    return card


def add_train_scene(sub) -> None:
    p = sub.add_parser("train-scene", help="train the scene model (FPFH + VRNet head) on real scans",
                       description="Self-supervised on SCANS: each step cuts two overlapping views out of one of the "
                                   "scans, turns each by a random rotation and resamples it on its own grid; the "
                                   "network learns to match them. With --real-pairs, also supervised by the ground "
                                   "truth of real pairs (their training pairs; the validation pairs are never used). "
                                   "Resumes from --out when it exists.",
                       formatter_class=DefaultsHelpFormatter)
    p.add_argument("scans", nargs="*", help="point-cloud files (sensor at the origin), e.g. 3DMatch fragments")
    p.add_argument("--real-pairs", type=existing_folder, default=None,
                   help="a real_pairs folder (MANIFEST.tsv, clouds/, gt/): train on its training pairs "
                        "(vrnet_ext.data.real_pairs.split)")
    p.add_argument("--synthetic-share", type=unit_interval, default=0.5,
                   help="with --real-pairs: share of steps on a self-supervised pair cut from a training pair's "
                        "source scan")
    p.add_argument("--out", required=True, type=writable_path, help="checkpoint to write (and resume)")
    p.add_argument("--steps", type=positive_int, default=600, help="training pairs")
    p.add_argument("--points", type=view_points, default=3000,
                   help=f"about this many points per training view (at most {MAX_VIEW_POINTS})")
    p.add_argument("--lr", type=positive_float, default=2e-3, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="seed of the views and rotations")
    p.add_argument("--progress", action=Switch, default=True, help="progress bars")


def run_train_scene(args) -> int:
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.learning.scene_training import SceneTrainConfig, train_scene_model

    if not args.scans and args.real_pairs is None:
        raise ValueError("scans: give point-cloud files, --real-pairs, or both")
    scans = {Path(path).name: read_points(path) for path in args.scans}
    if len(scans) != len(args.scans):
        raise ValueError("scans: give each file once (file names must differ)")
    cfg = SceneTrainConfig(steps=args.steps, points=args.points, lr=args.lr, seed=args.seed)
    provider = None
    if args.real_pairs is not None:
        from vrnet_ext.data.real_pairs import RealPairProvider, read_manifest, split

        provider = RealPairProvider(split(read_manifest(args.real_pairs))[0], args.synthetic_share,
                                    self_supervised=set(scans))
        clash = set(scans) & {pair.pair_id for pair in provider.pairs}
        if clash:
            raise ValueError(f"scans: file names {sorted(clash)} clash with pair ids of --real-pairs")
        scans.update(provider.scans())
    path = train_scene_model(scans, args.out, cfg, progress=args.progress,
                             **({} if provider is None else {"pairs": provider}))
    print(f"wrote {path}")
    return 0
