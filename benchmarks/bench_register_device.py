"""``vrnet_ext.register`` on a device from arrays in memory: time, stages, transform against the CPU's.

In one process: time per pair and by stage, the transform against the CPU's of the same run, peak
memory.

    python benchmarks/bench_register_device.py [--device cuda] [--methods default fpfh]
                                               [--repeats 5] [--json register_device.json]

Pairs: the kitchen pairs of ``../shared/data/scenes/3dmatch_redkitchen`` (bench_large_scene's) and
the LiDAR pair, read once. Per (pair, method): one warm-up run on the device, then ``--repeats``
timed runs (median; on a GPU a synchronisation before each clock read), and one run on the CPU
with the same seed, whose transform the device's is compared with (rotation in degrees, translation
in metres; 0 when ``--device cpu``). Errors against the ground truth too. Peak memory: on a GPU
torch's allocator peak over the timed runs; on the CPU the process's peak resident set.
"""
from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_large_scene import DEFAULT_DATA, pairs  # noqa: E402
from outputs import cpu_description, write_outputs  # noqa: E402

METHODS = {"default": None, "sc2": "sc2", "fpfh": "fpfh"}  # row name: register(method=...)


def timed(run, device) -> tuple[float, object]:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
    begin = time.perf_counter()
    result = run()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - begin, result


def main(argv: list[str] | None = None) -> None:
    import torch

    from vrnet_ext.cli.common import DefaultsHelpFormatter, device_name
    from vrnet_ext.geometry.io import read_points
    from vrnet_ext.registration import register
    from vrnet_ext.registration.result import transform_errors

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the shared scenes folder")
    parser.add_argument("--device", type=device_name, default="cpu", help="where register() runs: cpu, cuda or cuda:N")
    parser.add_argument("--methods", nargs="+", default=["default"], choices=list(METHODS), help="register() methods")
    parser.add_argument("--pairs", nargs="+", default=None, help="only pairs whose name contains one of these")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per pair and method (median)")
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    rows = []
    with tempfile.TemporaryDirectory() as workdir:
        for pair in pairs(Path(args.data), Path(workdir), args.pairs):
            src, tgt = read_points(pair["source"]), read_points(pair["target"])
            truth = np.loadtxt(pair["gt"])
            for name in args.methods:
                def run(on=device):
                    return register(src, tgt, method=METHODS[name], device=on)

                run()  # warm-up: lazy initialisation, caches
                if device.type == "cuda":
                    torch.cuda.reset_peak_memory_stats(device)
                seconds, results = [], []
                for _ in range(args.repeats):
                    elapsed, result = timed(run, device)
                    seconds.append(elapsed)
                    results.append(result)
                on_cpu = run(torch.device("cpu"))
                result = results[-1]
                against_cpu = transform_errors(result.T_target_source, on_cpu.T_target_source)
                rows.append({"pair": pair["name"], "method": name, "points": [len(src), len(tgt)],
                             "median_s": statistics.median(seconds), "seconds": seconds,
                             "stages_s": result.seconds, "repeatable": all(
                                 np.array_equal(r.T_target_source, result.T_target_source) for r in results),
                             "vs_cpu_rotation_deg": against_cpu["rotation_error_deg"],
                             "vs_cpu_translation": against_cpu["translation_error"],
                             "truth": transform_errors(result.T_target_source, truth),
                             "peak_gpu_mb": torch.cuda.max_memory_allocated(device) / 2 ** 20
                             if device.type == "cuda" else None})
                print(f"{pair['name']}, {name}: {rows[-1]['median_s'] * 1e3:.1f} ms", file=sys.stderr, flush=True)
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    machine = (torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_description())
    lines = [f"`register()` in one process on {args.device} ({machine}; host {cpu_description()}, torch "
             f"{torch.__version__}, {time.strftime('%Y-%m-%d')}), median of {args.repeats} runs after a warm-up; "
             f"the transform against the CPU's in the same run; process peak RSS {peak_rss_mb:.0f} MB.", "",
             "| pair | method | points | ms / pair | stages (ms) | vs CPU: deg / mm | RE deg / TE m | repeatable | "
             "peak GPU MB |", "|---|---|---:|---:|---|---:|---:|---|---:|"]
    for row in rows:
        stages = ", ".join(f"{stage} {value * 1e3:.0f}" for stage, value in row["stages_s"].items())
        peak = f"{row['peak_gpu_mb']:.0f}" if row["peak_gpu_mb"] is not None else "–"
        lines.append(f"| {row['pair']} | {row['method']} | {row['points'][0]:,} / {row['points'][1]:,} | "
                     f"{row['median_s'] * 1e3:.1f} | {stages} | {row['vs_cpu_rotation_deg']:.3f} / "
                     f"{row['vs_cpu_translation'] * 1e3:.2f} | {row['truth']['rotation_error_deg']:.2f} / "
                     f"{row['truth']['translation_error']:.3f} | {'yes' if row['repeatable'] else 'no'} | {peak} |")
    write_outputs("\n".join(lines), {"device": args.device, "machine": machine, "host": cpu_description(),
                                     "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"),
                                     "repeats": args.repeats, "peak_rss_mb": peak_rss_mb, "rows": rows},
                  args.markdown, args.json)


if __name__ == "__main__":
    main()
