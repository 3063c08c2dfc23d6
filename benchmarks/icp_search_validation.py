"""The rotation search's multi-start ICP (``VRNetConfig.rotation_search_icp_starts``) on validation
pairs: what a shipped model's ICP search, and the share of the estimate's distance its result must
come below (``vrnet_ext.model.vrnet.ICP_SEARCH_NEARER``), are chosen on.

    python benchmarks/icp_search_validation.py --models vrnet-rs-nd-rcp [...] [--setting PV+RS]
        [--starts 512] [--slides 1] [--icp robust [trimmed]] [--nearer 1 0.9 0.85 0.8] [--rotations symmetric]
        [--max-items 300]
        [--json icp.json] [--markdown icp.md]

Pairs: ``--max-items`` shapes spread evenly over the ``val`` partition (held out of TRAIN by every
run, never the test split) of each model's cell (the first it serves, or ``--setting``), seed 1234,
rotations drawn as ``--rotations`` says. Each batch goes through the model once, solved as its file
says with the rotation search at ``--search-below`` and without the ICP search; then
:func:`vrnet_ext.geometry.alignment.multistart_icp` from ``--starts`` spread rotations (``--slides``
translations each, each ICP of ``--icp`` in turn) registers every pair the search took on
(``out.searched``), as the forward would last. For each share of
``--nearer`` the ICP's estimate replaces the model's where its median nearest-point distance is below
that share of the model's. Per row: recall (rotation error below 5 degrees and translation error
below 0.1), RMSE(R) (the paper's, on Euler angles), the median rotation error, the pairs more than 5
degrees off, the pairs searched and replaced, those the replacement registers (from more than 5
degrees off to at most 5) and those it loses, and the seconds per pair (the forward, plus the ICP
search per pair measured). Below the table every pair whose error a replacement (at share 1) would
change by more than 5 degrees, with the ratio of the two distances: what a share is chosen on; and
every pair left more than 5 degrees off by the model's estimate or the ICP's, with the ground truth's
distance over the estimate's (near 1 or above: the geometry cannot tell the estimate from the truth,
as on a symmetric shape) and the turn of the estimate and of the truth from the identity.
"""
from __future__ import annotations

import argparse
import sys
import time

import torch
from tqdm import tqdm

from outputs import machine_and_date, write_outputs  # benchmarks/, the script's folder
from polish_validation import COLUMNS  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter, positive_float, positive_int, unit_interval
from vrnet_ext.cli.training import icp_slides, icp_starts
from vrnet_ext.data.protocol import SETTINGS
from vrnet_ext.names import DEFAULT_SEARCH_ICP, ROTATION_RANGES, SEARCH_ICPS

WRONG_DEG = 5.0  # a pair more than this many degrees off is wrong (the recall's threshold)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="+", required=True, help="shipped names or checkpoint paths")
    parser.add_argument("--setting", choices=SETTINGS, default=None,
                        help="the cell's setting, for a model that serves several (default: the first it serves)")
    parser.add_argument("--starts", type=icp_starts, default=512, help="the ICP search's spread rotations")
    parser.add_argument("--slides", type=icp_slides, default=1, help="the ICP search's translations per rotation")
    parser.add_argument("--icp", choices=SEARCH_ICPS, nargs="+", default=[DEFAULT_SEARCH_ICP],
                        help="the ICP search's ICPs, rows of each beside one forward")
    parser.add_argument("--nearer", type=positive_float, nargs="+", default=[1.0, 0.9, 0.85, 0.8],
                        help="shares of the estimate's distance the ICP's must come below to replace it, a row each")
    parser.add_argument("--rotations", choices=ROTATION_RANGES, default="symmetric", help="the pairs' rotations")
    parser.add_argument("--search-below", type=unit_interval, default=0.1, help="rotation_search_below")
    parser.add_argument("--max-items", type=positive_int, default=300, help="validation shapes (pairs) per model")
    parser.add_argument("--batch-size", type=positive_int, default=16, help="pairs per forward")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--json", default=None, help="write the record here")
    parser.add_argument("--markdown", default=None, help="write the tables here")
    return parser.parse_args(argv)


def measure(name: str, args) -> tuple[list[dict], list[dict], list[dict]]:
    """One model's rows (one per ICP of ``--icp`` and share of ``--nearer``), the pairs a replacement
    would move by more than WRONG_DEG, and the pairs left more than WRONG_DEG off (by the model's
    estimate or an ICP's), each of the last two per ICP; one forward serves every ICP."""
    import numpy as np
    from torch.utils.data import DataLoader

    from modelnet40_tables import cells_of  # benchmarks/, the script's folder
    from vrnet_ext.data import ModelNet40Pairs, PairSpec
    from vrnet_ext.geometry.alignment import multistart_icp, nearest_median
    from vrnet_ext.geometry.metrics import rotation_error_deg, summarize
    from vrnet_ext.geometry.transforms import spread_rotations
    from vrnet_ext.model.pretrained import load_vrnet

    model, state = load_vrnet(name)
    config = state["config"]
    cells = cells_of(name, config)
    setting, split = next((cell for cell in cells if cell[0] == args.setting), cells[0])
    model.eval().config.rotation_search_below = args.search_below
    model.config.rotation_search_icp_starts = 0
    spec = PairSpec(setting=setting, num_points=config.get("num_points", 1024),
                    num_subsampled=config.get("num_subsampled", 768), rotation_range=args.rotations)
    data = ModelNet40Pairs(args.data_dir, partition="val", setting=setting, split=split, max_items=args.max_items,
                           spec=spec, val_fraction=config.get("val_fraction", 0.1))
    starts = torch.as_tensor(spread_rotations(args.starts))
    kept = {key: [] for key in ("R", "t", "gt_R", "gt_t", "searched", "truth_ratio")}
    found = {icp: {key: [] for key in ("R", "t", "ratio")} for icp in args.icp}
    forward_seconds, icp_seconds = 0.0, dict.fromkeys(args.icp, 0.0)
    with torch.no_grad():
        for batch in tqdm(DataLoader(data, batch_size=args.batch_size, shuffle=False), desc=name, leave=False):
            src, tgt = batch["src"], batch["tgt"]
            started = time.perf_counter()
            out = model(src, tgt)
            forward_seconds += time.perf_counter() - started
            so_far = nearest_median(src, tgt, out.rotation, out.translation)  # the model's estimate's distance
            truth_ratio = nearest_median(src, tgt, batch["rotation"], batch["translation"]) / so_far
            rows = out.searched.nonzero().squeeze(1)
            for icp in args.icp:
                R_icp, t_icp, ratio = out.rotation.clone(), out.translation.clone(), torch.ones(len(src))
                if rows.numel():
                    started = time.perf_counter()
                    R, t, distance = multistart_icp(src[rows], tgt[rows], starts.to(src.dtype),
                                                    slide_count=args.slides, icp=icp)
                    icp_seconds[icp] += time.perf_counter() - started
                    R_icp[rows], t_icp[rows] = R, t
                    ratio[rows] = distance / so_far[rows]
                for key, value in (("R", R_icp), ("t", t_icp), ("ratio", ratio)):
                    found[icp][key].append(value)
            for key, value in (("R", out.rotation), ("t", out.translation), ("gt_R", batch["rotation"]),
                               ("gt_t", batch["translation"]), ("searched", out.searched), ("truth_ratio", truth_ratio)):
                kept[key].append(value)
    values = {key: torch.cat(value) for key, value in kept.items()}
    gt_R = values["gt_R"].double()
    before = rotation_error_deg(values["R"].double(), gt_R)
    searched = values["searched"]
    identity = torch.eye(3, dtype=torch.float64).expand_as(gt_R)
    turn, truth_turn = rotation_error_deg(values["R"].double(), identity), rotation_error_deg(gt_R, identity)
    rows, changes, wrong = [], [], []
    for icp in args.icp:
        ours = {key: torch.cat(value) for key, value in found[icp].items()}
        after = rotation_error_deg(ours["R"].double(), gt_R)
        for share in args.nearer:
            take = searched & (ours["ratio"] < share)
            R = torch.where(take[:, None, None], ours["R"], values["R"]).double()
            t = torch.where(take[:, None], ours["t"], values["t"]).double()
            errors = summarize(R.numpy(), gt_R.numpy(), t.numpy(), values["gt_t"].double().numpy())
            error = torch.where(take, after, before)
            rows.append({"model": name, "cell": f"{setting} / {split}", "rotations": args.rotations,
                         "starts": args.starts, "slides": args.slides, "icp": icp, "nearer": share,
                         "pairs": len(data), **{key: errors[column] for key, column in COLUMNS.items()},
                         "wrong": int((error > WRONG_DEG).sum()), "searched": int(searched.sum()),
                         "replaced": int(take.sum()),
                         "registered": int((take & (before > WRONG_DEG) & (after <= WRONG_DEG)).sum()),
                         "lost": int((take & (before <= WRONG_DEG) & (after > WRONG_DEG)).sum()),
                         "seconds_per_pair": (forward_seconds + icp_seconds[icp]) / len(data),
                         "icp_seconds_per_searched_pair": icp_seconds[icp] / max(1, int(searched.sum()))})
            print(f"{name} {icp} nearer {share:g}: recall {100 * rows[-1]['recall']:.1f} %, "
                  f"RMSE(R) {rows[-1]['rmse_r']:.3g}, wrong {rows[-1]['wrong']}", file=sys.stderr)
        moved = searched & (ours["ratio"] < 1) & ((before - after).abs() > WRONG_DEG)
        changes += [{"model": name, "icp": icp, "pair": int(i), "ratio": float(ours["ratio"][i]),
                     "error_before": float(before[i]), "error_after": float(after[i])}
                    for i in np.flatnonzero(moved.numpy())]
        wrong += [{"model": name, "icp": icp, "pair": int(i), "searched": bool(searched[i]),
                   "truth_ratio": float(values["truth_ratio"][i]), "error_before": float(before[i]),
                   "error_after": float(after[i]), "turn": float(turn[i]), "truth_turn": float(truth_turn[i])}
                  for i in np.flatnonzero(((before > WRONG_DEG) | (after > WRONG_DEG)).numpy())]
    return rows, changes, wrong


def markdown(rows: list[dict], changes: list[dict], wrong: list[dict], caption: str) -> str:
    lines = [caption, "", "| model | cell | ICP | starts | slides | nearer than | pairs | recall | RMSE(R) | RE median | "
             "> 5° | searched | replaced | registered | lost | s / pair | ICP s / searched pair |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| `{row['model']}` | {row['cell']} | {row.get('icp', 'robust')} | {row['starts']} | "
                     f"{row.get('slides', 1)} | {row['nearer']:g} | {row['pairs']} | "
                     f"{100 * row['recall']:.1f} % | {row['rmse_r']:.3g} | {row['re_median']:.3g} | {row['wrong']} | "
                     f"{row['searched']} | {row['replaced']} | {row['registered']} | {row['lost']} | "
                     f"{row['seconds_per_pair']:.3f} | {row['icp_seconds_per_searched_pair']:.3f} |")
    lines += ["", "Pairs whose error a replacement would change by more than 5 degrees (the ICP's distance nearer "
              "than the estimate's):", "", "| model | ICP | pair | distance ratio | error before (deg) | error after |",
              "|---|---|---:|---:|---:|---:|"]
    lines += [f"| `{c['model']}` | {c.get('icp', 'robust')} | {c['pair']} | {c['ratio']:.3f} | {c['error_before']:.3g} | "
              f"{c['error_after']:.3g} |" for c in sorted(changes, key=lambda c: c["ratio"])] or ["| – | | | | | |"]
    lines += ["", "Pairs more than 5 degrees off by the model's estimate or the ICP's (the truth's distance over the "
              "estimate's: near 1 or above, the geometry cannot tell them apart; the turns from the identity in "
              "degrees):", "", "| model | ICP | pair | searched | truth's distance ratio | error (deg) | ICP's error | "
              "estimate's turn | truth's turn |", "|---|---|---:|---|---:|---:|---:|---:|---:|"]
    lines += [f"| `{w['model']}` | {w.get('icp', 'robust')} | {w['pair']} | {'yes' if w['searched'] else 'no'} | "
              f"{w['truth_ratio']:.3f} | {w['error_before']:.3g} | {w['error_after']:.3g} | {w['turn']:.1f} | "
              f"{w['truth_turn']:.1f} |" for w in wrong] or ["| – | | | | | | | | |"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows, changes, wrong = [], [], []
    for name in args.models:
        model_rows, model_changes, model_wrong = measure(name, args)
        rows += model_rows
        changes += model_changes
        wrong += model_wrong
    machine, date = machine_and_date()
    caption = (f"The rotation search's multi-start ICP on {args.max_items} validation shapes of each model's cell, "
               f"spread over the partition (seed 1234; never the test split), rotations {args.rotations}; each model "
               f"solved as its file says with the rotation search (rotation_search_below {args.search_below:g}), then "
               f"{' and '.join(args.icp)} ICP from {args.starts} spread rotations ({args.slides} translations each) on every pair "
               f"the search took on, its estimate kept "
               f"where its median nearest-point distance is below 'nearer than' x the estimate's. Recall: rotation "
               f"error below 5 degrees and translation error below 0.1; RMSE(R): the paper's (Euler angles); > 5°: "
               f"pairs more than 5 degrees off; registered / lost: pairs the replacement brings within 5 degrees / "
               f"takes beyond. {machine}, {date}.")
    record = {"partition": "val", "max_items": args.max_items, "rotations": args.rotations, "starts": args.starts,
              "slides": args.slides, "icp": args.icp,
              "search_below": args.search_below, "machine": machine, "date": date, "rows": rows, "changes": changes,
              "wrong": wrong}
    write_outputs(markdown(rows, changes, wrong, caption), record, args.markdown, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
