"""How well the `--max-memory` planner predicts the peak it plans for.

    python benchmarks/bench_memory_plan.py [--data ../shared/data/scenes] [--pairs kitchen LiDAR room3M]
                                           [--methods auto sc2 fpfh fgr icp vrnet vrnet-large]
                                           [--json plan.json] [--markdown plan.md]

For every pair (the 3DMatch kitchen pair 4 -> 0 at full resolution, the LiDAR pair, and ``room3M``:
two synthetic 3,000,000-point scans of one room, ``data.procedural.room_scan``) and method, at
the default point counts, the planner's smallest counts and large ones (20,000 global, 200,000 ICP
points), one fresh process reads the scans,
asks :func:`vrnet_ext.registration.budget.plan_registration` what peak it predicts for exactly those counts
(what the process holds then included), runs :func:`vrnet_ext.registration.register` with them and
reports its peak resident memory (``ru_maxrss``, the whole process). The ratio predicted / measured
should lie in [1, 1.1]: below 1 a budget could be exceeded, above 1.1 a budget 10 % above what the
run needs would be refused or shrink the run. ``vrnet-large``: a scene model of the largest size a file may ask for (random
weights), at the smallest counts.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from outputs import cpu_description  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "scenes"
METHODS = ("auto", "sc2", "fpfh", "fgr", "icp", "vrnet", "vrnet-large")
LARGE_SCENE_MODEL = dict(hidden=1024, emb_dims=1024, neighbours=64, walk_hidden=1024)  # the limits' largest

CHILD = r"""
import json, resource, sys
import torch
torch.set_num_threads(2)
from vrnet_ext.geometry.io import read_points
from vrnet_ext.registration.budget import plan_registration, resident_mb, transient_mb
from vrnet_ext.registration import IcpSettings, PointCounts, register
from vrnet_ext.registration.global_estimators import make_global_estimator
from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, load_pretrained
from vrnet_ext.model.scene import SceneConfig, SceneVRNet

source, target, method, global_points, icp_points, large = sys.argv[1:7]
global_points, icp_points = int(global_points), int(icp_points)
src, tgt = read_points(source), read_points(target)
model = load_pretrained(DEFAULT_SCENE_MODEL) if method == "vrnet" else None
if method == "vrnet-large":  # random weights: the memory, not the result, is measured
    method, model = "vrnet", SceneVRNet(SceneConfig(**json.loads(large))).eval()
estimator = make_global_estimator(method, model)
counts = PointCounts(global_points=global_points, icp_points=icp_points)
held = resident_mb()
plan = plan_registration(1 << 50, estimator, len(src), len(tgt), counts)
transient = transient_mb(estimator, max(len(src), len(tgt)), counts)
outcome = "registered"
try:
    register(src, tgt, method=method, model=model, global_points=global_points,
             icp_settings=IcpSettings(points=icp_points))
except ValueError as error:  # random weights find no consensus; their forward pass has run by then
    outcome = str(error)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(json.dumps({"predicted_mb": plan.predicted_peak_mb, "peak_mb": peak, "held_mb": held, "transient_mb": transient,
                  "outcome": outcome}))
"""


SYNTHETIC_POINTS = 3_000_000  # per scan of the room3M pair
MAKE_ROOM = r"""
import sys
from pathlib import Path
import numpy as np
from vrnet_ext.data.procedural import room_scan
work, points = Path(sys.argv[1]), int(sys.argv[2])
for seed, role in ((1, "source"), (2, "target")):
    np.save(work / f"room3M_{role}.npy", room_scan(points, seed).astype(np.float32))
"""


def pairs(data: Path, names: list[str], work: Path) -> list[dict]:
    """The pairs asked for by name; room3M's scans are made (and written to ``work``) only when asked."""
    kitchen = data / "3dmatch_redkitchen"
    chosen = [{"name": "kitchen", "source": kitchen / "cloud_bin_4.ply", "target": kitchen / "cloud_bin_0.ply"},
              {"name": "LiDAR", "source": data / "lidar_pair" / "source.ply", "target": data / "lidar_pair" / "target.ply"}]
    if "room3M" in names:  # made in a child: a child's peak RSS counts the parent's memory at the fork
        subprocess.run([sys.executable, "-c", MAKE_ROOM, str(work), str(SYNTHETIC_POINTS)], check=True)
        chosen.append({"name": "room3M", "source": work / "room3M_source.npy", "target": work / "room3M_target.npy"})
    return [pair for pair in chosen if pair["name"] in names]


def measure(pair: dict, method: str, global_points: int, icp_points: int) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(pair["source"]), str(pair["target"]), method,
                           str(global_points), str(icp_points), json.dumps(LARGE_SCENE_MODEL)],
                          capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["ratio"] = result["predicted_mb"] / result["peak_mb"]
    return result


def markdown(rows: list[dict], meta: dict) -> str:
    lines = [f"Measured {meta['date']} on {meta['machine']}, torch {meta['torch']}. Held: what the process holds when "
             f"it plans (Python, torch, the scans); growth: measured peak - held; transient: the planner's largest "
             f"stage. `auto` is planned for its first member (sc2): the others run only "
             f"when sc2 is doubtful, and under a budget only where they fit what is left.", "",
             "| pair | method | counts | held MB | growth MB | transient MB | predicted MB | measured peak MB "
             "| predicted / measured |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['pair']} | {r['method']} | {r['counts']} | – | – | – | – | – | error: {r['error']} |")
        else:
            lines.append(f"| {r['pair']} | {r['method']} | {r['counts']} | {r['held_mb']:.0f} | "
                         f"{r['peak_mb'] - r['held_mb']:.0f} | {r['transient_mb']:.0f} | {r['predicted_mb']:.0f} | "
                         f"{r['peak_mb']:.0f} | {r['ratio']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    import datetime

    import torch

    from vrnet_ext.registration.budget import MIN_GLOBAL_POINTS, MIN_ICP_POINTS
    from vrnet_ext.registration import IcpSettings

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared scenes folder")
    parser.add_argument("--pairs", nargs="+", choices=("kitchen", "LiDAR", "room3M"),
                        default=["kitchen", "LiDAR", "room3M"],
                        help="kitchen: 3DMatch fragments 4 -> 0; LiDAR: the LiDAR pair; room3M: two synthetic "
                             "3,000,000-point room scans")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                        help="global estimates to plan and run (default: all)")
    parser.add_argument("--json", type=Path, default=Path("memory_plan.json"),
                        help="where the JSON goes (default: memory_plan.json)")
    parser.add_argument("--markdown", type=Path, default=Path("memory_plan.md"),
                        help="where the Markdown goes (default: memory_plan.md)")
    args = parser.parse_args(argv)
    counts = {"default": (5000, IcpSettings().points), "smallest": (MIN_GLOBAL_POINTS, MIN_ICP_POINTS),
              "large": (20000, 200_000)}
    rows = []
    work = Path(tempfile.mkdtemp())
    for pair in pairs(args.data, args.pairs, work):
        for method in args.methods:
            for label, (global_points, icp_points) in counts.items():
                if method == "vrnet-large" and label != "smallest":
                    continue  # ~60x the shipped model's memory per point: the smallest counts say enough
                row = {"pair": pair["name"], "method": method, "counts": label, "global_points": global_points,
                       "icp_points": icp_points, **measure(pair, method, global_points, icp_points)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    meta = {"date": datetime.date.today().isoformat(), "machine": cpu_description(), "torch": torch.__version__}
    args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    args.markdown.write_text(markdown(rows, meta))
    print(f"wrote {args.json} and {args.markdown}")


if __name__ == "__main__":
    main()
