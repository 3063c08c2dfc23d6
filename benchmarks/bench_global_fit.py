"""The robust-fit stage alone on the real pairs: spatial consistency (``sc2``) against our RANSAC
(``fpfh``), on the same FPFH descriptors, in one process.

    python benchmarks/bench_global_fit.py [--real-pairs ../shared/data/scenes/real_pairs] [--seeds 3]
                                          [--json global_fit.json] [--markdown global_fit.md]

Per pair: both scans voxel-downsampled to about 5,000 points and described by FPFH once (not
timed); then, per seed, each method's matching + fit is timed: ``sc2`` = every source point's
nearest target descriptor + ``ops.spatial_consistency``; ``fpfh`` = mutual nearest descriptors +
``ransac`` (up to 1,000,000 hypotheses, Open3D's early stop). Success of the estimate:
``RealPair.registered`` (RE < 15 deg and TE < 30 cm indoors, RE < 5 deg and TE < 2 m for KITTI). Reports recall per subset and the
median seconds per pair of each method, and their ratio.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext import ops
from vrnet_ext.data.real_pairs import read_manifest
from vrnet_ext.geometry.features import mutual_matches, nearest_features
from vrnet_ext.geometry.io import read_points, read_transform
from vrnet_ext.registration import PointCounts, ScanPair, SpatialConsistency, transform_errors
from vrnet_ext.registration.ransac import ransac
from outputs import write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_PAIRS = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs"
POINTS = 5000


def fit_sc2(src, tgt, src_features, tgt_features, voxel, seed):
    nearest = nearest_features(src_features, tgt_features)
    settings = SpatialConsistency()
    transform, _ = ops.spatial_consistency(src, tgt[nearest], 2.0 * voxel, 2.0 * voxel, settings.seeds,
                                           settings.consensus)
    return transform


def fit_fpfh(src, tgt, src_features, tgt_features, voxel, seed):
    return ransac(src, tgt, mutual_matches(src_features, tgt_features), 1.5 * voxel, seed=seed)[0]


METHODS = {"sc2": fit_sc2, "fpfh": fit_fpfh}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--real-pairs", default=str(DEFAULT_PAIRS),
                        help="a real_pairs folder (MANIFEST.tsv, clouds/, gt/)")
    parser.add_argument("--seeds", type=int, default=3, help="runs per pair and fit (seeds 0, 1, ...)")
    parser.add_argument("--max-pairs", type=int, default=None, help="first N pairs only")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    records = []
    for pair in read_manifest(args.real_pairs)[:args.max_pairs]:
        src_view, tgt_view = ScanPair.of(read_points(pair.source), read_points(pair.target),
                                         PointCounts(global_points=POINTS)).global_views()
        src, tgt, voxel = src_view.tensor(), tgt_view.tensor(), src_view.voxel
        src_features, tgt_features = src_view.descriptors, tgt_view.descriptors
        truth = read_transform(pair.gt)
        for seed in range(args.seeds):
            for method, fit in METHODS.items():  # in turns, pair by pair
                start = time.perf_counter()
                transform = fit(src, tgt, src_features, tgt_features, voxel, seed)
                seconds = time.perf_counter() - start
                errors = transform_errors(transform.numpy(), truth)
                records.append({"pair": pair.pair_id, "subset": pair.subset, "seed": seed, "method": method,
                                "seconds": seconds,
                                "success": pair.registered(errors["rotation_error_deg"], errors["translation_error"])})
        print(pair.pair_id, {m: round(statistics.median(r["seconds"] for r in records
                                                        if r["pair"] == pair.pair_id and r["method"] == m), 4)
                             for m in METHODS}, flush=True)
    rows = []
    for method in METHODS:
        mine = [r for r in records if r["method"] == method]
        per_pair = {}
        for r in mine:
            per_pair.setdefault(r["pair"], []).append(r["seconds"])
        row = {"method": method, "median_s": statistics.median(statistics.median(v) for v in per_pair.values())}
        for subset in ("3DMatch", "3DLoMatch", "KITTI", "all"):
            runs = [r for r in mine if subset == "all" or r["subset"] == subset]
            row[subset] = sum(r["success"] for r in runs) / len(runs) if runs else float("nan")
        rows.append(row)
    ratio = rows[0]["median_s"] / rows[1]["median_s"]
    lines = ["| method | 3DMatch | 3DLoMatch | KITTI | all | median s per pair (matching + fit) |",
             "|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['method']} | {r['3DMatch']:.3f} | {r['3DLoMatch']:.3f} | {r['KITTI']:.3f} | {r['all']:.3f} | "
              f"{r['median_s']:.4f} |" for r in rows]
    pairs = len({r["pair"] for r in records})
    lines.append(f"\nsc2 / fpfh median time: {ratio:.2f}. {pairs} pairs x {args.seeds} seeds, global estimate only, "
                 f"{platform.machine()}, {os.cpu_count()} cpus, {torch.get_num_threads()} threads, torch "
                 f"{torch.__version__}, {time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"rows": rows, "ratio": ratio, "records": records}, args.markdown, args.json)


if __name__ == "__main__":
    main()
