"""The paper's ModelNet40 tables (I: consistent clouds, II: PV / RS / PV+RS) for our methods, in one run.

    python benchmarks/modelnet40_tables.py [--models vrnet-pv-upc-rcp ...] [--data-dir DIR] [--max-items N]
                                            [--methods vrnet vcp icp fpfh] [--rotation-range protocol] [--swap]
                                            [--json tables.json] [--markdown tables.md]

For every model (a shipped name or a checkpoint path; default: every shipped model) the setting and
split it was trained for (every setting of its split for a model trained on ``mixed`` settings, or
those of ``--settings``) define the test pairs: ``ModelNet40Pairs(partition="test")`` with seed
1234, the same deterministic pairs for every method, their rotations drawn as ``--rotation-range``
says (the paper's ``protocol``: each Euler angle in [0, 45] degrees; ``symmetric``: in [-45, 45];
``so3``: uniform over all rotations; ``rotations`` in the JSON). Methods:

* ``vrnet``: the model's own estimate (RCPs, weighted when the model has a confidence head, with the
  robust solve, the rotation search and the second pass its file names, or the solve flags given:
  ``solve`` in the JSON);
* ``vcp``: Kabsch on the VCPs of one forward pass (the network without its walk: DCP-v2's
  estimator on our features), never a second pass or a search;
* ``vrnet2`` (not run by default): the network twice per pair, the second pass registering the
  source moved by the first estimate (the paper's "VRNet with iteration", no further pass; its main
  tables are one pass, so this row is never the one compared with them);
* ``icp``: point-to-point ICP from the identity (``registration.icp``: 50 iterations, every pair within
  ``--icp-max-distance`` = 1.0 counts, i.e. the shapes' radius);
* ``fpfh``: FPFH + RANSAC (``registration.ransac.fpfh_ransac``) with a ``--fpfh-voxel`` of 0.05: normals
  from 30 neighbours, features within 0.25, inliers within 0.075 (Open3D's tutorial ratios).

``--swap`` registers every pair the other way round (the target onto the source, whose motion is
the inverse; ``swapped`` in the JSON). Failures of ICP / RANSAC (too few pairs or inliers) count as
the identity. Errors are the paper's
(RMSE / MAE of the 'zyx' Euler angles in degrees, of the translation) plus the mean isotropic
rotation error; the time per pair is wall time over the pairs (the network batched by
``--batch-size``). The paper's numbers are printed beside ours. Writes Markdown and JSON.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter
from vrnet_ext.cli.training import ROTATION_RANGE_HELP, add_solve_options, solve_overrides
from vrnet_ext.data import ModelNet40Pairs, PairSpec
from vrnet_ext.data.modelnet import SPLITS
from vrnet_ext.data.protocol import MIXED, SETTINGS, VIEW_PROTOCOL
from vrnet_ext.registration.ransac import fpfh_ransac
from vrnet_ext.geometry.metrics import summarize
from vrnet_ext.learning.export import INFERENCE_FIELDS
from vrnet_ext.model import VRNetConfig
from vrnet_ext.ops import kabsch
from vrnet_ext.model.checkpoints import model_values, read_checkpoint
from vrnet_ext.model.pretrained import available, cells, load_vrnet, weights_path
from vrnet_ext.names import DEFAULT_ROTATION_RANGE, ROTATION_RANGES
from vrnet_ext.registration import IcpFailure, IcpSettings, icp
from outputs import cpu_description  # benchmarks/, the script's folder

METHODS = ("vrnet", "vcp", "vrnet2", "icp", "fpfh")
LABELS = {"vrnet": "VRNet (ours)", "vcp": "VCP-only, same network (DCP-v2 estimator)",
          "vrnet2": "VRNet, 2 passes (ours; the paper's iteration mode)",
          "icp": "ICP from the identity (ours)", "fpfh": "FPFH + RANSAC (ours)"}
COLUMNS = ("RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)", "RE mean (deg)")
# The paper's Tables I (CO) and II (PV, RS, PV+RS), as printed: per method, RMSE(R), MAE(R),
# RMSE(t), MAE(t), each for UPC, UC and ND. Table I gives translation errors x 1e-4.
PAPER_TABLES = {
    "CO": (1e-4, {
        "ICP": (12.282, 12.707, 11.971, 4.613, 5.075, 4.497, 477.44, 485.32, 483.20, 22.80, 23.55, 43.35),
        "FGR": (20.054, 21.323, 18.359, 7.146, 8.077, 6.367, 441.21, 457.77, 391.01, 164.20, 18.07, 144.87),
        "PTLK": (13.751, 15.901, 15.692, 3.893, 4.032, 3.992, 199.00, 261.15, 239.58, 44.52, 62.13, 56.37),
        "DCP-v2": (1.094, 3.256, 8.417, 0.752, 2.102, 5.685, 17.17, 63.17, 318.37, 11.73, 46.29, 233.70),
        "PRNet": (1.722, 3.060, 3.218, 0.665, 1.326, 1.446, 63.72, 100.95, 111.78, 46.52, 75.89, 83.78),
        "VRNet": (0.091, 0.209, 2.558, 0.012, 0.028, 1.016, 2.97, 7.83, 57.02, 0.47, 0.99, 28.97)}),
    "PV": (1.0, {
        "ICP": (33.683, 34.894, 35.067, 25.045, 25.455, 25.564, 0.293, 0.293, 0.294, 0.250, 0.251, 0.250),
        "FGR": (11.238, 9.932, 27.653, 2.832, 1.952, 13.794, 0.030, 0.038, 0.070, 0.008, 0.007, 0.039),
        "PTLK": (16.735, 22.943, 19.939, 7.550, 9.655, 9.076, 0.045, 0.061, 0.057, 0.025, 0.033, 0.032),
        "DCP-v2": (6.709, 9.769, 6.883, 4.448, 6.954, 4.534, 0.027, 0.034, 0.028, 0.020, 0.025, 0.021),
        "PRNet": (3.199, 4.986, 4.323, 1.454, 2.329, 2.051, 0.016, 0.021, 0.017, 0.010, 0.015, 0.012),
        "VRNet": (0.982, 2.121, 3.615, 0.496, 0.585, 1.637, 0.0061, 0.0063, 0.0101, 0.0039, 0.0039, 0.0063)}),
    "RS": (1.0, {
        "ICP": (11.247, 12.723, 11.472, 4.531, 5.289, 4.752, 0.0421, 0.0454, 0.0430, 0.0232, 0.0231, 0.0249),
        "FGR": (19.293, 19.62, 37.452, 7.054, 7.566, 23.230, 0.0414, 0.0433, 360.6727, 0.0157, 0.0167, 6.0463),
        "DCP-v2": (5.018, 6.015, 5.536, 2.921, 3.964, 3.162, 0.0116, 0.0147, 0.0127, 0.0087, 0.0112, 0.0096),
        "PRNet": (4.851, 3.484, 3.824, 2.429, 1.764, 1.781, 0.0174, 0.0129, 0.0128, 0.0134, 0.0100, 0.0099),
        "VRNet": (1.496, 5.651, 3.099, 0.593, 1.971, 1.476, 0.0025, 0.0041, 0.0077, 0.0016, 0.0071, 0.0057)}),
    "PV+RS": (1.0, {
        "ICP": (11.971, 13.669, 12.215, 5.298, 6.018, 5.624, 0.0499, 0.0521, 0.0502, 0.0296, 0.0287, 0.0309),
        "FGR": (7.837, 9.187, 32.491, 2.076, 2.017, 14.680, 0.0167, 0.0168, 0.0604, 0.0063, 0.0065, 0.0360),
        "DCP-v2": (5.818, 7.059, 6.286, 3.399, 4.564, 3.844, 0.0184, 0.0176, 0.0222, 0.0138, 0.0131, 0.0168),
        "PRNet": (4.924, 3.836, 4.519, 2.573, 1.901, 1.925, 0.0162, 0.0163, 0.0139, 0.0112, 0.0112, 0.0099),
        "VRNet": (1.109, 1.842, 2.411, 0.513, 0.702, 1.020, 0.0037, 0.0045, 0.0072, 0.0023, 0.0026, 0.0050)}),
}
# (setting, split) -> method -> (RMSE(R), MAE(R), RMSE(t), MAE(t)) in plain units.
PAPER = {(setting, split): {method: (row[k], row[3 + k], row[6 + k] * scale, row[9 + k] * scale)
                            for method, row in rows.items()}
         for setting, (scale, rows) in PAPER_TABLES.items() for k, split in enumerate(SPLITS)}


class Swapped(Dataset):
    """A dataset of pairs the other way round: src and tgt exchanged, the motion inverted."""

    def __init__(self, pairs: Dataset) -> None:
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict:
        item = self.pairs[index]
        inverse = item["rotation"].T
        return {"src": item["tgt"], "tgt": item["src"], "rotation": inverse.contiguous(),
                "translation": -(inverse @ item["translation"])}


# The eval-mode steps after the passes, each switched off: the second look, the rotation search (and its
# polish of the starts), the polish.
LATER_STEPS_OFF = {"second_pass_below": 0.0, "rotation_search_below": 0.0, "rotation_search_polish": 0,
                   "rotation_search_icp_starts": 0, "polish_iterations": 0}


def network_estimates(model, data, batch_size: int, methods) -> dict:
    """{method: (R (S, 3, 3), t (S, 3), seconds, {share of pairs whose estimate came from a second
    pass, from a turned start of the rotation search, moved by the polish})} for the network's
    methods: "vrnet" as the model is configured; "vcp" from one pass without a second, a search or
    a polish (sharing the forward of "vrnet" when that has none of them); "vrnet2" runs the network
    twice per pair (the paper's iteration mode, none of the later steps)."""
    loader = DataLoader(data, batch_size=batch_size, shuffle=False)
    estimates = {}
    config = model.config
    configured = {"iterations": config.iterations, **{key: getattr(config, key) for key in LATER_STEPS_OFF}}
    one_pass = configured == {**configured, **LATER_STEPS_OFF}
    groups = [(configured, ("vrnet", "vcp") if one_pass else ("vrnet",)),
              ({**configured, **LATER_STEPS_OFF}, () if one_pass else ("vcp",)),
              ({"iterations": 2, **LATER_STEPS_OFF}, ("vrnet2",))]
    for settings, names in groups:
        names = [m for m in names if m in methods]
        if not names:
            continue
        rotations, translations = {m: [] for m in names}, {m: [] for m in names}
        seconds, counts = 0.0, dict.fromkeys(("second_pass_share", "turned_share", "polished_share",
                                              "icp_search_share"), 0)
        passes = settings["iterations"]
        for key, value in settings.items():
            setattr(config, key, value)
        try:
            with torch.no_grad():
                for batch in tqdm(loader, desc=f"network ({passes} pass{'es' if passes > 1 else ''})", leave=False):
                    started = time.perf_counter()
                    out = model(batch["src"], batch["tgt"])
                    seconds += time.perf_counter() - started
                    counts["second_pass_share"] += int(out.second_pass.sum())
                    counts["turned_share"] += int((out.start_rotation != torch.eye(3)).any(dim=(1, 2)).sum())
                    counts["polished_share"] += int(out.polished.sum())
                    counts["icp_search_share"] += int(out.icp_search.sum())
                    for name in names:
                        R, t = kabsch(batch["src"], out.vcp) if name == "vcp" else (out.rotation, out.translation)
                        rotations[name].append(R.double().numpy())
                        translations[name].append(t.double().numpy())
        finally:
            for key, value in configured.items():
                setattr(config, key, value)
        shares = {key: count / len(data) for key, count in counts.items()}
        estimates.update({m: (np.concatenate(rotations[m]), np.concatenate(translations[m]), seconds, shares)
                          for m in names})
    return estimates


def classical_estimates(data, method: str, icp_max_distance: float, fpfh_voxel: float) -> tuple:
    """(R (S, 3, 3), t (S, 3), seconds) of ICP or FPFH + RANSAC, pair by pair in float64."""
    rotations, translations, seconds, failures = [], [], 0.0, 0
    for i in tqdm(range(len(data)), desc=method, leave=False):
        item = data[i]
        src, tgt = item["src"].double().numpy(), item["tgt"].double().numpy()
        started = time.perf_counter()
        try:
            if method == "icp":
                settings = IcpSettings(step="point_to_point", max_distance=icp_max_distance,
                                       transform_tolerance=1e-6)
                T = icp(src, tgt, np.eye(4), settings).T_target_source
            else:
                T = fpfh_ransac(torch.from_numpy(src), torch.from_numpy(tgt), fpfh_voxel, seed=i)[0].numpy()
        except (IcpFailure, ValueError):
            T, failures = np.eye(4), failures + 1
        seconds += time.perf_counter() - started
        rotations.append(T[:3, :3])
        translations.append(T[:3, 3])
    return np.stack(rotations), np.stack(translations), seconds, failures


def solve_options(name: str) -> dict:
    """How a model solves its estimate from its network's output, as its file says (see
    :func:`solve_of`): a measurement holds for these and its weights; ``vrnet export`` may change
    them without touching the weights."""
    path = weights_path(name) if name in available("vrnet") else Path(name)
    return solve_of(VRNetConfig.from_dict(model_values(read_checkpoint(path)["config"], str(path))))


def solve_of(config: VRNetConfig) -> dict:
    """The model config's inference-time fields (:data:`vrnet_ext.learning.export.INFERENCE_FIELDS`)."""
    values = config.to_dict()  # JSON's types (lists), as the measurements record them
    return {field: values[field] for field in INFERENCE_FIELDS}


def weights_digest(name: str) -> str:
    """The first 16 hex digits of a SHA-256 over a shipped model's (or a checkpoint's) parameters,
    name by name: which weights a measurement was taken with (its card may change, they may not)."""
    path = weights_path(name) if name in available("vrnet") else Path(name)
    state = read_checkpoint(path)["model"]
    digest = hashlib.sha256()
    for key in sorted(state):
        digest.update(key.encode())
        digest.update(state[key].detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()[:16]


def cells_of(name: str, config: dict) -> list[tuple[str, str]]:
    """The (setting, split) cells a model serves: a shipped model's per its card
    (:func:`vrnet_ext.model.pretrained.cells`); a checkpoint's its own, or every setting for a
    mixed-setting run."""
    if name in available("vrnet"):
        return [tuple(cell.split("/")) for cell in cells(name)]
    setting, split = config.get("setting", "PV"), config.get("split", "UPC")
    return [(s, split) for s in SETTINGS] if setting == MIXED else [(setting, split)]


def evaluate_model(name: str, args) -> list[dict]:
    model, state = load_vrnet(name)
    for key, value in solve_overrides(args).items():
        setattr(model.config, key, value)
    return [evaluate_cell(name, model, state["config"], setting, split, args)
            for setting, split in cells_of(name, state["config"]) if not args.settings or setting in args.settings]


def evaluate_cell(name: str, model, config: dict, setting: str, split: str, args) -> dict:
    spec = PairSpec(setting=setting, num_points=config.get("num_points", 1024),
                    num_subsampled=config.get("num_subsampled", 768), rotation_range=args.rotation_range)
    data = ModelNet40Pairs(args.data_dir, partition="test", setting=setting, split=split, max_items=args.max_items,
                           seed=1234, spec=spec)
    if args.swap:
        data = Swapped(data)
    gt_R = np.stack([data[i]["rotation"].double().numpy() for i in range(len(data))])
    gt_t = np.stack([data[i]["translation"].double().numpy() for i in range(len(data))])
    rows = {}
    estimates = network_estimates(model, data, args.batch_size, args.methods)
    for method in args.methods:
        failures = 0
        if method in estimates:
            R, t, seconds, shares = estimates[method]
        else:
            R, t, seconds, failures = classical_estimates(data, method, args.icp_max_distance, args.fpfh_voxel)
        row = summarize(R, gt_R, t, gt_t)
        row.update(seconds_per_pair=seconds / len(data), failures=failures)
        if method == "vrnet":
            row.update(shares)
        rows[method] = row
        print(f"{name} {setting}/{split} {method}: RMSE(R) {row['RMSE(R)']:.3f}, MAE(R) {row['MAE(R)']:.3f}, "
              f"RMSE(t) {row['RMSE(t)']:.4f}, {row['seconds_per_pair'] * 1e3:.1f} ms/pair", flush=True)
    return {"model": name, "weights": weights_digest(name), "solve": solve_of(model.config), "setting": setting,
            "split": split, "pairs": len(data),
            "shapes": "the whole split" if args.max_items is None else "spread evenly over the split",
            "views": VIEW_PROTOCOL, "rotations": args.rotation_range, "swapped": args.swap, "methods": rows,
            "paper": {k: dict(zip(COLUMNS[:4], v)) for k, v in PAPER.get((setting, split), {}).items()}}


def card_test(cell: dict) -> dict:
    """A measured cell's ``vrnet`` row as ``vrnet export --test-json`` reads it: the errors, the cell,
    the pairs, the solve they were measured with and the script that measured them (not the time per
    pair, a figure of the machine and of what else ran on it, nor the classical methods' failures)."""
    errors = {k: v for k, v in cell["methods"]["vrnet"].items() if k not in ("seconds_per_pair", "failures")}
    return {**errors, **cell["solve"], "setting": cell["setting"], "split": cell["split"],
            "pairs": cell["pairs"], "measured_by": "modelnet40_tables.py"}


def markdown(results: list[dict], machine: str) -> str:
    lines = [f"Measured {time.strftime('%Y-%m-%d')} on {machine}.", ""]
    for result in results:
        lines += [f"**{result['setting']} / {result['split']}** (model `{result['model']}`, {result['pairs']} test pairs, "
                  f"rotations: {result.get('rotations', DEFAULT_ROTATION_RANGE)}"
                  + (", swapped: target onto source)" if result.get("swapped") else ")"),
                  "", "| method | " + " | ".join(COLUMNS) + " | s / pair |",
                  "|---|" + "---:|" * (len(COLUMNS) + 1)]
        for method, row in result["methods"].items():
            lines.append(f"| {LABELS[method]} | " + " | ".join(f"{row[c]:.4g}" for c in COLUMNS)
                         + f" | {row['seconds_per_pair']:.4f} |")
        for method, row in result["paper"].items():
            lines.append(f"| paper: {method} | " + " | ".join(f"{row[c]:.4g}" for c in COLUMNS[:4]) + " | – | – |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="+", default=None, help="shipped names or checkpoints (default: every shipped ModelNet40 VRNet)")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=["vrnet", "vcp", "icp", "fpfh"],
                        help="methods to run: VRNet, its VCPs alone, VRNet in two passes, ICP, FPFH + RANSAC")
    parser.add_argument("--settings", nargs="+", choices=SETTINGS, default=None,
                        help="only these settings of the models' cells (default: every cell a model serves)")
    parser.add_argument("--max-items", type=int, default=None, help="N test shapes spread evenly over the split (default: all)")
    parser.add_argument("--batch-size", type=int, default=16, help="pairs per network forward")
    parser.add_argument("--icp-max-distance", type=float, default=1.0, help="ICP's correspondence reach")
    parser.add_argument("--fpfh-voxel", type=float, default=0.05, help="FPFH + RANSAC's voxel edge")
    parser.add_argument("--rotation-range", choices=ROTATION_RANGES, default=DEFAULT_ROTATION_RANGE,
                        help=ROTATION_RANGE_HELP)
    parser.add_argument("--swap", action="store_true", help="register each pair the other way round (target onto source)")
    add_solve_options(parser, "the model's")
    parser.add_argument("--json", default="modelnet40_tables.json", help="where the JSON goes")
    parser.add_argument("--markdown", default="modelnet40_tables.md", help="where the Markdown goes")
    parser.add_argument("--card-json-dir", type=Path, default=None,
                        help="also write each cell's VRNet row here as MODEL_SETTING_SPLIT.json, the test results "
                             "`vrnet export --test-json` puts in a model card (none: not written)")
    args = parser.parse_args(argv)
    models = args.models or available("vrnet")
    if not models:
        print("modelnet40_tables: no shipped model and no --models given", file=sys.stderr)
        return 2
    results = [cell for name in models for cell in evaluate_model(name, args)]
    machine = f"{cpu_description()}, {torch.get_num_threads()} threads, torch {torch.__version__}"
    Path(args.json).write_text(json.dumps({"machine": machine, "results": results}, indent=1))
    Path(args.markdown).write_text(markdown(results, machine))
    if args.card_json_dir:
        args.card_json_dir.mkdir(parents=True, exist_ok=True)
        for cell in results:
            if "vrnet" in cell["methods"]:
                name = f"{Path(cell['model']).stem}_{cell['setting']}_{cell['split']}.json".replace("+", "")
                (args.card_json_dir / name).write_text(json.dumps(card_test(cell), indent=1))
    print(markdown(results, machine))
    print(f"wrote {args.json} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
