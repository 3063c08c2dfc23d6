"""The README's results table, rendered from a bench_real_pairs.py JSON (never copied by hand).

    python benchmarks/results_table.py benchmarks/results/2026-12-02/real_pairs.json

tests/test_docs.py checks that the README holds exactly this rendering of the JSON it links.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

SUBSETS = ("3DMatch", "3DLoMatch", "KITTI", "kitchen/LiDAR", "all")
# "default" repeats whichever method was the default when the JSON was measured (its meta names it; a JSON
# without that name measured the default as sc2): the table names the methods themselves, the default marked.
LABELS = {"fpfh": "`--method fpfh`", "sc2": "`--method sc2`", "vrnet": "`--method vrnet`", "fgr": "`--method fgr`",
          "open3d-ransac": "Open3D RANSAC + ICP", "open3d-fgr": "Open3D FGR + ICP"}


def label(method: str, default: str) -> str:
    if method == "default":
        return f"`vrnet register` (the default, `{default}`)"
    return LABELS.get(method, method) + (" (the default)" if method == default else "")


def render(record: dict) -> str:
    rows = {(r["method"], r["subset"]): r for r in record["summary"]}
    measured = list(dict.fromkeys(r["method"] for r in record["summary"]))
    default = record.get("meta", {}).get("default_method", "sc2")
    methods = [m for m in measured if m != "default" or default not in measured]
    lines = ["| method | " + " | ".join(f"{s} recall" for s in SUBSETS) + " | RE median (°) | s / pair |",
             "|---|" + "---:|" * (len(SUBSETS) + 2)]
    for method in methods:
        cells = []
        for subset in SUBSETS:
            r = rows.get((method, subset))
            cells.append(f"{100 * r['recall']:.0f} % ({r['successes']}/{r['runs']})" if r else "–")
        everything = rows[(method, "all")]
        lines.append(f"| {label(method, default)} | " + " | ".join(cells) +
                     f" | {everything['median_re_deg']:.2f} | {everything['median_process_s']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("json", help="a bench_real_pairs.py JSON")
    path = Path(parser.parse_args().json)
    if not path.is_file():
        parser.error(f"json: {path} is not a file")
    print(render(json.loads(path.read_text())))
