"""Large real scenes under a memory budget: `vrnet register` end to end on the shared scan pairs.

    python benchmarks/bench_large_scene.py [--data ../shared/data/scenes] [--heldout-dir DIR]
                                           [--budgets 2GB 4GB] [--methods vrnet fpfh] [--json r.json]
                                           [--markdown r.md] [--skip-synthetic]

Each run is a fresh `vrnet register SRC TGT --method M --max-memory B` process (so its peak RSS is
the whole program's, imports included): rotation error RE, translation error TE, success
(RE < 15 deg and TE < 0.3 m), the wall time of the process and of the registration alone, and the
peak RSS. Pairs: the three 3DMatch kitchen pairs at full resolution (source = fragment j, target =
fragment i for the ground truth T_i_j) and the LiDAR pair.

Held-out models: `--method vrnet` on kitchen pair (i, j) uses ``DIR/only<k>.pt``, the scene model
trained (``vrnet train-scene``) on the third fragment k alone, when ``--heldout-dir`` is given;
otherwise the shipped scene model (trained on all three fragments, so the kitchen rows then are
not a held-out result and the table says so). The LiDAR pair always uses the shipped model, which
never saw a LiDAR scan.

Also: a synthetic pair of two 1,000,000-point room scans (a known motion, independent sampling)
under the largest budget, and the memory of the soft matching itself: the dense (N x M matrix)
path measured where it fits and extrapolated (x N^2) above, against the streamed ``ops.soft_match``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.data.procedural import room_scan

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "scenes"
KITCHEN_PAIRS = [(0, 4), (0, 10), (4, 10)]
SUCCESS_RE_DEG, SUCCESS_TE_M = 15.0, 0.3


def kitchen_truth(data: Path, i: int, j: int) -> np.ndarray:
    lines = (data / "3dmatch_redkitchen" / "gt_pairs.txt").read_text().splitlines()
    start = lines.index(f"pair {i} {j}")
    return np.array([[float(v) for v in line.split()] for line in lines[start + 1:start + 5]])


def pairs(data: Path, workdir: Path, only: list[str] | None = None) -> list[dict]:
    """The shared pairs found under ``data`` (only those whose name contains one of ``only``)."""
    return [pair for pair in _all_pairs(data, workdir) if not only or any(word in pair["name"] for word in only)]


def _all_pairs(data: Path, workdir: Path) -> list[dict]:
    found = []
    kitchen = data / "3dmatch_redkitchen"
    for i, j in KITCHEN_PAIRS:
        if not (kitchen / f"cloud_bin_{i}.ply").exists() or not (kitchen / f"cloud_bin_{j}.ply").exists():
            continue
        gt = workdir / f"gt_{i}_{j}.txt"
        np.savetxt(gt, kitchen_truth(data, i, j))
        heldout = ({0, 4, 10} - {i, j}).pop()
        found.append({"name": f"kitchen {j}->{i}", "source": kitchen / f"cloud_bin_{j}.ply",
                      "target": kitchen / f"cloud_bin_{i}.ply", "gt": gt, "heldout_fragment": heldout})
    lidar = data / "lidar_pair"
    if (lidar / "source.ply").exists():
        found.append({"name": "LiDAR", "source": lidar / "source.ply", "target": lidar / "target.ply",
                      "gt": lidar / "T_target_source.txt", "heldout_fragment": None})
    return found


def synthetic_pair(workdir: Path, points: int) -> dict:
    from scipy.spatial.transform import Rotation

    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("zyx", [25.0, 4.0, -3.0], degrees=True).as_matrix()
    truth[:3, 3] = [0.4, -0.3, 0.05]
    src, tgt = room_scan(points, 1), room_scan(points, 2) @ truth[:3, :3].T + truth[:3, 3]
    np.save(workdir / "room_src.npy", src.astype(np.float32))
    np.save(workdir / "room_tgt.npy", tgt.astype(np.float32))
    np.savetxt(workdir / "room_gt.txt", truth)
    return {"name": f"synthetic room {points // 1000}k", "source": workdir / "room_src.npy",
            "target": workdir / "room_tgt.npy", "gt": workdir / "room_gt.txt", "heldout_fragment": None}


def run_register(pair: dict, method: str, budget: str, checkpoint: str | None, workdir: Path) -> dict:
    out = workdir / "result.json"
    out.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "vrnet_ext.cli", "register", str(pair["source"]), str(pair["target"]),
           "--method", method, "--max-memory", budget, "--gt", str(pair["gt"]), "--json", str(out)]
    if checkpoint:
        cmd += ["--checkpoint", checkpoint]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    record = {"pair": pair["name"], "method": method, "budget": budget, "model": checkpoint or "shipped",
              "process_s": wall, "returncode": proc.returncode}
    if proc.returncode != 0 or not out.exists():
        record["error"] = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return record
    result = json.loads(out.read_text())
    errors, initial = result["errors"], result["errors_initial"]
    record.update(rotation_error_deg=errors["rotation_error_deg"], translation_error_m=errors["translation_error"],
                  initial_rotation_error_deg=initial["rotation_error_deg"],
                  initial_translation_error_m=initial["translation_error"],
                  register_s=sum(result["seconds"].values()), peak_rss_mb=result["peak_rss_mb"],
                  fitness=result["fitness"], warnings=result["warnings"], points=result["points"])
    record["success"] = (errors["rotation_error_deg"] < SUCCESS_RE_DEG and errors["translation_error"] < SUCCESS_TE_M)
    return record


def soft_match_memory(sizes: list[int], channels: int = 32, values: int = 35) -> list[dict]:
    """Peak RSS growth of one soft matching, dense reference vs streamed op (fresh process each)."""
    script = ("import re,sys,torch\nfrom vrnet_ext import ops\n"
              "def hwm(): return int(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1))/1024\n"
              "n,c,d,b=int(sys.argv[1]),int(sys.argv[2]),int(sys.argv[3]),sys.argv[4]\n"
              "q,k,v=torch.randn(1,n,c),torch.randn(1,n,c),torch.randn(1,n,d)\n"
              "ops.soft_match(q[:,:8],k[:,:600],v[:,:600],backend=b)\n"
              "open('/proc/self/clear_refs','w').write('5'); before=hwm()\n"
              "ops.soft_match(q,k,v,backend=b)\nprint(hwm()-before)\n")
    rows = []
    for n in sizes:
        row = {"points": n}
        for backend, key in (("ext", "streamed_mb"), ("torch", "dense_mb")):
            if backend == "torch" and n > 12_000:
                continue
            proc = subprocess.run([sys.executable, "-c", script, str(n), str(channels), str(values), backend],
                                  capture_output=True, text=True)
            row[key] = float(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else None
        rows.append(row)
    measured = [r for r in rows if r.get("dense_mb")]
    if measured:
        largest = measured[-1]
        for row in rows:
            if row.get("dense_mb") is None:
                row["dense_mb_extrapolated"] = largest["dense_mb"] * (row["points"] / largest["points"]) ** 2
    return rows


def markdown(records: list[dict], memory: list[dict], kitchen_heldout: bool) -> str:
    lines = ["| pair | method | budget | global estimate RE (deg) / TE (cm) | final RE (deg) | final TE (cm) | success | "
             "register (s) | process (s) | peak RSS (MB) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['pair']} | {r['method']} | {r['budget']} | failed: {r['error']} | | | | | | |")
            continue
        lines.append(f"| {r['pair']} | {r['method']} | {r['budget']} | {r['initial_rotation_error_deg']:.2f} / "
                     f"{100 * r['initial_translation_error_m']:.1f} | {r['rotation_error_deg']:.2f} | "
                     f"{100 * r['translation_error_m']:.1f} | {'yes' if r['success'] else 'no'} | "
                     f"{r['register_s']:.1f} | {r['process_s']:.1f} | {r['peak_rss_mb']:.0f} |")
    lines.append("")
    lines.append("vrnet on the kitchen pairs: " + ("scene models trained on the third fragment alone (held out)."
                                                  if kitchen_heldout else
                                                  "the shipped scene model, which was trained on these fragments "
                                                  "(self-supervised, one fragment at a time): not a held-out result."))
    lines += ["", "| soft matching N = M (c = 32, D = 35) | streamed ops.soft_match (MB) | dense matrix path (MB) |",
              "|---|---|---|"]
    for m in memory:
        dense = (f"{m['dense_mb']:.0f}" if m.get("dense_mb") is not None
                 else f"~{m['dense_mb_extrapolated']:.0f} (extrapolated)" if "dense_mb_extrapolated" in m else "-")
        lines.append(f"| {m['points']:,} | {m['streamed_mb']:.0f} | {dense} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="folder with 3dmatch_redkitchen/ and lidar_pair/")
    parser.add_argument("--heldout-dir", default=None, help="folder with only0.pt, only4.pt, only10.pt")
    parser.add_argument("--budgets", nargs="+", default=["2GB", "4GB"],
                        help="--max-memory budgets to run each pair under")
    parser.add_argument("--pairs", nargs="+", default=None, help="only pairs whose name contains one of these")
    parser.add_argument("--methods", nargs="+", default=["vrnet", "fpfh"], choices=["vrnet", "fpfh", "icp"],
                        help="`vrnet register --method` values to run")
    parser.add_argument("--synthetic-points", type=int, default=1_000_000, help="points of the synthetic large scene")
    parser.add_argument("--skip-synthetic", action="store_true", help="leave the synthetic large scene out")
    parser.add_argument("--memory-sizes", type=int, nargs="+", default=[2000, 4000, 8000, 12000, 50000],
                        help="cloud sizes of the peak-memory rows")
    parser.add_argument("--json", default="bench_large_scene.json", help="where the JSON goes")
    parser.add_argument("--markdown", default="bench_large_scene.md", help="where the Markdown goes")
    args = parser.parse_args(argv)
    data = Path(args.data)
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        todo = pairs(data, workdir, args.pairs)
        if not todo:
            raise SystemExit(f"bench_large_scene: no scan pairs under {data}")
        records = []
        for pair in todo:
            for method in args.methods:
                for budget in args.budgets:
                    checkpoint = None
                    if method == "vrnet" and pair["heldout_fragment"] is not None and args.heldout_dir:
                        checkpoint = str(Path(args.heldout_dir) / f"only{pair['heldout_fragment']}.pt")
                    record = run_register(pair, method, budget, checkpoint, workdir)
                    records.append(record)
                    print(json.dumps({k: v for k, v in record.items() if k not in ("warnings", "points")}), flush=True)
        if not args.skip_synthetic:
            pair = synthetic_pair(workdir, args.synthetic_points)
            for method in args.methods:
                record = run_register(pair, method, args.budgets[-1], None, workdir)
                records.append(record)
                print(json.dumps({k: v for k, v in record.items() if k not in ("warnings", "points")}), flush=True)
    memory = soft_match_memory(args.memory_sizes)
    print(json.dumps(memory))
    meta = {"machine": f"{platform.machine()}, {os.cpu_count()} cpus", "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d"), "threads": os.environ.get("OMP_NUM_THREADS", "default")}
    Path(args.json).write_text(json.dumps({"meta": meta, "runs": records, "soft_match_memory": memory}, indent=1))
    table = markdown(records, memory, bool(args.heldout_dir))
    Path(args.markdown).write_text(table + "\n")
    print(table)
    print(f"wrote {args.json} and {args.markdown}")


if __name__ == "__main__":
    main()
