"""The ``vrnet`` command line: ``vrnet train``, ``vrnet eval``, ``vrnet plot``, ``vrnet register``, ...

The ``vrnet`` executable (:func:`run`) ends a short command's process with ``os._exit`` once its
outputs are written and flushed: the interpreter's own teardown of a process that imported torch
takes ~0.35 s on a 2-core machine (a third of a typical ``vrnet register``) and writes nothing.
Training commands exit normally (DDP process groups and DataLoader workers get their clean-up).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import typing
from dataclasses import fields
from pathlib import Path

from vrnet_ext.data.protocol import FAR_POINTS, MIXED, SETTINGS


def _parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected 1/0/true/false, got {text!r}")


def _int_at_least(low: int):
    """An argparse type: an integer >= ``low``, with an error that says so."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


_positive_int = _int_at_least(1)
_nonnegative_int = _int_at_least(0)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text}")
    return value


def _memory_size(text: str) -> int:
    """A memory size such as 2GB, 512MB, 1.5G or a plain byte count -> bytes."""
    from vrnet_ext.registration.budget import parse_memory_size

    try:
        return parse_memory_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _device(text: str) -> str:
    """A device name torch knows and this machine has (checked before any work starts)."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"not a device name: {text!r} (e.g. cpu, cuda, cuda:1)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text!r}: no CUDA device is available here")
    if device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"{text!r}: only cpu and cuda devices are supported")
    return text


def _train_device(text: str) -> str:
    """``auto`` (CUDA when there is one) or a device of :func:`_device`."""
    return text if text == "auto" else _device(text)


def _output_folder(text: str) -> str:
    """A folder to create or fill: not an existing file, and under a writable existing ancestor."""
    path = Path(text).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file; give a folder")
    ancestor = next(p for p in (path, *path.parents) if p.exists())
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text!r}: {ancestor} is not a writable folder")
    return text


def _writable_path(text: str) -> str:
    """An output file whose folder exists and is writable, and that is not a folder itself (checked
    before the work, not after it)."""
    path = Path(text).expanduser().resolve()
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder; give a file name")
    if not os.access(path.parent, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text!r}: the folder {path.parent} is not writable")
    return text


MAX_VIEW_POINTS = 200_000  # train-scene: the InfoNCE matrix grows as the square of the view's points


def _view_points(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_VIEW_POINTS:
        raise argparse.ArgumentTypeError(f"{value} is more than {MAX_VIEW_POINTS} points per view (memory grows "
                                         f"as its square)")
    return value


DATA_DIR_HELP = ("folder holding modelnet40_1024_{train,test}.h5 (default: $VRNET_DATA/modelnet40, "
                 "else ../shared/data/modelnet40 beside the project)")


def _train_parser(sub) -> None:
    from vrnet_ext.learning.config import FIELD_HELP, L4_FORMS, PRECISIONS, PRESETS, TrainConfig, preset_values

    p = sub.add_parser("train", help="two-stage training on ModelNet40 (DDP under torchrun)",
                       description="Two-stage VRNet training. Start from a preset; any flag overrides it. "
                                   "Under `torchrun --nproc_per_node N` the same command trains with DDP.")
    p.add_argument("--preset", choices=sorted(PRESETS), default="small",
                   help="paper: batch 28, 100+100 epochs (GPU); cpu: the small model on the full training split at the paper's 768-point views (the shipped model; hours per session on a CPU); small: minutes on a CPU; tiny: seconds (smoke test)")
    hints = typing.get_type_hints(TrainConfig)
    for f in fields(TrainConfig):
        if f.name in ("preset", "model", "progress"):
            continue
        flag = "--" + f.name.replace("_", "-")
        kind = hints[f.name]
        values = preset_values(f.name)
        shown = {str(v) for v in values.values()}
        default = (f"default: {shown.pop()}" if len(shown) == 1
                   else "default: " + ", ".join(f"{k} {v}" for k, v in values.items()))
        description = f"{FIELD_HELP.get(f.name, f.name)} ({default})"
        if f.name in ("classes", "lr_milestones"):
            p.add_argument(flag, type=int, nargs="+", default=None, help=description)
        elif f.name == "setting":
            p.add_argument(flag, choices=SETTINGS + (MIXED,), default=None, help=description)
        elif f.name == "split":
            p.add_argument(flag, choices=("UPC", "UC", "ND"), default=None, help=description)
        elif f.name == "data_dir":
            p.add_argument(flag, default=None, help=DATA_DIR_HELP)
        elif f.name == "out_dir":
            p.add_argument(flag, type=_output_folder, default=None, help=description)
        elif f.name == "device":
            p.add_argument(flag, type=_train_device, default=None, help=description)
        elif f.name == "precision":
            p.add_argument(flag, choices=PRECISIONS, default=None, help=description)
        elif f.name == "backend":
            p.add_argument(flag, choices=("ext", "torch"), default=None, help=description)
        elif f.name == "loss_l4_form":
            p.add_argument(flag, choices=L4_FORMS, default=None, help=description)
        elif f.name == "far_points":
            p.add_argument(flag, choices=FAR_POINTS, default=None, help=description)
        elif kind is bool:
            p.add_argument(flag, type=_parse_bool, default=None, help=description)
        else:
            base = int if "int" in str(kind) else float if "float" in str(kind) else str
            p.add_argument(flag, type=base, default=None, help=description)
    p.add_argument("--emb-dims", type=int, default=None, help="model embedding size c")
    p.add_argument("--k", type=int, default=None, help="DGCNN neighbours")
    p.add_argument("--iterations", type=int, default=None, help="ICP-like passes at evaluation")
    p.add_argument("--walk-gate", type=_parse_bool, default=None,
                   help="1: the walk's offsets are gated per point (right VCPs stay exact); 0: the paper's walk")
    p.add_argument("--walk-confidence", type=_parse_bool, default=None,
                   help="1: the walk also predicts per-point confidences that weight the Procrustes; 0: unweighted")
    p.add_argument("--walk-match-stats", type=_parse_bool, default=None,
                   help="1: the walk also sees each point's largest matching weight and matching entropy")
    p.add_argument("--walk-confidence-trunk", type=_parse_bool, default=None,
                   help="1: the confidence has its own MLP (the offsets' loss L4 does not shape it)")
    p.add_argument("--irls-iterations", type=int, default=None,
                   help="Cauchy reweighting steps after the Procrustes solve (0: none)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def build_train_config(args):
    """TrainConfig from parsed ``vrnet train`` flags: the preset, then every flag given."""
    from vrnet_ext.learning.config import PRESETS, TrainConfig

    model_keys = ("emb_dims", "k", "iterations", "walk_gate", "walk_confidence", "walk_match_stats",
                  "walk_confidence_trunk", "irls_iterations")
    overrides = {k: v for k, v in vars(args).items() if k not in ("command", "preset", "no_progress") + model_keys}
    model = dict(PRESETS[args.preset]["model"])
    for key in model_keys:
        if getattr(args, key) is not None:
            model[key] = getattr(args, key)
    return TrainConfig.from_preset(args.preset, model=model, progress=not args.no_progress, **overrides)


def _run_train(args) -> int:
    from vrnet_ext.learning.train import train

    cfg = build_train_config(args)
    record = train(cfg)
    out_dir = Path(cfg.out_dir)
    if record.get("stopped"):  # saved and resumable, but not finished: the shell's status of that signal
        return 128 + record.get("signal", 0) if record.get("signal") else 1
    if record:
        summary = ", ".join(f"{k} {record[k]:.4g}" for k in ("val_RMSE(R)", "val_MAE(R)", "val_RMSE(t)") if k in record)
        print(f"last epoch (stage {record['stage']}, epoch {record['epoch']}): {summary}")
    roles = {"last.pt": "last.pt (to --resume)", "best.pt": "best.pt (lowest validation RMSE(R))"}
    written = [roles.get(name, name) for name in ("last.pt", "best.pt", "best_stage1.pt", "best_stage2.pt",
                                                  "metrics.jsonl", "metrics.csv", "curves.png")
               if (out_dir / name).exists()]
    print(f"wrote {out_dir}/: {', '.join(written)}")
    print(f"evaluate with: vrnet eval --checkpoint {out_dir / 'best.pt'}")
    return 0


def _eval_parser(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a checkpoint on the ModelNet40 test pairs",
                       description="Prints the paper's table (RMSE/MAE of Euler angles and translation) "
                                   "plus isotropic errors, recall, Chamfer distances and match ratios; writes JSON.")
    p.add_argument("--checkpoint", default=None,
                   help="a shipped model name (e.g. vrnet-pv-upc-rcp) or best.pt / last.pt written by `vrnet train` "
                        "(default: the shipped model trained for --setting / --split)")
    p.add_argument("--setting", choices=SETTINGS, default=None, help="default: the checkpoint's, else PV")
    p.add_argument("--split", choices=("UPC", "UC", "ND"), default=None, help="default: the checkpoint's, else UPC")
    p.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--max-items", type=_positive_int, default=None,
                   help="evaluate the first N test shapes only (default: the whole test split)")
    p.add_argument("--iterations", type=int, default=None, help="ICP-like passes (paper Table 'with iteration')")
    p.add_argument("--far-points", choices=FAR_POINTS, default="prnet",
                   help="partial views: prnet = the paper's far points near the diagonal; sphere = in a random "
                        "direction for each cloud; mixed = one of the two per pair")
    p.add_argument("--backend", choices=("ext", "torch"), default="ext",
                   help="ext: the compiled kernels; torch: the pure-PyTorch references")
    p.add_argument("--device", default="cpu", help="torch device to run on, e.g. cpu or cuda")
    p.add_argument("--json", default=None,
                   help="output JSON path (default: eval_SETTING_SPLIT.json beside a checkpoint file, or in the "
                        "working folder for a shipped model)")


def _run_eval(args) -> int:
    from vrnet_ext.data import ModelNet40Pairs, PairSpec
    from vrnet_ext.learning.evaluate import evaluate, format_table, time_inference
    from vrnet_ext.model.pretrained import load_vrnet

    if args.checkpoint is None:
        from vrnet_ext.model.pretrained import model_for

        wanted = (args.setting or "PV", args.split or "UPC")
        args.checkpoint = model_for(*wanted)
        if args.checkpoint is None:
            raise ValueError(f"no shipped model is trained for setting {wanted[0]} / split {wanted[1]}; "
                             f"give --checkpoint")
    model, state = load_vrnet(args.checkpoint, args.device)
    cfg = state["config"]
    if args.iterations:
        model.config.iterations = args.iterations
    # the paper's protocol unless the checkpoint says otherwise (shipped weights carry no data path)
    setting, split = args.setting or cfg.get("setting", "PV"), args.split or cfg.get("split", "UPC")
    spec = PairSpec(num_points=cfg.get("num_points", 1024), num_subsampled=cfg.get("num_subsampled", 768),
                    far_points=args.far_points)
    data = ModelNet40Pairs(args.data_dir or cfg.get("data_dir"), partition="test", setting=setting, split=split,
                           max_items=args.max_items, seed=cfg.get("seed", 1234), spec=spec)
    model.to(args.device)
    result = evaluate(model, data, args.batch_size, args.device, args.backend)
    result["inference_seconds_per_pair"] = time_inference(model, data, args.device, backend=args.backend)
    result.update(setting=setting, split=split, far_points=args.far_points, checkpoint=str(args.checkpoint),
                  iterations=model.config.iterations)
    print(format_table({k: v for k, v in result.items() if isinstance(v, (int, float))}, f"VRNet {setting} {split}"))
    out = Path(args.json) if args.json else Path(args.checkpoint).with_name(f"eval_{setting}_{split}.json".replace("+", ""))
    _write_json(out, result)
    return 0


def _plot_parser(sub) -> None:
    p = sub.add_parser("plot", help="plot a training run's curves to RUN_DIR/curves.png")
    p.add_argument("run_dir", help="the --out-dir of `vrnet train`")


def _run_plot(args) -> int:
    from vrnet_ext.learning.curves import plot_metrics

    print(f"wrote {plot_metrics(args.run_dir)}")
    return 0


def _register_parser(sub) -> None:
    from vrnet_ext.registration.global_estimators import DEFAULT_METHOD, GLOBAL_ESTIMATORS

    p = sub.add_parser(
        "register", help="register two real scans (PLY, PCD, NPY, XYZ/TXT/PTS/CSV, KITTI .bin)",
        description="Estimates the rigid transform taking SOURCE onto TARGET: a global estimate (--method sc2: "
                    "FPFH matches filtered by spatial consistency, the default; --method fpfh: FPFH + RANSAC; "
                    "--method vrnet: the shipped scene model, FPFH descriptors under VRNet's head, or --checkpoint, "
                    "with ICP also started from sc2's estimate and the better fit kept; --method fgr: FPFH + Fast "
                    "Global Registration; --method icp: none), refined by ICP (--estimator) on voxel-downsampled "
                    "clouds. --max-memory sizes everything to a memory budget. Prints the 4x4 transform (source -> "
                    "target); --json, --out and --plot write the result, the moved source and a picture.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("source", help="point-cloud file to move")
    p.add_argument("target", help="point-cloud file to align to (same unit)")
    p.add_argument("--method", choices=GLOBAL_ESTIMATORS, default=argparse.SUPPRESS,
                   help=f"global estimate (default: {DEFAULT_METHOD}, the best recall on the real pairs of "
                        f"benchmarks/bench_real_pairs.py; vrnet when --checkpoint is given, fpfh with --fpfh)")
    initial = p.add_mutually_exclusive_group()
    initial.add_argument("--checkpoint", default=None,
                         help="with --method vrnet: shipped model name or checkpoint (a scene model of `vrnet "
                              "train-scene`, or best.pt of `vrnet train`); default: the shipped scene model")
    initial.add_argument("--fpfh", action="store_true", help="the same as --method fpfh")
    p.add_argument("--global-points", "--fpfh-points", dest="global_points", type=_positive_int, default=5000,
                   help="about this many points per scan for the global estimate (scene model, FPFH)")
    p.add_argument("--max-memory", type=_memory_size, default=None,
                   help="peak memory budget of the whole run, e.g. 2GB or 512MB: sizes the point counts "
                        "and fails at once if the budget cannot be met")
    p.add_argument("--network-points", type=_positive_int, default=1024, help="points per cloud fed to VRNet")
    p.add_argument("--icp-points", type=_positive_int, default=50_000,
                   help="about this many points per cloud for ICP")
    p.add_argument("--voxel-size", type=_positive_float, default=None,
                   help="ICP voxel edge, in the scans' unit (default: from --icp-points)")
    p.add_argument("--max-distance", type=_positive_float, default=None,
                   help="ICP inlier reach, in the scans' unit (default: 3 voxels)")
    p.add_argument("--icp-iterations", type=_nonnegative_int, default=50, help="0: no ICP")
    p.add_argument("--icp-tolerance", type=_positive_float, default=1e-4,
                   help="ICP stops when a step moves the transform by less (radians; the scans' unit)")
    p.add_argument("--coarse-start", action=argparse.BooleanOptionalAction, default=True,
                   help="ICP from no motion first runs on 4x coarser voxels with a 4x longer reach")
    p.add_argument("--estimator", choices=("point_to_point", "point_to_plane", "gicp"), default="point_to_plane",
                   help="ICP step: point-to-point (Kabsch), point-to-plane, or plane-to-plane (GICP)")
    p.add_argument("--gt", default=None, help="ground-truth 4x4 transform file: report the errors")
    p.add_argument("--json", type=_writable_path, default=None, help="write the result here")
    p.add_argument("--out", type=_writable_path, default=None, help="write the moved source as a PLY here")
    p.add_argument("--plot", type=_writable_path, default=None, help="write top/side views (PNG) here")
    p.add_argument("--backend", choices=("ext", "torch"), default="ext",
                   help="ext: the compiled kernels; torch: the pure-PyTorch references")
    p.add_argument("--device", type=_device, default="cpu", help="torch device to run on, e.g. cpu or cuda")
    p.add_argument("--seed", type=int, default=0, help="seed of the global estimate's sampling")


INITIAL_NAMES = {"vrnet": "VRNet", "fpfh": "FPFH + RANSAC", "sc2": "FPFH + spatial consistency", "fgr": "FPFH + FGR",
                 "icp": "identity"}


def _run_register(args) -> int:
    import numpy as np

    from vrnet_ext.geometry.io import read_points, read_transform, write_ply
    from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL
    from vrnet_ext.registration import IcpSettings, register, transform_errors
    from vrnet_ext.registration.global_estimators import DEFAULT_METHOD
    from vrnet_ext.geometry.transforms import apply

    if args.max_memory is not None:
        from vrnet_ext.registration.budget import require_headroom

        require_headroom(args.max_memory)
    method = getattr(args, "method", None) or ("fpfh" if args.fpfh else "vrnet" if args.checkpoint else DEFAULT_METHOD)
    if args.fpfh and method != "fpfh" or args.checkpoint and method != "vrnet":
        raise ValueError(f"--method {method} does not take {'--fpfh' if args.fpfh else '--checkpoint'}")
    model = None
    if method == "vrnet":  # before the scans: a bad checkpoint fails at once
        from vrnet_ext.model.pretrained import load_model

        model = load_model(args.checkpoint or DEFAULT_SCENE_MODEL, args.device)[0]
    src, tgt = read_points(args.source), read_points(args.target)
    truth = read_transform(args.gt) if args.gt else None
    icp_settings = IcpSettings(estimator=args.estimator, points=args.icp_points, voxel_size=args.voxel_size,
                               max_distance=args.max_distance, max_iterations=args.icp_iterations,
                               transform_tolerance=args.icp_tolerance, coarse_start=args.coarse_start)
    result = register(src, tgt, method=method, model=model, global_points=args.global_points,
                      network_points=args.network_points, icp_settings=icp_settings, seed=args.seed,
                      device=args.device, backend=args.backend, max_memory=args.max_memory)
    record = result.to_dict()
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    record.update(source=str(args.source), target=str(args.target), peak_rss_mb=peak_mb,
                  checkpoint=args.checkpoint or (DEFAULT_SCENE_MODEL if method == "vrnet" else None))
    unconverged = " (not converged)" if result.iterations and not result.converged else ""
    print(f"source {len(src)} points, target {len(tgt)} points; "
          f"initial estimate: {INITIAL_NAMES[result.start or method]}; "
          f"ICP ({result.estimator}) iterations {result.iterations}{unconverged}, "
          f"fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse:.4g}; "
          f"{sum(result.seconds.values()):.1f} s, peak memory {peak_mb:.0f} MB")
    for warning in result.warnings:  # the library names its arguments; the command's user knows the flags
        for argument, flag in (("IcpSettings.max_iterations", "--icp-iterations"), ("max_distance", "--max-distance")):
            warning = warning.replace(argument, flag)
        print(f"vrnet register: warning: {warning}", file=sys.stderr)
    print("transform (source -> target):")
    print(np.array2string(result.T_target_source, precision=6, suppress_small=True))
    if truth is not None:
        record["errors_initial"] = transform_errors(result.initial, truth)
        record["errors"] = transform_errors(result.T_target_source, truth)
        for label in ("errors_initial", "errors"):
            e = record[label]
            print(f"{label}: rotation {e['rotation_error_deg']:.3f} deg, translation {e['translation_error']:.4g}")
        swapped = transform_errors(result.T_target_source, np.linalg.inv(truth))
        if swapped["rotation_error_deg"] < 0.2 * record["errors"]["rotation_error_deg"] and \
                record["errors"]["rotation_error_deg"] > 2.0:
            print(f"vrnet register: warning: the estimate matches the inverse of --gt {args.gt} far better "
                  f"({swapped['rotation_error_deg']:.2f} deg): --gt must map SOURCE into TARGET's frame; this one "
                  f"seems to map TARGET into SOURCE's", file=sys.stderr)
    if args.out:
        write_ply(args.out, apply(result.T_target_source, src))
        print(f"wrote {args.out}")
    if args.plot:
        from vrnet_ext.plots import plot_registration

        views = {"initial": result.initial, "final": result.T_target_source}
        print(f"wrote {plot_registration(src, tgt, views, args.plot)}")
    if args.json:
        _write_json(args.json, record)
    return 0


def _write_json(path: str | Path, record: dict) -> None:
    from vrnet_ext.geometry.atomic import atomic_output

    with atomic_output(path) as temporary:
        temporary.write_text(json.dumps(record, indent=1))
    print(f"wrote {path}")


def _demo_parser(sub) -> None:
    p = sub.add_parser("demo", help="register a few pairs with the shipped model (no data needed)",
                       description="Builds pairs with the paper's protocol (768-point partial views, angles in "
                                   "[0, 45) deg) from procedural chairs, or from ModelNet40 test shapes with "
                                   "--data-dir, registers them with a shipped model, prints the errors and times "
                                   "and draws the first pair.",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--model", default=None,
                   help="shipped model name or checkpoint path (default: the shipped PV/UPC model)")
    p.add_argument("--data-dir", default=None, help="use ModelNet40 test shapes from this folder instead")
    p.add_argument("--pairs", type=int, default=4, help="pairs to register")
    p.add_argument("--seed", type=int, default=0, help="seed of the shapes and motions")
    p.add_argument("--out", default="demo.png", help="picture of the first pair")
    p.add_argument("--json", default=None, help="also write the results here")


def _run_demo(args) -> int:
    from vrnet_ext.model.pretrained import load_vrnet
    from vrnet_ext.demo import run_demo
    from vrnet_ext.model.pretrained import DEFAULT_MODEL

    name = args.model or DEFAULT_MODEL
    model, _ = load_vrnet(name)
    result = run_demo(model, args.pairs, args.seed, args.data_dir, args.out)
    print(f"model {name}; {result['shapes']}")
    print(f"{'pair':>4} {'true angle':>11} {'rot. error':>11} {'VCP-only':>9} {'transl. error':>14} {'time':>8}")
    for row in result["pairs"]:
        print(f"{row['pair']:>4} {row['true_angle_deg']:>9.1f}°  {row['rotation_error_deg']:>9.3f}° "
              f"{row['vcp_only_rotation_error_deg']:>8.3f}° {row['translation_error']:>14.4f} {row['seconds']:>7.3f}s")
    print(f"mean rotation error {result['mean_rotation_error_deg']:.3f}°, mean translation error "
          f"{result['mean_translation_error']:.4f}, median {result['median_seconds_per_pair']:.3f} s per pair")
    if result.get("plot"):
        print(f"wrote {result['plot']}")
    if args.json:
        _write_json(args.json, result)
    return 0


def _export_parser(sub) -> None:
    p = sub.add_parser("export", help="write a checkpoint as shipped float16 weights with a model card",
                       description="Writes OUT_DIR/NAME.pt (float16 weights, the training config without local "
                                   "paths, a card of training facts and metrics) and OUT_DIR/NAME.md (the model "
                                   "card). load_pretrained(NAME) then finds it when OUT_DIR is vrnet_ext/weights.",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("checkpoint", help="best.pt / last.pt of `vrnet train` (metrics.jsonl beside it is read too)")
    p.add_argument("name", help="model name, e.g. vrnet-pv-upc-rcp")
    p.add_argument("--out-dir", type=_output_folder, default=None,
                   help="folder to write to (default: the package's weights folder)")
    p.add_argument("--test-json", default=None, help="`vrnet eval --json` output on the test split (a VRNet), or a Markdown results table (a scene model), for the card")
    p.add_argument("--summary", default="", help="one paragraph: what the model is for")
    p.add_argument("--machine", default=None, help="where it was trained (for the card)")
    p.add_argument("--sessions", type=_positive_int, default=None, help="how many sessions the training took")
    p.add_argument("--note", action="append", default=[], help="a note for the card (repeatable)")
    p.add_argument("--procrustes-points", choices=("rcp", "vcp"), default=None,
                   help="set the exported model's final Procrustes points (an inference-time choice; default: as trained)")
    p.add_argument("--irls-iterations", type=_nonnegative_int, default=None,
                   help="set the exported model's Cauchy reweighting steps (default: as trained)")


def _read_test_results(path: str) -> str:
    try:
        return Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--test-json {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None


def _run_export(args) -> int:
    from vrnet_ext.model.checkpoints import read_checkpoint
    from vrnet_ext.model.scene import SCENE_FORMAT
    from vrnet_ext.learning.export import export_pretrained, export_scene_model, training_facts
    from vrnet_ext.model.pretrained import WEIGHTS_DIR

    out = Path(args.out_dir) if args.out_dir else WEIGHTS_DIR
    if read_checkpoint(args.checkpoint).get("format") == SCENE_FORMAT:
        card = {"summary": args.summary, "notes": args.note,
                "training": {k: v for k, v in (("machine", args.machine), ("sessions", args.sessions)) if v}}
        if args.test_json:
            card["results"] = _read_test_results(args.test_json).splitlines()
            card["results_note"] = f"From {Path(args.test_json).name}."
        path = export_scene_model(args.checkpoint, out / f"{args.name}.pt", card)
        print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.md')}")
        return 0
    training = training_facts(args.checkpoint)
    if args.machine:
        training["machine"] = args.machine
    if args.sessions:
        training["sessions"] = args.sessions
    card = {"summary": args.summary, "training": training, "notes": args.note}
    if args.test_json:
        try:
            test = json.loads(_read_test_results(args.test_json))
        except json.JSONDecodeError as exc:
            raise ValueError(f"--test-json {args.test_json}: not the JSON of `vrnet eval` ({exc})") from None
        if not isinstance(test, dict):
            raise ValueError(f"--test-json {args.test_json}: not the JSON of `vrnet eval` (no object of metrics)")
        card["test"] = {k: v for k, v in test.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        card["test_note"] = (f"`vrnet eval` on {test.get('pairs')} ModelNet40 test pairs ({test.get('setting')} / "
                             f"{test.get('split')}, the whole official test split unless fewer are stated).")
    overrides = {k: getattr(args, k) for k in ("procrustes_points", "irls_iterations") if getattr(args, k) is not None}
    path = export_pretrained(args.checkpoint, out / f"{args.name}.pt", card, overrides)
    print(f"wrote {path} ({path.stat().st_size / 2**20:.2f} MB) and {path.with_suffix('.md')}")
    return 0


def _train_scene_parser(sub) -> None:
    p = sub.add_parser("train-scene", help="train the scene model (FPFH + VRNet head) on real scans",
                       description="Self-supervised: each step cuts two overlapping views out of one of the scans, "
                                   "turns each by a random rotation and resamples it on its own grid; the network "
                                   "learns to match them. No pair of different scans is used. Resumes from --out "
                                   "when it exists.",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("scans", nargs="+", help="point-cloud files (sensor at the origin), e.g. 3DMatch fragments")
    p.add_argument("--out", required=True, type=_writable_path, help="checkpoint to write (and resume)")
    p.add_argument("--steps", type=_positive_int, default=600, help="training pairs")
    p.add_argument("--points", type=_view_points, default=3000,
                   help=f"about this many points per training view (at most {MAX_VIEW_POINTS})")
    p.add_argument("--lr", type=_positive_float, default=2e-3, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="seed of the views and rotations")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_train_scene(args) -> int:
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.learning.scene_training import SceneTrainConfig, train_scene_model

    scans = {Path(path).name: read_points(path) for path in args.scans}
    if len(scans) != len(args.scans):
        raise ValueError("scans: give each file once (file names must differ)")
    cfg = SceneTrainConfig(steps=args.steps, points=args.points, lr=args.lr, seed=args.seed)
    path = train_scene_model(scans, args.out, cfg, progress=not args.no_progress)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from vrnet_ext import __version__

    parser = argparse.ArgumentParser(prog="vrnet", description="VRNet point-cloud registration (vrnet_ext).")
    parser.add_argument("--version", action="version", version=f"vrnet_ext {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _train_parser(sub)
    _eval_parser(sub)
    _plot_parser(sub)
    _register_parser(sub)
    _demo_parser(sub)
    _export_parser(sub)
    _train_scene_parser(sub)
    return parser


def _print_warning(command: str):
    """A ``warnings.showwarning`` that prints one line ``vrnet COMMAND: warning: ...`` (no source line)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"vrnet {command}: warning: {message}", file=sys.stderr)
    return show


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import warnings

    previous, warnings.showwarning = warnings.showwarning, _print_warning(args.command)
    try:
        return _dispatch(args)
    finally:
        warnings.showwarning = previous


def _dispatch(args) -> int:
    try:
        commands = {"train": _run_train, "eval": _run_eval, "plot": _run_plot, "register": _run_register,
                    "demo": _run_demo, "export": _run_export, "train-scene": _run_train_scene}
        return commands[args.command](args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"vrnet {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that could not be written (atomic_output names it)
        print(f"vrnet {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"vrnet {args.command}: error: out of memory (use fewer points: --icp-points, --network-points, "
              f"--batch-size)", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"vrnet {args.command}: error: {first_line}", file=sys.stderr)
        return 1


TRAINING_COMMANDS = ("train", "train-scene")


def run() -> None:
    """The ``vrnet`` executable: :func:`main`, then the process ends (see the module docstring)."""
    try:
        status = main()
    except SystemExit as exc:  # argparse's --help and usage errors (an int code, the message printed)
        if exc.code is None or isinstance(exc.code, int):
            status = exc.code or 0
        else:
            print(exc.code, file=sys.stderr)
            status = 1
    sys.stdout.flush()
    sys.stderr.flush()
    if len(sys.argv) > 1 and sys.argv[1] in TRAINING_COMMANDS:
        sys.exit(status)
    os._exit(status)


if __name__ == "__main__":
    run()
