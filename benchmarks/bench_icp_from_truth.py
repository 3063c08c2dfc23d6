"""Where ICP goes when it starts from the official ground truth: on real scans the geometry's own
optimum and the published ground truth differ, and no registration can score better against that
ground truth than this floor.

    python benchmarks/bench_icp_from_truth.py [--data ../shared/data/scenes/3dmatch_redkitchen]
                                              [--json icp_from_truth.json] [--markdown icp_from_truth.md]

For each kitchen pair (official 3DMatch gt.log), each ICP step and two voxel sizes (about 50,000 and
200,000 points per scan), ICP runs from the ground truth (reach 3 voxels, steps below 1e-6, at most
100 iterations); the table gives how far it moves from it, beside `register()`'s errors (defaults).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.geometry.io import read_ground_truth, read_points
from vrnet_ext.geometry.preprocessing import voxel_downsample, voxel_size_for
from vrnet_ext.names import ICP_STEPS
from vrnet_ext.registration import IcpProblem, IcpSettings, register, transform_errors
from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "scenes" / "3dmatch_redkitchen"
PAIRS = ((0, 4), (4, 10), (0, 10))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="folder of cloud_bin_*.ply and gt_3DMatch_*.log")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    data = Path(args.data)
    log = next(data.glob("gt_3DMatch_*.log"))
    rows = []
    for source, target in PAIRS:
        src, tgt = read_points(data / f"cloud_bin_{source}.ply"), read_points(data / f"cloud_bin_{target}.ply")
        truth = read_ground_truth(log, fragments=(source, target))
        registered = transform_errors(register(src, tgt).T_target_source, truth)
        for points in (50_000, 200_000):
            voxel = voxel_size_for(tgt, points)
            for step in ICP_STEPS:
                settings = IcpSettings(step=step, max_distance=3 * voxel, transform_tolerance=1e-6,
                                       max_iterations=100)
                problem = IcpProblem(voxel_downsample(src, voxel), voxel_downsample(tgt, voxel), settings)
                moved = transform_errors(problem.run(truth).T_target_source, truth)
                rows.append({"pair": f"{source}->{target}", "points": points, "step": step,
                             "moved_deg": moved["rotation_error_deg"], "moved_cm": 100 * moved["translation_error"],
                             "register_deg": registered["rotation_error_deg"],
                             "register_cm": 100 * registered["translation_error"]})
    lines = ["| pair | points | ICP step | ICP from the truth moves (deg / cm) | register() error (deg / cm) |",
             "|---|---:|---|---:|---:|"]
    lines += [f"| {r['pair']} | {r['points']} | {r['step']} | {r['moved_deg']:.2f} / {r['moved_cm']:.1f} | "
              f"{r['register_deg']:.2f} / {r['register_cm']:.1f} |" for r in rows]
    lines.append(f"\n{cpu_description()}, {time.strftime('%Y-%m-%d')}.")
    write_outputs("\n".join(lines), {"rows": rows}, args.markdown, args.json)


if __name__ == "__main__":
    main()
