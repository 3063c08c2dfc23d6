"""The ModelNet40 cells on other rotations than the paper's protocol, with and without the rotation search.

    python benchmarks/modelnet40_rotations.py --tables DIR [DIR ...] [--json rotations.json] [--markdown rotations.md]

Reads every JSON that ``modelnet40_tables.py`` wrote into each DIR (in order: a later folder's
estimate of a cell replaces an earlier one's, e.g. a re-run with another search), each run with its own
``--rotation-range`` (``symmetric``: each Euler angle in [-45, 45] degrees; ``so3``: uniform over
all rotations), ``--swap`` (every pair registered the other way round: the protocol's motions
inverted), ``--max-rotation`` (a bound on the motion given to the search: rows of their own) and
``--rotation-search-below`` (0: the model alone; else the search of
``VRNetConfig.rotation_search_below``). One row per cell and kind of pair: the shipped model that
serves the cell, the pairs, and per estimate (alone, with the search) the share of pairs registered
(recall: rotation error below 5 degrees and translation error below 0.1), RMSE(R) in degrees and the
seconds per pair, the geometric polish's steps of each (``VRNetConfig.polish_iterations``; alone /
with the search), the steps the search polishes each start with (``rotation_search_polish``) and
the starts of its multi-start ICP (``rotation_search_icp_starts``; x its slides and its ICP where
not 1 and robust) and the penalty on the turn its choices weigh distances by
(``rotation_search_turn_penalty``). The paper's VRNet RMSE(R) (its protocol) stands beside them.
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
from vrnet_ext.names import ANY_ROTATION, DEFAULT_ROTATION_RANGE, DEFAULT_SEARCH_ICP

RECALL = "recall(RE<5,TE<0.1)"
ESTIMATES = ("alone", "search")


def pair_kind(cell: dict) -> str:
    """What a measured cell's pairs were: their rotations, whether registered the other way round, and
    the bound on their motion the caller gave (``VRNetConfig.max_rotation``, where below 180)."""
    kind = cell.get("rotations", DEFAULT_ROTATION_RANGE) + (", swapped" if cell.get("swapped") else "")
    bound = cell["solve"].get("max_rotation", ANY_ROTATION)
    return f"{kind}, bound {bound:g}°" if bound < ANY_ROTATION else kind


def collect(folders: list[Path]) -> list[dict]:
    """One row per (cell, kind of pair) with each estimate's recall, RMSE(R) and time. The folders are
    read in order: an estimate measured again in a later folder (the same cell, kind of pair, alone or
    with the search) replaces the earlier one; the estimates side by side in a row must come from the
    same model, pair count and shapes."""
    estimates: dict[tuple[str, str, str], dict] = {}
    for folder in folders:
        measured_here: dict[tuple, str] = {}
        for path in sorted(folder.glob("*.json")):
            for cell in json.loads(path.read_text())["results"]:
                estimate = "search" if cell["solve"].get("rotation_search_below", 0) > 0 else "alone"
                key = (cell["setting"], cell["split"], pair_kind(cell))
                if (key, estimate) in measured_here:
                    raise ValueError(f"{path}: {key} {estimate} measured twice in {folder} (also in "
                                     f"{measured_here[key, estimate]})")
                measured_here[key, estimate] = path.name
                vrnet = cell["methods"]["vrnet"]
                estimates.setdefault(key, {})[estimate] = {
                    "model": cell["model"], "pairs": cell["pairs"], "shapes": cell.get("shapes"),
                    "recall": vrnet[RECALL], "RMSE(R)": vrnet["RMSE(R)"], "seconds_per_pair": vrnet["seconds_per_pair"],
                    "search_below": cell["solve"].get("rotation_search_below", 0),
                    "polish_iterations": cell["solve"].get("polish_iterations", 0),
                    "search_polish": cell["solve"].get("rotation_search_polish", 0),
                    "icp_starts": icp_search(cell["solve"]),
                    "turn_penalty": cell["solve"].get("rotation_search_turn_penalty", 0.0),
                    "source": str(path.relative_to(folder.parent))}
    rows = []
    for (setting, split, pairs_of), measured in estimates.items():
        first = next(iter(measured.values()))
        for estimate, value in measured.items():
            if any(value[field] != first[field] for field in ("model", "pairs", "shapes")):
                raise ValueError(f"{value['source']}: {setting} / {split}, {pairs_of} measured with another model, "
                                 f"pair count or shapes than {first['source']}")
        row = {"setting": setting, "split": split, "pairs_of": pairs_of, "model": first["model"],
               "pairs": first["pairs"]}
        for estimate, value in measured.items():
            row[estimate] = {field: value[field] for field in
                             ("recall", "RMSE(R)", "seconds_per_pair", "search_below", "polish_iterations",
                              "search_polish", "icp_starts", "turn_penalty", "source")}
        rows.append(row)
    order = {(s, p): i for i, (s, p) in enumerate((s, p) for p in SPLITS for s in SETTINGS)}
    return sorted(rows, key=lambda r: (r["pairs_of"], order[(r["setting"], r["split"])]))


def icp_search(solve: dict) -> int | str:
    """A recorded solve's multi-start ICP: its starts (0: none), with its slides and ICP where not 1 and robust."""
    starts = solve.get("rotation_search_icp_starts", 0)
    slides, icp = solve.get("rotation_search_icp_slides", 1), solve.get("rotation_search_icp", DEFAULT_SEARCH_ICP)
    return starts if not starts or (slides, icp) == (1, DEFAULT_SEARCH_ICP) else f"{starts} × {slides}, {icp}"


def markdown(rows: list[dict], note: str) -> str:
    lines = [note, "", "| pairs | cell | model | pairs measured | recall alone | recall with search | "
             "RMSE(R) alone | RMSE(R) with search | paper RMSE(R) (protocol) | s / pair alone | s / pair with search | "
             "polish steps | search polish steps | search ICP starts | search turn penalty |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        paper = PAPER.get((row["setting"], row["split"]), {}).get("VRNet", ("–",))[0]
        cells = []
        for field, form in (("recall", "{:.1%}"), ("RMSE(R)", "{:.3g}"), ("seconds_per_pair", "{:.3f}"),
                            ("polish_iterations", "{}")):
            cells.append([form.format(row[e][field]) if e in row else "–" for e in ESTIMATES])
        lines.append(f"| {row['pairs_of']} | {row['setting']} / {row['split']} | `{row['model']}` | {row['pairs']} | "
                     f"{cells[0][0]} | {cells[0][1]} | {cells[1][0]} | {cells[1][1]} | {paper} | "
                     f"{cells[2][0]} | {cells[2][1]} | {' / '.join(cells[3])} | "
                     f"{row['search']['search_polish'] if 'search' in row else '–'} | "
                     f"{row['search']['icp_starts'] if 'search' in row else '–'} | "
                     f"{format(row['search']['turn_penalty'], 'g') if 'search' in row else '–'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--tables", type=Path, nargs="+", required=True,
                        help="folders of modelnet40_tables.py JSON files, read in order (a later folder's estimate "
                             "of a cell replaces an earlier one's)")
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
        print(f"modelnet40_rotations: no modelnet40_tables.py JSON in {', '.join(map(str, args.tables))}",
              file=sys.stderr)
        return 2
    args.json.write_text(json.dumps({"note": args.note, "rows": rows}, indent=1))
    args.markdown.write_text(markdown(rows, args.note))
    print(markdown(rows, args.note))
    print(f"wrote {args.json} and {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
