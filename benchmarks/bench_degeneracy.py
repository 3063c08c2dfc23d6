"""How well real scans constrain ICP, against shapes that do not: the smallest eigenvalue share of
the point-to-plane information matrix (:mod:`vrnet_ext.registration.degeneracy`) at the ground
truth of every real pair, and of a plane and a straight corridor. It shows where the warning
threshold ``DEGENERATE`` sits between the two.

    python benchmarks/bench_degeneracy.py [--real-pairs ../shared/data/scenes/real_pairs]
                                          [--json degeneracy.json] [--markdown degeneracy.md]

Per pair: both scans voxel-downsampled to about 50,000 points (``register``'s ICP default), the
source moved by the ground truth, pairs within 3 voxels, target normals from 20 neighbours.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from vrnet_ext import ops
from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.data.real_pairs import read_manifest
from vrnet_ext.geometry.io import read_points, read_transform
from vrnet_ext.geometry.preprocessing import voxel_downsample, voxel_size_for
from vrnet_ext.geometry.transforms import apply
from vrnet_ext.registration.degeneracy import DEGENERATE, constraint_spectrum
from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_PAIRS = ROOT.parent / "shared" / "data" / "scenes" / "real_pairs"


def smallest_share(src: np.ndarray, tgt: np.ndarray, truth: np.ndarray, points: int = 50_000) -> float:
    """The smallest eigenvalue share at ``truth`` (4, 4) of src (N, 3) onto tgt (M, 3)."""
    voxel = voxel_size_for(tgt, points)
    moved = torch.as_tensor(apply(truth, voxel_downsample(src, voxel)))
    target = torch.as_tensor(voxel_downsample(tgt, voxel))
    dist2, idx = ops.knn(moved[None], target[None], 1)
    close = dist2[0, :, 0] <= (3 * voxel) ** 2
    normals = ops.normals(target, 20)
    values, _ = constraint_spectrum(moved[close], normals[idx[0, close, 0]])
    return float(values[0])


def synthetic() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (20_000, 2)), 0.001 * rng.normal(size=20_000)]
    walls = [np.c_[rng.uniform(-5, 5, 8000), np.full(8000, side), rng.uniform(0, 2, 8000)] for side in (-1.0, 1.0)]
    floor = np.c_[rng.uniform(-5, 5, 8000), rng.uniform(-1, 1, 8000), np.zeros(8000)]
    return {"plane": plane, "corridor": np.concatenate([*walls, floor])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--real-pairs", default=str(DEFAULT_PAIRS), help="a real_pairs folder (MANIFEST.tsv, ...)")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    rows = []
    for pair in read_manifest(args.real_pairs):
        share = smallest_share(read_points(pair.source), read_points(pair.target), read_transform(pair.gt))
        rows.append({"case": pair.pair_id, "kind": pair.subset, "smallest_share": share})
    for name, cloud in synthetic().items():
        rows.append({"case": name, "kind": "synthetic", "smallest_share": smallest_share(cloud, cloud, np.eye(4))})
    lines = ["| kind | cases | smallest share: min | median | flagged (< DEGENERATE) |", "|---|---:|---:|---:|---:|"]
    for kind in dict.fromkeys(r["kind"] for r in rows):
        shares = [r["smallest_share"] for r in rows if r["kind"] == kind]
        lines.append(f"| {kind} | {len(shares)} | {min(shares):.2e} | {np.median(shares):.2e} | "
                     f"{sum(s < DEGENERATE for s in shares)} |")
    lines.append(f"\nDEGENERATE = {DEGENERATE:g}. {cpu_description()}, torch {torch.__version__}, "
                 f"{time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"threshold": DEGENERATE, "rows": rows}, args.markdown, args.json)


if __name__ == "__main__":
    main()
