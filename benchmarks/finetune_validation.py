"""A fine-tune against the model it would replace, on validation pairs only, under the rotations
beyond the protocol's and the protocol's own: the comparison a ModelNet40 model is shipped on.

    python benchmarks/finetune_validation.py --before vrnet-pv-nd-rcp --after runs/ft/best.pt
        [--setting PV --split ND] [--max-items 300] [--search-below 0.1] [solve flags]
        [--json val.json] [--markdown val.md]

Pairs: ``--max-items`` shapes spread evenly over the ``val`` partition (held out of TRAIN by every run,
never the test split) of the cell (default: the one ``--before`` was trained for), seed 1234, in
three sets of rotations: uniform over SO(3) with the rotation search (``rotation_search_below`` =
``--search-below``), each Euler angle in [-45, 45] degrees (``symmetric``) and the protocol's
[0, 45], both without it. Both models solve as ``--before``'s file says, unless the solve flags
say otherwise (a fine-tune is shipped with its predecessor's solve). Per row: recall (rotation
error below 5 degrees and translation error below 0.1), RMSE(R) (the paper's, on Euler angles),
the median rotation error and the time of one pair (batch 1). Writes Markdown and JSON.
"""
from __future__ import annotations

import argparse
import sys

from outputs import machine_and_date, write_outputs  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter
from vrnet_ext.cli.training import add_solve_options, solve_overrides
from vrnet_ext.names import SETTINGS, SPLITS

# (rotations, whether the rotation search runs): the sets of pairs, in the order of the table
RANGES = (("so3", True), ("symmetric", False), ("protocol", False))
COLUMNS = {"recall": "recall(RE<5,TE<0.1)", "rmse_r": "RMSE(R)", "mae_r": "MAE(R)", "rmse_t": "RMSE(t)",
           "re_median": "RE median (deg)"}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--before", required=True, help="the model a fine-tune would replace: a shipped name or a path")
    parser.add_argument("--after", required=True, help="the fine-tune: a checkpoint (best.pt of `vrnet train`)")
    parser.add_argument("--after-label", default="fine-tuned (the run's best.pt)", help="the fine-tune's name in the table")
    parser.add_argument("--setting", choices=SETTINGS, default=None, help="the cell (default: --before's)")
    parser.add_argument("--split", choices=SPLITS, default=None, help="the cell (default: --before's)")
    parser.add_argument("--max-items", type=int, default=300, help="validation shapes (pairs) per set")
    parser.add_argument("--search-below", type=float, default=0.1,
                        help="rotation_search_below of the SO(3) rows (the other rows never search)")
    parser.add_argument("--batch-size", type=int, default=16, help="pairs per forward")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--note", default="", help="a sentence added to the table's caption")
    parser.add_argument("--json", default=None, help="write the record here")
    parser.add_argument("--markdown", default=None, help="write the table here")
    add_solve_options(parser, "--before's")
    args = parser.parse_args(argv)
    if args.max_items < 1:
        parser.error(f"--max-items must be at least 1, got {args.max_items}")
    if not 0 < args.search_below <= 1:
        parser.error(f"--search-below must be in (0, 1], got {args.search_below}")
    if args.rotation_search_below is not None:
        parser.error("--rotation-search-below: each set of pairs says whether it searches; give --search-below")
    return args


def measure(label: str, checkpoint: str, solve: dict, cell: tuple[str, str], args) -> list[dict]:
    """One model's rows: each set of RANGES measured with ``solve`` (and the search where due)."""
    from vrnet_ext.data import ModelNet40Pairs, PairSpec
    from vrnet_ext.learning.evaluate import evaluate, time_inference
    from vrnet_ext.model.pretrained import load_vrnet

    model, state = load_vrnet(checkpoint, args.device)
    config = state["config"]
    rows = []
    for rotations, search in RANGES:
        for key, value in {**solve, "rotation_search_below": args.search_below if search else 0.0}.items():
            setattr(model.config, key, value)
        spec = PairSpec(num_points=config.get("num_points", 1024), num_subsampled=config.get("num_subsampled", 768),
                        rotation_range=rotations)
        data = ModelNet40Pairs(args.data_dir, partition="val", setting=cell[0], split=cell[1], max_items=args.max_items,
                               spec=spec, val_fraction=config.get("val_fraction", 0.1))
        result = evaluate(model.to(args.device), data, batch_size=args.batch_size, device=args.device)
        rows.append({"rotations": rotations, "model": label, "checkpoint": checkpoint,
                     "rotation_search_below": model.config.rotation_search_below, "pairs": result["pairs"],
                     **{name: result[key] for name, key in COLUMNS.items()},
                     "ms_per_pair": 1000 * time_inference(model, data, args.device)})
        print(f"{rotations:9s} {label}: recall {100 * rows[-1]['recall']:.1f} %, RMSE(R) {rows[-1]['rmse_r']:.3g}",
              file=sys.stderr)
    return rows


def markdown(rows: list[dict], caption: str) -> str:
    lines = [caption, "", "| pairs' rotations | model | search | pairs | recall | RMSE(R) | RE median | ms / pair |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for row in sorted(rows, key=lambda r: [name for name, _ in RANGES].index(r["rotations"])):
        lines.append(f"| {row['rotations']} | {row['model']} | {row['rotation_search_below']:g} | {row['pairs']} | "
                     f"{100 * row['recall']:.1f} % | {row['rmse_r']:.3g} | {row['re_median']:.3g} | "
                     f"{row['ms_per_pair']:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from vrnet_ext.learning.export import INFERENCE_FIELDS
    from vrnet_ext.model.pretrained import load_vrnet

    _, state = load_vrnet(args.before)
    config = state["config"]
    cell = (args.setting or config.get("setting"), args.split or config.get("split"))
    if cell[0] not in SETTINGS or cell[1] not in SPLITS:
        raise SystemExit(f"--before {args.before} names no single cell ({cell[0]} / {cell[1]}): give --setting and --split")
    # each set of pairs says whether it searches; each model searches about its own training rotations
    own = ("rotation_search_below", "rotation_search_centre")
    solve = {key: config["model"][key] for key in INFERENCE_FIELDS if key in config["model"] and key not in own}
    solve.update(solve_overrides(args))
    rows = (measure(f"{args.before} (before)", args.before, solve, cell, args)
            + measure(args.after_label, args.after, solve, cell, args))
    machine, date = machine_and_date()
    caption = (f"{cell[0]} / {cell[1]}, {args.max_items} validation shapes spread over the partition (seed 1234; never the test split), "
               f"before and after the fine-tune, both solved as {args.before}'s file says"
               f"{' with ' + str(solve_overrides(args)) if solve_overrides(args) else ''}. Recall: rotation error below "
               f"5 degrees and translation error below 0.1; RMSE(R): the paper's (Euler angles); search: "
               f"rotation_search_below. {machine}, {date}.{' ' + args.note if args.note else ''}")
    record = {"setting": cell[0], "split": cell[1], "partition": "val", "max_items": args.max_items, "solve": solve,
              "machine": machine, "date": date, "note": args.note, "rows": rows}
    write_outputs(markdown(rows, caption), record, args.markdown, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
