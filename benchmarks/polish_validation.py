"""The geometric polish (``VRNetConfig.polish_iterations``, and ``rotation_search_polish`` in the
rotation search) on validation pairs: what a shipped model's polish is chosen on.

    python benchmarks/polish_validation.py --models vrnet-pv-nd-rcp [...] [--steps 0 3 10 30]
        [--rotations protocol symmetric] [--search-below 0.1] [--search-polish 0 30] [--max-items 300]
        [--json polish.json] [--markdown polish.md]

Pairs: ``--max-items`` shapes spread evenly over the ``val`` partition (held out of TRAIN by every
run, never the test split) of each model's cell, seed 1234, for each set of ``--rotations``. Each
model solves as its file says; the pairs whose rotations go beyond the protocol's (``symmetric``,
``so3``) also take the rotation search (``rotation_search_below`` = ``--search-below``), once for
each ``--search-polish`` (its ``rotation_search_polish``: a forward each). Each batch goes through
the model once per search polish; every step count of ``--steps`` then polishes that output
(:meth:`vrnet_ext.VRNet.polished`, the forward's last step), so the rows of one forward differ by
the polish alone. Per row: recall (rotation error below 5 degrees and translation error below 0.1),
RMSE(R) (the paper's, on Euler angles), the median rotation error, the pairs more than 5 degrees
off, the share the polish moved and the seconds per pair (the batch's forward plus its polish).
"""
from __future__ import annotations

import argparse
import sys
import time

import torch

from outputs import machine_and_date, write_outputs  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter, nonnegative_int, positive_int, unit_interval
from vrnet_ext.names import ROTATION_RANGES

COLUMNS = {"recall": "recall(RE<5,TE<0.1)", "rmse_r": "RMSE(R)", "mae_r": "MAE(R)", "rmse_t": "RMSE(t)",
           "re_median": "RE median (deg)"}
SEARCHED = ("symmetric", "so3")  # the sets of pairs beyond the protocol's rotations: these search


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="+", required=True, help="shipped names or checkpoint paths")
    parser.add_argument("--steps", type=nonnegative_int, nargs="+", default=[0, 3, 10, 30],
                        help="polish step counts, one row each (0: the model's estimate as it is)")
    parser.add_argument("--rotations", nargs="+", choices=ROTATION_RANGES, default=["protocol", "symmetric"],
                        help="the sets of pairs' rotations")
    parser.add_argument("--search-below", type=unit_interval, default=0.1,
                        help=f"rotation_search_below of the pairs beyond the protocol's ({', '.join(SEARCHED)})")
    parser.add_argument("--search-polish", type=nonnegative_int, nargs="+", default=[0],
                        help="rotation_search_polish steps of the searched pairs, a forward each")
    parser.add_argument("--max-items", type=positive_int, default=300, help="validation shapes (pairs) per set")
    parser.add_argument("--batch-size", type=positive_int, default=16, help="pairs per forward")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--note", default="", help="a sentence added to the table's caption")
    parser.add_argument("--json", default=None, help="write the record here")
    parser.add_argument("--markdown", default=None, help="write the table here")
    return parser.parse_args(argv)


def measure(name: str, rotations: str, search_polish: int, args) -> list[dict]:
    """One model's rows on one set of pairs (of the first cell it serves), its rotation search (where
    the set takes one) polishing its starts ``search_polish`` steps: its estimate, then each polish
    of ``--steps``."""
    from torch.utils.data import DataLoader

    from modelnet40_tables import cells_of  # benchmarks/, the script's folder
    from vrnet_ext.data import ModelNet40Pairs, PairSpec
    from vrnet_ext.geometry.metrics import rotation_error_deg, summarize
    from vrnet_ext.model.pretrained import load_vrnet

    model, state = load_vrnet(name)
    config = state["config"]
    setting, split = cells_of(name, config)[0]
    model.eval().config.rotation_search_below = args.search_below if rotations in SEARCHED else 0.0
    model.config.polish_iterations, model.config.rotation_search_polish = 0, search_polish
    spec = PairSpec(setting=setting, num_points=config.get("num_points", 1024),
                    num_subsampled=config.get("num_subsampled", 768), rotation_range=rotations)
    data = ModelNet40Pairs(args.data_dir, partition="val", setting=setting, split=split, max_items=args.max_items,
                           spec=spec, val_fraction=config.get("val_fraction", 0.1))
    outputs = {steps: [] for steps in args.steps}  # per step count, the polished output of each batch
    seconds = dict.fromkeys(args.steps, 0.0)
    truth = []
    with torch.no_grad():
        for batch in DataLoader(data, batch_size=args.batch_size, shuffle=False):
            started = time.perf_counter()
            out = model(batch["src"], batch["tgt"])
            forward = time.perf_counter() - started
            truth.append((batch["rotation"], batch["translation"]))
            for steps in args.steps:
                started = time.perf_counter()
                outputs[steps].append(model.polished(batch["src"], batch["tgt"], out, steps) if steps else out)
                seconds[steps] += forward + time.perf_counter() - started
    gt_R, gt_t = (torch.cat(values).double() for values in zip(*truth))
    rows = []
    for steps, polished in outputs.items():
        R = torch.cat([out.rotation for out in polished]).double()
        t = torch.cat([out.translation for out in polished]).double()
        errors = summarize(R.numpy(), gt_R.numpy(), t.numpy(), gt_t.numpy())
        wrong = int((rotation_error_deg(R, gt_R) > 5).sum())
        moved = torch.cat([out.polished for out in polished])
        rows.append({"model": name, "cell": f"{setting} / {split}", "rotations": rotations,
                     "rotation_search_below": model.config.rotation_search_below,
                     "rotation_search_polish": search_polish, "polish_iterations": steps,
                     "pairs": len(data), **{key: errors[column] for key, column in COLUMNS.items()},
                     "wrong": wrong, "polished_share": float(moved.float().mean()),
                     "seconds_per_pair": seconds[steps] / len(data)})
        print(f"{name} {rotations} search polish {search_polish}, polish {steps}: "
              f"recall {100 * rows[-1]['recall']:.1f} %, RMSE(R) {rows[-1]['rmse_r']:.3g}, RE median {rows[-1]['re_median']:.3g}", file=sys.stderr)
    return rows


def markdown(rows: list[dict], caption: str) -> str:
    lines = [caption, "", "| model | cell | pairs' rotations | search | search polish | polish steps | pairs | "
             "recall | RMSE(R) | RE median | > 5° | polished | s / pair |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| `{row['model']}` | {row['cell']} | {row['rotations']} | {row['rotation_search_below']:g} | "
                     f"{row['rotation_search_polish']} | {row['polish_iterations']} | {row['pairs']} | "
                     f"{100 * row['recall']:.1f} % | {row['rmse_r']:.3g} | "
                     f"{row['re_median']:.3g} | {row['wrong']} | {100 * row['polished_share']:.0f} % | "
                     f"{row['seconds_per_pair']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows = [row for name in args.models for rotations in args.rotations
            for search_polish in (args.search_polish if rotations in SEARCHED else [0])
            for row in measure(name, rotations, search_polish, args)]
    machine, date = machine_and_date()
    caption = (f"The geometric polish on {args.max_items} validation shapes of each model's cell, spread over the "
               f"partition (seed 1234; never the test split); each model solved as its file says, the pairs beyond "
               f"the protocol's rotations with the rotation search (rotation_search_below {args.search_below:g}); "
               f"the search polishing each start's estimate (and the pair's own) that many steps before they are "
               f"compared where 'search polish' says so; each row of one forward the same estimates polished with "
               f"'polish steps' (0: none). Recall: rotation error below "
               f"5 degrees and translation error below 0.1; RMSE(R): the paper's (Euler angles); > 5°: pairs more "
               f"than 5 degrees off; polished: the share of pairs the polish moved. {machine}, {date}."
               f"{' ' + args.note if args.note else ''}")
    record = {"partition": "val", "max_items": args.max_items, "steps": args.steps, "search_below": args.search_below,
              "search_polish": args.search_polish,
              "machine": machine, "date": date, "note": args.note, "rows": rows}
    write_outputs(markdown(rows, caption), record, args.markdown, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
