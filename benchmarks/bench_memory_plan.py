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
reports its peak resident memory (the whole process) and each stage's (on Linux: the kernel's peak
is reset as a stage starts). The ratio predicted / measured should lie in [1, 1.1]: below 1 a budget
could be exceeded, above 1.1 a budget 10 % above what the run needs would be refused or shrink the
run. ``vrnet-large``: a scene model of the largest size a file may ask for (random
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
import functools, json, os, re, resource, sys
import torch
torch.set_num_threads(2)
from vrnet_ext.geometry.io import read_points
import vrnet_ext.registration.pipeline as pipeline
from vrnet_ext.registration.budget import (plan_registration, resident_mb, return_freed_memory, stage_peaks_mb,
                                           transient_mb)
from vrnet_ext.registration import IcpSettings, PointCounts, register
from vrnet_ext.registration.global_estimators import make_global_estimator
from vrnet_ext.model.pretrained import DEFAULT_SCENE_MODEL, load_pretrained
from vrnet_ext.model.scene import SceneConfig, SceneVRNet

# register's stages (the planner's, budget.STAGES, and the default's check), each measured on its own:
# the kernel's peak (VmHWM) is reset as a stage starts and read as it ends; the peaks between stages are kept
STAGES = {"_global_starts": "global", "_icp_problem": "preparation", "_refine": "iterations",
          "_cross_check": "check", "_fallback_starts": "check"}
BY_STAGE = os.access("/proc/self/clear_refs", os.W_OK)  # Linux; elsewhere only the whole run's peak
peaks, stages, depth = [], {}, [0]


def status(field):
    return int(re.search(field + r":\s+(\d+)", open("/proc/self/status").read()).group(1)) / 1024.0


def staged(function, stage):
    @functools.wraps(function)
    def run(*args, **kwargs):
        if depth[0]:
            return function(*args, **kwargs)
        depth[0] += 1
        peaks.append(status("VmHWM"))  # the peak since the last reset
        open("/proc/self/clear_refs", "w").write("5")
        try:
            return function(*args, **kwargs)
        finally:
            depth[0] -= 1
            stages[stage] = max(stages.get(stage, 0.0), status("VmHWM") - held)
    return run


source, target, method, global_points, icp_points, large = sys.argv[1:7]
return_freed_memory()  # as `vrnet register --max-memory` does before it reads the scans
global_points, icp_points = int(global_points), int(icp_points)
src, tgt = read_points(source), read_points(target)
model = load_pretrained(DEFAULT_SCENE_MODEL) if method == "vrnet" else None
if method == "vrnet-large":  # random weights: the memory, not the result, is measured
    method, model = "vrnet", SceneVRNet(SceneConfig(**json.loads(large))).eval()
estimator = make_global_estimator(method, model)
counts = PointCounts(global_points=global_points, icp_points=icp_points)
held = resident_mb()
plan = plan_registration(1 << 50, estimator, len(src), len(tgt), counts)
scans = (len(src), len(tgt))
transient, predicted_stages = transient_mb(estimator, scans, counts), stage_peaks_mb(estimator, scans, counts)
if BY_STAGE:
    for name, stage in STAGES.items():
        setattr(pipeline, name, staged(getattr(pipeline, name), stage))
outcome = "registered"
try:
    register(src, tgt, method=method, model=model, global_points=global_points,  # a budget that fits: its
             icp_settings=IcpSettings(points=icp_points), max_memory=1 << 50)    # allocator setting, these counts
except ValueError as error:  # random weights find no consensus; their forward pass has run by then
    outcome = str(error)
peak = max(peaks + [status("VmHWM")]) if BY_STAGE else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(json.dumps({"predicted_mb": plan.predicted_peak_mb, "peak_mb": peak, "held_mb": held, "transient_mb": transient,
                  "scan_points": scans, "predicted_stages_mb": predicted_stages, "measured_stages_mb": stages, "outcome": outcome}))
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


def planned(row: dict) -> bool:
    """Whether the planner's prediction is the run's bound: not ``auto`` (its other members are planned
    one by one against what is left of a budget)."""
    return row["method"] != "auto"


def summary(rows: list[dict]) -> dict:
    """The ratio's range over the planned rows, and over those at the smallest counts (a budget is
    refused only when the smallest run's prediction exceeds it)."""
    def span(ratios: list[float]) -> list[float] | None:
        return [min(ratios), max(ratios)] if ratios else None

    measured = [r for r in rows if "ratio" in r and planned(r)]
    return {"planned_rows": len(measured), "ratio": span([r["ratio"] for r in measured]),
            "smallest_ratio": span([r["ratio"] for r in measured if r["counts"] == "smallest"])}


def _stages(r: dict) -> str:
    measured = r.get("measured_stages_mb", {})
    return " · ".join(f"{r['predicted_stages_mb'][stage]:.0f}/{measured[stage]:.0f}" if stage in measured
                      else f"{r['predicted_stages_mb'][stage]:.0f}/–" for stage in r["predicted_stages_mb"])


def markdown(rows: list[dict], meta: dict) -> str:
    s = summary(rows)
    lines = [f"Measured {meta['date']} on {meta['machine']}, torch {meta['torch']}. Held: what the process holds when "
             f"it plans (Python, torch, the scans); growth: measured peak - held; transient: the planner's largest "
             f"stage; stages: predicted / measured growth of the global estimate, ICP's preparation and ICP's "
             f"iterations (each stage's peak above held). Every run under a budget (freed memory goes back to the "
             f"system). `auto` is planned for its first member (sc2): the others run only when sc2 is doubtful, and "
             f"under a budget only where they fit what is left.", "",
             f"Predicted / measured over the {s['planned_rows']} planned rows (not `auto`, marked *): {s['ratio'][0]:.3f}-{s['ratio'][1]:.3f}; at the smallest counts, "
             f"which decide a refusal: {s['smallest_ratio'][0]:.3f}-{s['smallest_ratio'][1]:.3f}." if s["ratio"] else
             "No planned row was measured.", "",
             "| pair | method | counts | held MB | growth MB | transient MB | stages MB | predicted MB | "
             "measured peak MB | predicted / measured |",
             "|---|---|---|---:|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['pair']} | {r['method']} | {r['counts']} | – | – | – | – | – | – | error: {r['error']} |")
        else:
            mark = "" if planned(r) else " *"
            lines.append(f"| {r['pair']} | {r['method']}{mark} | {r['counts']} | {r['held_mb']:.0f} | "
                         f"{r['peak_mb'] - r['held_mb']:.0f} | {r['transient_mb']:.0f} | {_stages(r)} | "
                         f"{r['predicted_mb']:.0f} | {r['peak_mb']:.0f} | {r['ratio']:.2f} |")
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
    args.json.write_text(json.dumps({"meta": meta, "summary": summary(rows), "rows": rows}, indent=1))
    args.markdown.write_text(markdown(rows, meta))
    print(f"wrote {args.json} and {args.markdown}")


if __name__ == "__main__":
    main()
