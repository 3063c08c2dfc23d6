"""Selects a scene model on the validation pairs of ``real_pairs/`` (never on the pairs it trained on).

    python benchmarks/scene_validation.py --real-pairs ../shared/data/scenes/real_pairs \
        --checkpoint runs/scene_real/model.pt [--checkpoint scene-fpfh-vrnet-kitchen] [--seeds 3] \
        [--json scene_validation.json]

For each validation pair (:func:`vrnet_ext.data.real_pairs.split`) and seed: the global estimate
alone (no ICP, no second start) of each checkpoint's scene network (its RCPs fitted by RANSAC and
by spatial consistency), of ``fpfh`` (FPFH + RANSAC)
and of ``sc2`` (spatial consistency), on both scans voxel-downsampled to about 5,000 points.
Success: ``RealPair.registered`` (RE < 15 deg and TE < 30 cm indoors, RE < 5 deg and TE < 2 m for KITTI). Prints recall per
kind and overall, the median RE / TE of successes and the median seconds per estimate; writes JSON.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.data.real_pairs import read_manifest, split
from vrnet_ext.geometry.io import read_points, read_transform
from vrnet_ext.model.pretrained import load_model
from vrnet_ext.registration import FpfhRansac, PointCounts, ScanPair, SpatialConsistency, transform_errors
from vrnet_ext.registration.global_estimators import ROBUST_FITS, SceneNetwork
from outputs import write_outputs  # benchmarks/, the script's folder

POINTS = 5000


def global_estimators(checkpoints: list[str]) -> dict:
    found = {"fpfh": FpfhRansac(), "sc2": SpatialConsistency()}
    for checkpoint in checkpoints:
        model, _ = load_model(checkpoint)
        for robust in ROBUST_FITS:
            found[f"{Path(checkpoint).stem} + {robust}"] = SceneNetwork(model, robust=robust)
    return found


def summary(records: list[dict]) -> list[dict]:
    rows = []
    for method in dict.fromkeys(r["method"] for r in records):
        mine = [r for r in records if r["method"] == method]
        row = {"method": method}
        for subset in ("3DMatch", "3DLoMatch", "KITTI", "all"):
            runs = [r for r in mine if subset == "all" or r["subset"] == subset]
            row[subset] = sum(r["success"] for r in runs) / len(runs) if runs else float("nan")
        good = [r for r in mine if r["success"]]
        row["median_re_deg"] = statistics.median(r["re_deg"] for r in good) if good else float("nan")
        row["median_te_m"] = statistics.median(r["te_m"] for r in good) if good else float("nan")
        row["median_s"] = statistics.median(r["seconds"] for r in mine)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--real-pairs", required=True, help="a real_pairs folder (MANIFEST.tsv, clouds/, gt/)")
    parser.add_argument("--checkpoint", action="append", default=[], help="a scene model (file or shipped name)")
    parser.add_argument("--seeds", type=int, default=3, help="runs per pair and estimate (seeds 0, 1, ...)")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    _, validation = split(read_manifest(args.real_pairs))
    methods = global_estimators(args.checkpoint)
    records = []
    for pair in validation:
        src, tgt, truth = read_points(pair.source), read_points(pair.target), read_transform(pair.gt)
        for seed in range(args.seeds):
            for name, estimator in methods.items():
                torch.manual_seed(seed)
                start = time.perf_counter()
                prepared = ScanPair.of(src, tgt, PointCounts(global_points=POINTS))  # each estimate prepares anew
                estimate = estimator.estimate_pair(prepared, seed=seed).T_target_source
                seconds = time.perf_counter() - start
                errors = transform_errors(np.asarray(estimate), truth)
                records.append({"pair": pair.pair_id, "subset": pair.subset, "seed": seed, "method": name,
                                "re_deg": errors["rotation_error_deg"], "te_m": errors["translation_error"],
                                "success": pair.registered(errors["rotation_error_deg"], errors["translation_error"]),
                                "seconds": seconds})
        done = {m: sum(r["success"] for r in records if r["pair"] == pair.pair_id and r["method"] == m) for m in methods}
        print(pair.pair_id, done, flush=True)
    rows = summary(records)
    lines = ["| global estimate | 3DMatch | 3DLoMatch | KITTI | all | median RE (deg) | median TE (cm) | median s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {row['method']} | {row['3DMatch']:.3f} | {row['3DLoMatch']:.3f} | "
              f"{row['KITTI']:.3f} | {row['all']:.3f} | {row['median_re_deg']:.3f} | "
              f"{100 * row['median_te_m']:.1f} | {row['median_s']:.3f} |" for row in rows]
    lines.append(f"\nRecall (share of runs) on the {len(validation)} validation pairs x {args.seeds} seeds, global "
                 f"estimate only (no ICP), {time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"pairs": [p.pair_id for p in validation], "seeds": args.seeds,
                                               "summary": rows, "records": records}, args.markdown, args.json)


if __name__ == "__main__":
    main()
