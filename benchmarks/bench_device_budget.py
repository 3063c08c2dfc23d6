"""`register()` under memory budgets on a device: whether each run stays within its budget (the
peak measured) or is refused, with the point counts and where the whole scans were downsampled.

    python benchmarks/bench_device_budget.py [--device cuda] [--points 10000000] [--budgets 2GB 512MB 64MB]
                                             [--json budget.json] [--markdown budget.md]

The pair: two synthetic scans of one room (``data.procedural.room_scan``, seeds 1 and 2, the second
turned by 10 degrees and moved 0.2 m), ``--points`` each. Per budget, one run of the default method:
on a CUDA device the peak is torch's (``torch.cuda.max_memory_allocated``, reset before the run),
the budget then being the GPU's; on the CPU the process's peak resident memory since it started
(the budget being the host's: the first budget's run includes reading nothing but these arrays).
A run the planner refuses is recorded with its message; the errors against the known motion too.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder


def main(argv: list[str] | None = None) -> None:
    import torch

    from vrnet_ext.cli.common import DefaultsHelpFormatter, device_name, memory_size
    from vrnet_ext.data.procedural import room_scan
    from vrnet_ext.geometry.transforms import apply, to_homogeneous
    from vrnet_ext.registration import register
    from vrnet_ext.registration.budget import MB, MemoryBudgetError
    from vrnet_ext.registration.result import transform_errors
    from scipy.spatial.transform import Rotation

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", type=device_name, default="cpu", help="where register() runs: cpu, cuda or cuda:N")
    parser.add_argument("--points", type=int, default=10_000_000, help="points per synthetic scan")
    parser.add_argument("--budgets", nargs="+", type=memory_size, default=[2 << 30, 512 << 20, 64 << 20],
                        help="max_memory values, e.g. 2GB 512MB (each one run)")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    truth = to_homogeneous(Rotation.from_euler("z", 10, degrees=True).as_matrix(), [0.2, 0.0, 0.05])
    src, tgt = room_scan(args.points, 1), apply(truth, room_scan(args.points, 2))
    rows = []
    for budget in args.budgets:
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        begin = time.perf_counter()
        row = {"budget_mb": budget / MB}
        try:
            result = register(src, tgt, device=device, max_memory=budget)
            row.update(outcome="registered", warnings=result.warnings, points=result.points,
                       errors=transform_errors(result.T_target_source, truth))
        except MemoryBudgetError as error:
            row.update(outcome="refused", message=str(error))
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            row["peak_mb"] = torch.cuda.max_memory_allocated(device) / MB
        else:
            row["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        row["seconds"] = time.perf_counter() - begin
        row["within"] = row["peak_mb"] <= row["budget_mb"] if row["outcome"] == "registered" else None
        rows.append(row)
        print(f"{row['budget_mb']:.0f} MB: {row['outcome']}, peak {row['peak_mb']:.0f} MB", flush=True)
    machine = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_description()
    lines = [f"`register()` under `max_memory` on {device} ({machine}, torch {torch.__version__}, "
             f"{time.strftime('%Y-%m-%d')}): two synthetic room scans of {args.points:,} points; the peak is "
             + ("torch's allocation on the GPU." if device.type == "cuda" else "the process's resident memory."), "",
             "| budget MB | outcome | peak MB | within | seconds | RE deg / TE m | notes |",
             "|---:|---|---:|---|---:|---:|---|"]
    for row in rows:
        errors = row.get("errors")
        accuracy = f"{errors['rotation_error_deg']:.2f} / {errors['translation_error']:.3f}" if errors else "–"
        notes = "; ".join(row.get("warnings", [])) or row.get("message", "")
        lines.append(f"| {row['budget_mb']:.0f} | {row['outcome']} | {row['peak_mb']:.0f} | "
                     f"{ {True: 'yes', False: 'NO', None: '–'}[row['within']]} | {row['seconds']:.1f} | {accuracy} | "
                     f"{notes} |")
    write_outputs("\n".join(lines), {"device": str(device), "machine": machine, "date": time.strftime("%Y-%m-%d"),
                                     "points": args.points, "rows": rows}, args.markdown, args.json)


if __name__ == "__main__":
    main()
