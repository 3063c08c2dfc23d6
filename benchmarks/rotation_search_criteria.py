"""How the rotation search should choose among its starts, on validation pairs: for every pair, the
24 starts of the search (the cube's rotations, each with the second look the model takes) and which
start each criterion would keep, against the best any start reaches.

    python benchmarks/rotation_search_criteria.py [--models vrnet-pv-nd-rcp ...] [--pairs 60]
                                                  [--rotation-range so3] [--json criteria.json]

Pairs: ``--pairs`` shapes spread evenly over each model's cell, partition ``val`` (the shapes training
holds out for choosing), seed 99, rotations drawn by ``--rotation-range``. Per pair and start: the
model's estimate from the source turned by the start, then a pass from that estimate, whichever
agrees more with its RCPs (as ``VRNet._rotation_search`` takes each start). Criteria, each keeping
the start with the best score: the RCPs' agreement (``consistency``), the median distance from the
moved source to the nearest target point (``median_nn``), the mean of that distance cut at 0.1 and
0.2 (``chamfer_*``), the share of moved source points within 0.05 of a target point
(``fitness_0.05``). ``oracle``: a start registers the pair (rotation error below 5 degrees).
"""
from __future__ import annotations

import argparse
import time

import torch

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

DEFAULT_MODELS = ["vrnet-pv-nd-rcp", "vrnet-rs-nd-rcp", "vrnet-co-nd-rcp", "vrnet-pv-upc-rcp", "vrnet-pvrs-uc-rcp"]
CRITERIA = ("oracle", "consistency", "median_nn", "chamfer_0.1", "chamfer_0.2", "fitness_0.05")
SUCCESS_DEG = 5.0


def starts_of(model, src: torch.Tensor, tgt: torch.Tensor, starts: torch.Tensor):
    """Every start's estimate of one pair (src, tgt (1, N, 3)) as the search takes it -> (R, t, consistency)."""
    from vrnet_ext.geometry.transforms import compose, move

    count = len(starts)
    src, tgt = src.expand(count, -1, -1), tgt.expand(count, -1, -1)
    first = model(move(src, starts, torch.zeros(count, 3)), tgt)
    R1, t1 = first.rotation @ starts, first.translation
    again = model(move(src, R1, t1), tgt)
    R2, t2 = compose(again.rotation, again.translation, R1, t1)
    consistency2 = model._consistency(src, R2, t2, again.rcp)
    looked = consistency2 > first.consistency
    return (torch.where(looked[:, None, None], R2, R1), torch.where(looked[:, None], t2, t1),
            torch.maximum(consistency2, first.consistency))


def scores(src, tgt, rotation, translation, consistency) -> dict[str, torch.Tensor]:
    from vrnet_ext import ops
    from vrnet_ext.geometry.transforms import move

    count = len(rotation)
    moved = move(src.expand(count, -1, -1), rotation, translation).contiguous()
    distance = ops.knn(moved, tgt.expand(count, -1, -1).contiguous(), 1)[0][..., 0].sqrt()
    return {"consistency": consistency, "median_nn": -distance.median(dim=1).values,
            "chamfer_0.1": -distance.clamp(max=0.1).mean(dim=1), "chamfer_0.2": -distance.clamp(max=0.2).mean(dim=1),
            "fitness_0.05": (distance < 0.05).float().mean(dim=1)}


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext import load_pretrained
    from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter
    from vrnet_ext.data.modelnet import ModelNet40Pairs
    from vrnet_ext.data.protocol import ROTATION_RANGES, PairSpec
    from vrnet_ext.geometry.metrics import rotation_error_deg
    from vrnet_ext.geometry.transforms import cube_rotations
    from vrnet_ext.model.pretrained import cells

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="+", default=DEFAULT_MODELS, help="shipped names")
    parser.add_argument("--pairs", type=int, default=60, help="validation shapes per model")
    parser.add_argument("--rotation-range", choices=ROTATION_RANGES, default="so3", help="the pairs' rotations")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    starts = torch.as_tensor(cube_rotations(), dtype=torch.float32)
    rows = []
    for name in args.models:
        model = load_pretrained(name).eval()
        model.config.second_pass_below = model.config.rotation_search_below = 0.0
        setting, split = cells(name)[0].split("/")  # the first cell the model serves
        data = ModelNet40Pairs(args.data_dir, partition="val", setting=setting, split=split, max_items=args.pairs, seed=99,
                               spec=PairSpec(setting=setting, rotation_range=args.rotation_range))
        kept = dict.fromkeys(CRITERIA, 0)
        begin = time.perf_counter()
        for index in range(len(data)):
            item = data[index]
            src, tgt = item["src"][None], item["tgt"][None]
            with torch.no_grad():
                rotation, translation, consistency = starts_of(model, src, tgt, starts)
                scored = scores(src, tgt, rotation, translation, consistency)
            right = rotation_error_deg(rotation, item["rotation"].expand(len(starts), 3, 3)) < SUCCESS_DEG
            kept["oracle"] += bool(right.any())
            for criterion, score in scored.items():
                kept[criterion] += bool(right[score.argmax()])
        rows.append({"model": name, "cell": f"{setting} / {split}", "pairs": len(data),
                     **{criterion: kept[criterion] / len(data) for criterion in CRITERIA},
                     "seconds": time.perf_counter() - begin})
    lines = [f"Which start the rotation search keeps, by criterion ({len(starts)} starts with their second looks; "
             f"validation pairs, seed 99, rotations {args.rotation_range}; {cpu_description()}, "
             f"{time.strftime('%Y-%m-%d')}): the share of pairs whose kept start is right (rotation error below "
             f"{SUCCESS_DEG:g} degrees).", "",
             "| model | cell | pairs | " + " | ".join(CRITERIA) + " |", "|---|---|---:|" + "---:|" * len(CRITERIA)]
    lines += [f"| `{row['model']}` | {row['cell']} | {row['pairs']} | "
              + " | ".join(f"{row[criterion]:.2f}" for criterion in CRITERIA) + " |" for row in rows]
    write_outputs("\n".join(lines), {"machine": cpu_description(), "date": time.strftime("%Y-%m-%d"),
                                     "rotation_range": args.rotation_range, "rows": rows}, args.markdown, args.json)


if __name__ == "__main__":
    main()
