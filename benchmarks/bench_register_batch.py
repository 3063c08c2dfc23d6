"""Many pairs: one `vrnet register` process per pair against `vrnet register-batch` in one process
and under `torchrun` with 2 processes (one thread each), on the same manifest, in one run.

    python benchmarks/bench_register_batch.py [--manifest ../shared/data/scenes/real_pairs/MANIFEST.tsv]
                                              [--max-pairs N] [--json batch.json] [--markdown batch.md]

Reports pairs per second (wall time of the whole command, process starts and imports included),
recall (RE < 15 deg, TE < 30 cm: `register-batch`'s defaults), and whether the three give the same
transforms bit for bit (the default method and seed).
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


def main(argv: list[str] | None = None) -> None:
    from vrnet_ext.cli.common import DefaultsHelpFormatter
    from vrnet_ext.geometry.atomic import read_json_lines
    from vrnet_ext.registration.batch import read_manifest

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--manifest", default=str(DEFAULT_MANIFEST), help="pairs (register-batch's manifest)")
    parser.add_argument("--max-pairs", type=int, default=None, help="the first N pairs only")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp())
    tasks = read_manifest(args.manifest)[:args.max_pairs]
    manifest = work / "pairs.csv"
    with manifest.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["id", "source", "target", "gt"])
        writer.writerows([t.id, t.source, t.target, t.gt or ""] for t in tasks)
    started = time.perf_counter()
    singles = []
    for task in tasks:
        out = work / f"single_{task.index}.json"
        subprocess.run([*VRNET, "register", str(task.source), str(task.target), "--json", str(out)], check=True,
                       capture_output=True, text=True)
        singles.append(json.loads(out.read_text())["T_target_source"])
    rows = {"one process per pair": time.perf_counter() - started}
    rows["register-batch"] = _timed([*VRNET, "register-batch", str(manifest), "--out", str(work / "batch.jsonl"),
                                     "--no-progress"])
    env = dict(os.environ, OMP_NUM_THREADS="1")
    rows["torchrun, 2 processes x 1 thread"] = _timed(
        ["torchrun", "--nproc-per-node", "2", "-m", "vrnet_ext.cli", "register-batch", str(manifest), "--out",
         str(work / "sharded.jsonl"), "--no-progress"], env)
    batch, sharded = read_json_lines(work / "batch.jsonl"), read_json_lines(work / "sharded.jsonl")
    transforms = [r["T_target_source"] for r in batch]
    same = {"register-batch = one process per pair": transforms == singles,
            "torchrun = register-batch": [r["T_target_source"] for r in sharded] == transforms}
    judged = [r for r in batch if "registered" in r]
    recall = sum(r["registered"] for r in judged) / max(1, len(judged))
    base = rows["one process per pair"]
    lines = ["| how | seconds | pairs / s | speed-up |", "|---|---:|---:|---:|"]
    lines += [f"| {name} | {seconds:.1f} | {len(tasks) / seconds:.2f} | {base / seconds:.2f}x |"
              for name, seconds in rows.items()]
    lines.append(f"\n{len(tasks)} pairs, recall {recall:.1%} ({len(judged)} with ground truth); bit-identical "
                 f"transforms: " + ", ".join(f"{k}: {'yes' if v else 'NO'}" for k, v in same.items())
                 + f". {cpu_description()}, {time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"pairs": len(tasks), "seconds": rows, "recall": recall, "identical": same},
                  args.markdown, args.json)


if __name__ == "__main__":
    main()
