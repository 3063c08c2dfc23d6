"""The ModelNet40 cells on other rotations than the paper's protocol, with and without the rotation search.

    python benchmarks/modelnet40_rotations.py --tables DIR [--json rotations.json] [--markdown rotations.md]

Reads every JSON that ``modelnet40_tables.py`` wrote into DIR, each run with its own
``--rotation-range`` (``symmetric``: each Euler angle in [-45, 45] degrees; ``so3``: uniform over
all rotations), ``--swap`` (every pair registered the other way round: the protocol's motions
inverted) and ``--rotation-search-below`` (0: the model alone; else the search of
``VRNetConfig.rotation_search_below``). One row per cell and kind of pair: the shipped model that
serves the cell, the pairs, and per estimate (alone, with the search) the share of pairs registered
(recall: rotation error below 5 degrees and translation error below 0.1), RMSE(R) in degrees and the
seconds per pair. The paper's VRNet RMSE(R) (its protocol) stands beside them.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from modelnet40_tables import PAPER  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.data.protocol import SETTINGS
from vrnet_ext.data.modelnet import SPLITS
from vrnet_ext.names import DEFAULT_ROTATION_RANGE

RECALL = "recall(RE<5,TE<0.1)"
ESTIMATES = ("alone", "search")


def pair_kind(cell: dict) -> str:
    """What a measured cell's pairs were: their rotations, and whether registered the other way round."""
    rotations = cell.get("rotations", DEFAULT_ROTATION_RANGE)
    return f"{rotations}, swapped" if cell.get("swapped") else rotations


def collect(tables: Path) -> list[dict]:
    """One row per (cell, kind of pair) with each estimate's recall, RMSE(R) and time."""
    rows: dict[tuple[str, str, str], dict] = {}
    for path in sorted(tables.glob("*.json")):
        for cell in json.loads(path.read_text())["results"]:
            estimate = "search" if cell["solve"].get("rotation_search_below", 0) > 0 else "alone"
            key = (cell["setting"], cell["split"], pair_kind(cell))
            row = rows.setdefault(key, {"setting": cell["setting"], "split": cell["split"], "pairs_of": key[2],
                                        "model": cell["model"], "pairs": cell["pairs"]})
            if row["model"] != cell["model"] or row["pairs"] != cell["pairs"]:
                raise ValueError(f"{path}: {key} measured with another model or pair count than before")
            vrnet = cell["methods"]["vrnet"]
            row[estimate] = {"recall": vrnet[RECALL], "RMSE(R)": vrnet["RMSE(R)"],
                             "seconds_per_pair": vrnet["seconds_per_pair"],
                             "search_below": cell["solve"].get("rotation_search_below", 0), "source": path.name}
    order = {(s, p): i for i, (s, p) in enumerate((s, p) for p in SPLITS for s in SETTINGS)}
    return sorted(rows.values(), key=lambda r: (r["pairs_of"], order[(r["setting"], r["split"])]))


def markdown(rows: list[dict], note: str) -> str:
    lines = [note, "", "| pairs | cell | model | pairs measured | recall alone | recall with search | "
             "RMSE(R) alone | RMSE(R) with search | paper RMSE(R) (protocol) | s / pair alone | s / pair with search |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        paper = PAPER.get((row["setting"], row["split"]), {}).get("VRNet", ("–",))[0]
        cells = []
        for field, form in (("recall", "{:.1%}"), ("RMSE(R)", "{:.3g}"), ("seconds_per_pair", "{:.3f}")):
            cells.append([form.format(row[e][field]) if e in row else "–" for e in ESTIMATES])
        lines.append(f"| {row['pairs_of']} | {row['setting']} / {row['split']} | `{row['model']}` | {row['pairs']} | "
                     f"{cells[0][0]} | {cells[0][1]} | {cells[1][0]} | {cells[1][1]} | {paper} | "
                     f"{cells[2][0]} | {cells[2][1]} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--tables", type=Path, required=True, help="folder of modelnet40_tables.py JSON files")
    parser.add_argument("--json", type=Path, default=Path("rotations.json"), help="where the JSON goes")
    parser.add_argument("--markdown", type=Path, default=Path("rotations.md"), help="where the Markdown goes")
    parser.add_argument("--note", default="", help="a line above the table: machine, date, what else ran")
    args = parser.parse_args(argv)
    try:
        rows = collect(args.tables)
    except (OSError, ValueError, KeyError) as exc:
        print(f"modelnet40_rotations: {exc}", file=sys.stderr)
        return 2
    if not rows:
        print(f"modelnet40_rotations: no modelnet40_tables.py JSON in {args.tables}", file=sys.stderr)
        return 2
    args.json.write_text(json.dumps({"note": args.note, "rows": rows}, indent=1))
    args.markdown.write_text(markdown(rows, args.note))
    print(markdown(rows, args.note))
    print(f"wrote {args.json} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
