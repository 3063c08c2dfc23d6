"""Registration pipeline against Open3D on the shared scan pairs: time, RE, TE, peak RSS.

    python benchmarks/bench_register.py [--data ../shared/data/scenes] [--repeats 3]
                                        [--json bench_register.json] [--markdown bench_register.md]

Every run is a fresh process (so time and peak RSS include imports and reading the scans), and
the implementations take turns within each repetition (interleaved), so a machine that slows
down mid-run slows all alike. Same settings on both sides: the global estimate works on the scans
voxel-downsampled to about 5,000 points (``vrnet_ext.geometry.preprocessing.voxel_size_for``, which the
benchmark runs beforehand for Open3D and hands it the two voxel edges, so Open3D's time leaves
that search out while ours includes it; FPFH radius
5 voxels with at most 100 neighbours, RANSAC inliers within 1.5 voxels, Open3D's tutorial
checkers and its 100,000 iterations / 0.999 confidence), ICP on about 50,000 points with reach 3
ICP voxels. Rows:

* ``ours default + point_to_plane``: ``vrnet register`` with its default method;
* ``ours fpfh + <estimator>``: ``vrnet register --method fpfh --icp-step E``;
* ``ours vrnet + point_to_plane``: the shipped scene model (``--method vrnet``);
* ``open3d fpfh + <estimator>``: Open3D's ``registration_ransac_based_on_feature_matching`` then
  ``registration_icp`` (point-to-point, point-to-plane) or ``registration_generalized_icp``.

Open3D is optional: without it, its rows are skipped with the reason. ``--beside-busy`` keeps one
core busy with another process for the whole run (a shared machine).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_large_scene import DEFAULT_DATA, pairs  # noqa: E402

from vrnet_ext.cli.common import DefaultsHelpFormatter  # noqa: E402
from vrnet_ext.geometry.io import read_points  # noqa: E402
from vrnet_ext.geometry.preprocessing import voxel_size_for  # noqa: E402

GLOBAL_POINTS, ICP_POINTS = 5000, 50_000
SUCCESS_RE_DEG, SUCCESS_TE_M = 15.0, 0.3

OPEN3D_SCRIPT = textwrap.dedent(f"""
    import json, resource, sys, time
    start = time.perf_counter()
    sys.path.insert(0, {str(ROOT / "benchmarks")!r})
    import numpy as np
    from open3d_pipeline import cloud, features, global_estimate, icp_clouds, refine
    from vrnet_ext.geometry.io import read_points
    src_path, tgt_path, estimator, out = sys.argv[1:5]
    voxel, icp_voxel = float(sys.argv[5]), float(sys.argv[6])
    global_method = sys.argv[7] if len(sys.argv) > 7 else "ransac"
    src_points, tgt_points = read_points(src_path), read_points(tgt_path)
    begin = time.perf_counter()
    src, tgt = cloud(src_points), cloud(tgt_points)
    ransac = global_estimate(features(src, voxel), features(tgt, voxel), voxel, global_method)
    icp = refine(*icp_clouds(src, tgt, icp_voxel, estimator), icp_voxel, ransac.transformation, estimator)
    seconds = time.perf_counter() - begin
    json.dump({{"transform": np.asarray(icp.transformation).tolist(), "initial": np.asarray(ransac.transformation).tolist(),
               "register_s": seconds, "fitness": icp.fitness,
               "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}}, open(out, "w"))
""")


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    cos = (np.trace(estimate[:3, :3].T @ truth[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


def run_ours(pair: dict, method: str | None, estimator: str, out: Path, seed: int = 0) -> dict:
    """`vrnet register` in a fresh process (method None: its default)."""
    chosen = [] if method is None else ["--method", method]
    cmd = [sys.executable, "-m", "vrnet_ext.cli", "register", str(pair["source"]), str(pair["target"]), *chosen,
           "--icp-step", estimator, "--global-points", str(GLOBAL_POINTS), "--icp-points", str(ICP_POINTS),
           "--seed", str(seed), "--json", str(out)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["?"])[-1], "process_s": wall}
    result = json.loads(out.read_text())
    return {"transform": result["T_target_source"], "register_s": sum(result["seconds"].values()),
            "stage_s": result["seconds"],
            "peak_rss_mb": result["peak_rss_mb"], "process_s": wall, "fitness": result["fitness"],
            "start": result.get("start", "")}


def run_open3d(pair: dict, estimator: str, out: Path, global_method: str = "ransac") -> dict:
    """Open3D's FPFH + RANSAC (or FGR) + ICP in a fresh process, on our voxel edges."""
    voxels = [str(voxel_size_for(read_points(pair["target"]), points)) for points in (GLOBAL_POINTS, ICP_POINTS)]
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", OPEN3D_SCRIPT, str(pair["source"]), str(pair["target"]), estimator,
                           str(out), *voxels, global_method], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["?"])[-1], "process_s": wall}
    return dict(json.loads(out.read_text()), process_s=wall)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the shared scenes folder")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per pair and estimator, in turns")
    parser.add_argument("--pairs", nargs="+", default=None, help="only pairs whose name contains one of these")
    parser.add_argument("--estimators", nargs="+", default=["point_to_point", "point_to_plane", "gicp"],
                        help="ICP estimators to time")
    parser.add_argument("--json", default="bench_register.json", help="where the JSON goes")
    parser.add_argument("--markdown", default="bench_register.md", help="where the Markdown goes")
    parser.add_argument("--beside-busy", action="store_true",
                        help="run beside another process that keeps one core busy (a shared machine)")
    args = parser.parse_args(argv)
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.beside_busy else None
    try:
        _run(args)
    finally:
        if busy is not None:
            busy.kill()


def _run(args: argparse.Namespace) -> None:
    have_open3d = importlib.util.find_spec("open3d") is not None
    rows: dict[tuple[str, str], list[dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        todo = pairs(Path(args.data), workdir, args.pairs)
        if not todo:
            raise SystemExit(f"bench_register: no scan pairs under {args.data}")
        runners = [("ours default + point_to_plane", lambda p, o: run_ours(p, None, "point_to_plane", o))]
        runners += [(f"ours fpfh + {e}", lambda p, o, e=e: run_ours(p, "fpfh", e, o)) for e in args.estimators]
        runners.append(("ours vrnet + point_to_plane", lambda p, o: run_ours(p, "vrnet", "point_to_plane", o)))
        if have_open3d:
            runners += [(f"open3d fpfh + {e}", lambda p, o, e=e: run_open3d(p, e, o)) for e in args.estimators]
        for pair in todo:
            truth = np.loadtxt(pair["gt"])
            for repeat in range(args.repeats):
                for name, runner in runners:  # interleaved: every implementation once per repetition
                    record = runner(pair, workdir / "out.json")
                    if "transform" in record:
                        re, te = errors(np.array(record["transform"]), truth)
                        record.update(rotation_error_deg=re, translation_error_m=te,
                                      success=re < SUCCESS_RE_DEG and te < SUCCESS_TE_M)
                        del record["transform"]
                    rows.setdefault((pair["name"], name), []).append(record)
                    print(pair["name"], name, repeat, json.dumps(record), flush=True)
    summary = []
    for (pair_name, name), records in rows.items():
        good = [r for r in records if "error" not in r]
        entry = {"pair": pair_name, "implementation": name, "runs": len(records), "failed": len(records) - len(good)}
        for key in ("register_s", "process_s", "peak_rss_mb", "rotation_error_deg", "translation_error_m"):
            values = [r[key] for r in good if key in r]
            if values:
                entry[key] = statistics.median(values)
        entry["success"] = all(r.get("success") for r in good) and bool(good)
        summary.append(entry)
    lines = ["| pair | implementation | register (s) | process (s) | RE (deg) | TE (cm) | success | peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|"]
    for e in summary:
        if "register_s" not in e:
            lines.append(f"| {e['pair']} | {e['implementation']} | failed | | | | | |")
            continue
        lines.append(f"| {e['pair']} | {e['implementation']} | {e['register_s']:.2f} | {e['process_s']:.2f} | "
                     f"{e['rotation_error_deg']:.2f} | {100 * e['translation_error_m']:.1f} | "
                     f"{'yes' if e['success'] else 'no'} | {e['peak_rss_mb']:.0f} |")
    if not have_open3d:
        lines.append("\nOpen3D rows skipped: `open3d` is not installed (pip install open3d; needs libusb-1.0-0).")
    table = "\n".join(lines)
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} cpus", "date": time.strftime("%Y-%m-%d"),
            "repeats": args.repeats, "threads": os.environ.get("OMP_NUM_THREADS", "default"),
            "beside_busy": args.beside_busy}
    Path(args.json).write_text(json.dumps({"meta": meta, "summary": summary,
                                           "runs": {f"{p} | {n}": r for (p, n), r in rows.items()}}, indent=1))
    Path(args.markdown).write_text(table + "\n")
    print(table)
    busy = ", beside a process keeping one core busy" if args.beside_busy else ""
    print(f"medians of {args.repeats} interleaved runs{busy}; wrote {args.json} and {args.markdown}")


if __name__ == "__main__":
    main()
