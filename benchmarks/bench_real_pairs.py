"""Registration recall on the real scan pairs: every method of ours and Open3D's, in one run.

    python benchmarks/bench_real_pairs.py [--data ../shared/data/scenes] [--seeds 2]
        [--methods default fpfh sc2 vrnet fgr open3d-ransac open3d-fgr] [--extra-rotation 180]
        [--out-dir benchmarks/results/DATE]

Pairs: the 45 of ``real_pairs/`` (3DMatch and 3DLoMatch pairs of 7-scenes-redkitchen, KITTI
odometry) plus the kitchen fragments and the LiDAR pair. Every run is a fresh process
(``vrnet register``, or Open3D's pipeline of ``bench_register.py`` on the same voxel edges), the
methods take turns within each pair and seed. Success: rotation error < 15 deg and translation
error < 30 cm indoors; < 5 deg and < 2 m on KITTI and the LiDAR pair (the literature's thresholds).
``--extra-rotation D`` turns each source by a random rotation of up to D degrees about its centroid
first (a different one per seed; the ground truth follows), so that pairs 180 deg apart are tried.

Reported per method and subset (3DMatch, 3DLoMatch, KITTI, kitchen/LiDAR, and "unseen": the pairs
the shipped scene model never trained on, as its model card lists them): recall, median RE and
TE of the successes, median time of the registration and of the whole process, median peak RSS.
Writes real_pairs.json, real_pairs.md and real_pairs.png (recall against overlap) to --out-dir.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_large_scene import DEFAULT_DATA, pairs as shared_pairs  # noqa: E402
from bench_register import errors, run_open3d, run_ours  # noqa: E402

from vrnet_ext.cli.common import DefaultsHelpFormatter  # noqa: E402
from vrnet_ext.data.real_pairs import SUCCESS_THRESHOLDS, read_manifest  # noqa: E402
from vrnet_ext.names import DEFAULT_METHOD  # noqa: E402

METHODS = ("default", "fpfh", "sc2", "vrnet", "fgr", "open3d-ransac", "open3d-fgr")


def scene_model_training_pairs() -> set[str]:
    """The pair ids the shipped scene model (``--method vrnet``) was trained on, from its card."""
    from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, model_card

    return set(model_card(DEFAULT_SCENE_MODEL)["training"]["scans"].split(", "))


def real_pairs(data: Path, workdir: Path) -> list[dict]:
    """The pairs of real_pairs/MANIFEST.tsv and the kitchen / LiDAR pairs, with subset and overlap."""
    found = []
    if (data / "real_pairs" / "MANIFEST.tsv").exists():
        found = [{"name": pair.pair_id, "source": pair.source, "target": pair.target, "gt": pair.gt,
                  "subset": pair.subset, "overlap": pair.overlap, "outdoor": pair.outdoor}
                 for pair in read_manifest(data / "real_pairs")]
    for pair in shared_pairs(data, workdir):
        outdoor = pair["name"] == "LiDAR"
        found.append(dict(pair, subset="kitchen/LiDAR", overlap=float("nan"), outdoor=outdoor))
    return found


def rotated(pair: dict, degrees: float, seed: int, workdir: Path) -> dict:
    """The pair with its source turned by a random rotation of up to ``degrees`` about its centroid."""
    from scipy.spatial.transform import Rotation

    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.geometry.transforms import apply, to_homogeneous

    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(0.0, degrees))
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    source = read_points(pair["source"])
    centre = source.mean(axis=0)
    turn = to_homogeneous(R, centre - R @ centre)
    path = workdir / f"{pair['name'].replace(' ', '_').replace('>', '')}_s{seed}.npy"
    np.save(path, apply(turn, source))
    gt = workdir / f"{path.stem}_gt.txt"
    np.savetxt(gt, np.loadtxt(pair["gt"]) @ np.linalg.inv(turn))
    return dict(pair, source=path, gt=gt)


def run(method: str, pair: dict, seed: int, out: Path) -> dict:
    if method.startswith("open3d-"):
        return run_open3d(pair, "point_to_plane", out, method.split("-")[1])
    return run_ours(pair, None if method == "default" else method, "point_to_plane", out, seed)


def summarise(records: list[dict], methods: list[str]) -> list[dict]:
    subsets = ["3DMatch", "3DLoMatch", "KITTI", "kitchen/LiDAR", "unseen", "all"]
    rows = []
    for method in methods:
        for subset in subsets:
            chosen = [r for r in records if r["method"] == method and (
                subset == "all" or r["subset"] == subset or (subset == "unseen" and r["unseen"]))]
            if not chosen:
                continue
            good = [r for r in chosen if r.get("success")]
            ok = [r for r in chosen if "register_s" in r]

            def median(key, among):
                values = [r[key] for r in among if key in r]
                return statistics.median(values) if values else float("nan")

            rows.append({"method": method, "subset": subset, "runs": len(chosen), "successes": len(good),
                         "recall": len(good) / len(chosen), "failed_runs": len(chosen) - len(ok),
                         "median_re_deg": median("rotation_error_deg", good),
                         "median_te_m": median("translation_error_m", good),
                         "median_register_s": median("register_s", ok), "median_process_s": median("process_s", ok),
                         "median_peak_rss_mb": median("peak_rss_mb", ok)})
    return rows


def markdown(rows: list[dict], meta: dict) -> str:
    lines = [f"Real pairs, {meta['date']}, {meta['machine']}; {meta['seeds']} seed(s) per pair"
             + (f", sources turned by up to {meta['extra_rotation']} deg" if meta["extra_rotation"] else ""),
             "", "| method | subset | recall | successes / runs | RE median (deg) | TE median (cm) | "
             "register median (s) | process median (s) | peak RSS median (MB) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['subset']} | {100 * r['recall']:.1f} % | {r['successes']} / {r['runs']} | "
                     f"{r['median_re_deg']:.3f} | {100 * r['median_te_m']:.2f} | {r['median_register_s']:.2f} | "
                     f"{r['median_process_s']:.2f} | {r['median_peak_rss_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def plot(records: list[dict], methods: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = [0.0, 0.2, 0.3, 0.5, 1.0]
    fig, ax = plt.subplots(figsize=(7, 4))
    centres = [0.5 * (lo + hi) for lo, hi in zip(bins, bins[1:])]
    for method in methods:
        recall = []
        for lo, hi in zip(bins, bins[1:]):
            chosen = [r for r in records if r["method"] == method and lo <= r["overlap"] < hi]
            recall.append(100 * sum(bool(r.get("success")) for r in chosen) / len(chosen) if chosen else np.nan)
        ax.plot(centres, recall, marker="o", label=method)
    ax.set_xlabel("overlap (share of source points within 2.5 cm / KITTI radius under the ground truth)")
    ax.set_ylabel("registration recall (%)")
    ax.set_title("Recall against overlap, real pairs")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the shared scenes folder")
    parser.add_argument("--seeds", type=int, default=2, help="runs per pair and method (seeds 0, 1, ...)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS,
                        help="methods to run (the open3d ones only where open3d is installed)")
    parser.add_argument("--pairs", nargs="+", default=None, help="only pairs whose name contains one of these")
    parser.add_argument("--extra-rotation", type=float, default=0.0,
                        help="turn each source by a random rotation of up to this many degrees first")
    parser.add_argument("--out-dir", default=str(ROOT / "benchmarks" / "results" / time.strftime("%Y-%m-%d")),
                        help="folder of the outputs")
    parser.add_argument("--name", default="real_pairs", help="file stem of the outputs")
    args = parser.parse_args(argv)
    methods = list(args.methods)
    if importlib.util.find_spec("open3d") is None:
        skipped = [m for m in methods if m.startswith("open3d")]
        methods = [m for m in methods if not m.startswith("open3d")]
        if skipped:
            print(f"bench_real_pairs: skipping {skipped}: open3d is not installed (pip install open3d)")
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        todo = [p for p in real_pairs(Path(args.data), workdir)
                if not args.pairs or any(word in p["name"] for word in args.pairs)]
        if not todo:
            raise SystemExit(f"bench_real_pairs: no pairs under {args.data}")
        total = len(todo) * args.seeds * len(methods)
        trained_on = scene_model_training_pairs()
        for pair in todo:
            max_re, max_te = SUCCESS_THRESHOLDS["outdoor" if pair["outdoor"] else "indoor"]
            for seed in range(args.seeds):
                case = rotated(pair, args.extra_rotation, seed, workdir) if args.extra_rotation else pair
                truth = np.loadtxt(case["gt"])
                for method in methods:  # interleaved: every method once per pair and seed
                    record = run(method, case, seed, workdir / "out.json")
                    if "transform" in record:
                        re, te = errors(np.array(record.pop("transform")), truth)
                        record.update(rotation_error_deg=re, translation_error_m=te, success=re < max_re and te < max_te)
                    record.update(pair=pair["name"], method=method, seed=seed, subset=pair["subset"],
                                  overlap=pair["overlap"], unseen=pair["name"] not in trained_on)
                    record.pop("initial", None)
                    records.append(record)
                    print(f"[{len(records)}/{total}] {pair['name']} seed {seed} {method}: "
                          f"{'ok' if record.get('success') else 'FAIL'} "
                          f"RE {record.get('rotation_error_deg', float('nan')):.2f} "
                          f"TE {record.get('translation_error_m', float('nan')):.3f} "
                          f"{record.get('process_s', float('nan')):.1f} s {record.get('error', '')}", flush=True)
    rows = summarise(records, methods)
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} cpus", "date": time.strftime("%Y-%m-%d"),
            "seeds": args.seeds, "extra_rotation": args.extra_rotation, "pairs": len(todo),
            "thresholds": SUCCESS_THRESHOLDS, "default_method": DEFAULT_METHOD}
    stem = out_dir / args.name
    Path(f"{stem}.json").write_text(json.dumps({"meta": meta, "summary": rows, "runs": records}, indent=1))
    Path(f"{stem}.md").write_text(markdown(rows, meta))
    plot(records, methods, Path(f"{stem}.png"))
    print(markdown(rows, meta))
    print(f"wrote {stem}.json, {stem}.md and {stem}.png")


if __name__ == "__main__":
    main()
