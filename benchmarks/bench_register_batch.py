"""Many pairs: one `vrnet register` process per pair against `vrnet register-batch` in one process
and under `torchrun` with 2 processes (one thread each), on the same manifest, in one run.

    python benchmarks/bench_register_batch.py [--manifest ../shared/data/scenes/real_pairs/MANIFEST.tsv]
                                              [--max-pairs N] [--device cuda] [--processes 4]
                                              [--synthetic 48] [--no-singles]
                                              [--json batch.json] [--markdown batch.md]

Reports pairs per second (wall time of the whole command, process starts and imports included),
recall (RE < 15 deg, TE < 30 cm: `register-batch`'s defaults), and whether they give the same
transforms bit for bit (the default method and seed). ``--device cuda``: every command registers on
the GPU (under torchrun the processes share it, or take one each). ``--synthetic N``: N pairs of
synthetic room scans (``data.procedural.room_scan``, 300,000 points, each target turned by up to 30
degrees) written to a temporary folder, for a machine without the shared scans. ``--no-singles``:
without the one-process-per-pair run (minutes of process starts on a GPU); register-batch is then
the base of the speed-ups.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MANIFEST = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs" / "MANIFEST.tsv"
VRNET = [sys.executable, "-m", "vrnet_ext.cli"]


def _timed(command: list[str], env: dict | None = None) -> float:
    started = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, text=True, env=env)
    return time.perf_counter() - started


SYNTHETIC_POINTS = 300_000  # per scan of a --synthetic pair


def synthetic_manifest(work: Path, count: int) -> Path:
    """``count`` pairs of synthetic room scans with their ground truth, as a manifest in ``work``."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from vrnet_ext.data.procedural import room_scan
    from vrnet_ext.geometry.transforms import apply, to_homogeneous

    rng = np.random.default_rng(0)
    manifest = work / "synthetic.csv"
    with manifest.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["id", "source", "target", "gt"])
        for index in range(count):
            truth = to_homogeneous(Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(15)).as_matrix(),
                                   rng.uniform(-0.5, 0.5, 3))
            names = [work / f"room{index}_{role}.npy" for role in ("source", "target")]
            np.save(names[0], room_scan(SYNTHETIC_POINTS, 2 * index).astype(np.float32))
            np.save(names[1], apply(truth, room_scan(SYNTHETIC_POINTS, 2 * index + 1)).astype(np.float32))
            np.savetxt(work / f"room{index}_gt.txt", truth)
            writer.writerow([f"room{index}", *names, work / f"room{index}_gt.txt"])
    return manifest


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext.cli.common import DefaultsHelpFormatter, device_name
    from vrnet_ext.geometry.atomic import read_json_lines
    from vrnet_ext.registration.batch import read_manifest

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--manifest", default=str(DEFAULT_MANIFEST), help="pairs (register-batch's manifest)")
    parser.add_argument("--max-pairs", type=int, default=None, help="the first N pairs only")
    parser.add_argument("--device", type=device_name, default="cpu", help="where every command registers")
    parser.add_argument("--processes", type=int, default=2, help="torchrun processes (one thread each)")
    parser.add_argument("--synthetic", type=int, default=None, help="N synthetic pairs instead of --manifest")
    parser.add_argument("--no-singles", dest="singles", action="store_false",
                        help="leave out the one-process-per-pair run")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp())
    source = synthetic_manifest(work, args.synthetic) if args.synthetic else Path(args.manifest)
    tasks = read_manifest(source)[:args.max_pairs]
    manifest = work / "pairs.csv"
    with manifest.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["id", "source", "target", "gt"])
        writer.writerows([t.id, t.source, t.target, t.gt or ""] for t in tasks)
    device = ["--device", args.device]
    rows, same = {}, {}
    if args.singles:
        started = time.perf_counter()
        singles = []
        for task in tasks:
            out = work / f"single_{task.index}.json"
            subprocess.run([*VRNET, "register", str(task.source), str(task.target), "--json", str(out), *device],
                           check=True, capture_output=True, text=True)
            singles.append(json.loads(out.read_text())["T_target_source"])
        rows["one process per pair"] = time.perf_counter() - started
    rows["register-batch"] = _timed([*VRNET, "register-batch", str(manifest), "--out", str(work / "batch.jsonl"),
                                     "--no-progress", *device])
    env = dict(os.environ, OMP_NUM_THREADS="1")
    sharded_name = f"torchrun, {args.processes} processes x 1 thread"
    rows[sharded_name] = _timed(
        ["torchrun", "--nproc-per-node", str(args.processes), "-m", "vrnet_ext.cli", "register-batch", str(manifest),
         "--out", str(work / "sharded.jsonl"), "--no-progress", *device], env)
    batch, sharded = read_json_lines(work / "batch.jsonl"), read_json_lines(work / "sharded.jsonl")
    transforms = [r["T_target_source"] for r in batch]
    if args.singles:
        same["register-batch = one process per pair"] = transforms == singles
    same["torchrun = register-batch"] = [r["T_target_source"] for r in sharded] == transforms
    judged = [r for r in batch if "registered" in r]
    recall = sum(r["registered"] for r in judged) / max(1, len(judged))
    base = next(iter(rows.values()))
    lines = ["| how | seconds | pairs / s | speed-up |", "|---|---:|---:|---:|"]
    lines += [f"| {name} | {seconds:.1f} | {len(tasks) / seconds:.2f} | {base / seconds:.2f}x |"
              for name, seconds in rows.items()]
    where = cpu_description() if args.device == "cpu" else f"{args.device}, host {cpu_description()}"
    what = f"{len(tasks)} synthetic room pairs" if args.synthetic else f"{len(tasks)} pairs"
    lines.append(f"\n{what}, recall {recall:.1%} ({len(judged)} with ground truth); bit-identical "
                 f"transforms: " + ", ".join(f"{k}: {'yes' if v else 'NO'}" for k, v in same.items())
                 + f". {where}, {time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"pairs": len(tasks), "device": args.device, "synthetic": bool(args.synthetic),
                                     "seconds": rows, "recall": recall, "identical": same}, args.markdown, args.json)


if __name__ == "__main__":
    main()
