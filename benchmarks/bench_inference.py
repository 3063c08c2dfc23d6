"""ModelNet40 inference speed of a shipped VRNet: pairs per second at several batch sizes, the
compiled backend beside the pure-PyTorch reference backend, each with the Transformer in float32
and in bfloat16 (``VRNetConfig.transformer_precision``; the default "auto" takes bf16 on a CPU with
native bf16), in one run, with the accuracy of each on the same pairs.

    python benchmarks/bench_inference.py [--model vrnet-pv-upc-rcp] [--batches 1 16 64]
                                         [--pairs 256] [--threads 2] [--device cpu] [--json inference.json]

Pairs: the first ``--pairs`` of the official test split (PV, UPC, 768-point views), the same for
every variant; no_grad, eval mode. Each (variant, batch) is timed over whole passes through those
pairs (median of ``--repeats``), variants taking turns within each repeat. Accuracy: the RMS of
the rotation angle error (degrees; not the paper's Euler-angle RMSE(R)) and RMSE(t) over the pairs,
so a faster variant can be seen to keep the numbers. "x reference": against the reference backend
with everything in float32 (the plain-PyTorch model); "x same precision": against the reference
backend with the same Transformer precision, where that variant was timed too ("–" where not).
On a GPU, ``ext, CUDA graphs`` replays the compiled backend's forward as CUDA graphs
(:class:`vrnet_ext.model.cuda_graphs.CudaGraphForward`, one captured per batch size before the
timing; every pair then takes the model's second look, chosen on the device), and ``ext, TF32
matmuls`` runs the compiled backend with TF32 allowed in float32 CUDA matmuls
(``torch.backends.cuda.matmul.fp32_precision = "tf32"``; what it costs the errors, simulated on a CPU:
``reduced_precision.py``).
Peak memory: the process's peak resident set after the run (all variants); on a GPU
(``--device cuda``, clock reads after a device synchronisation) also the peak of torch's CUDA
allocator.

Arithmetic: the floating-point operations per pair as the reference backend computes them in
float32 (matrix products, convolutions and attention, 2 per multiply-add; torch's
``FlopCounterMode``; the mean over the pairs, since a pair whose RCPs disagree with its first
estimate takes a second pass where the model's ``second_pass_below`` says so), and this
machine's float32 matrix-product rate in the same run (a 2048^3 product on ``--threads`` threads). Their ratio bounds the pairs per second of any float32 run that
does the reference's products; the "GFLOP/s" column is pairs/s times the reference's count.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import resource
import statistics
import sys
import time
from collections.abc import Iterator

import torch
from torch.utils.flop_counter import FlopCounterMode, sdpa_flop_count

from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter, device_name
from vrnet_ext.data.modelnet import ModelNet40Pairs
from vrnet_ext.geometry.metrics import rotation_error_deg
from vrnet_ext.model.pretrained import load_pretrained
from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder

# name: (backend, transformer_precision, replayed as CUDA graphs, TF32 allowed in float32 CUDA matmuls)
VARIANTS = {"torch": ("torch", "fp32", False, False), "torch, bf16 Transformer": ("torch", "bf16", False, False),
            "ext": ("ext", "fp32", False, False), "ext, bf16 Transformer": ("ext", "bf16", False, False),
            "ext, CUDA graphs": ("ext", "fp32", True, False), "ext, TF32 matmuls": ("ext", "fp32", False, True)}
GPU_ONLY = {name for name, settings in VARIANTS.items() if settings[2] or settings[3]}
SAME_PRECISION_REFERENCE = {"fp32": "torch", "bf16": "torch, bf16 Transformer"}


def load_pairs(count: int, data_dir: str | None, device: torch.device) -> dict[str, torch.Tensor]:
    dataset = ModelNet40Pairs(data_dir, partition="test", setting="PV", max_items=count)
    items = [dataset[i] for i in range(len(dataset))]
    return {key: torch.stack([item[key] for item in items]).to(device)
            for key in ("src", "tgt", "rotation", "translation")}


def synchronize(device: torch.device) -> None:
    """Waits for the device's queued work (a no-op on the CPU), so that a clock read after it counts it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@contextlib.contextmanager
def cuda_matmul_precision(tf32: bool) -> Iterator[None]:
    """TF32 allowed (or not) in float32 CUDA matmuls for the block, torch's setting restored after."""
    matmul = torch.backends.cuda.matmul
    previous = matmul.fp32_precision
    matmul.fp32_precision = "tf32" if tf32 else "ieee"
    try:
        yield
    finally:
        matmul.fp32_precision = previous


def run_pass(model, pairs: dict[str, torch.Tensor], batch: int, backend: str, transformer_precision: str,
             graphs: bool, tf32: bool, graphed: dict):
    """One pass over the pairs -> their rotations and translations. ``graphs``: through a
    :class:`CudaGraphForward` kept in ``graphed`` per (backend, precision): captured in the first
    pass at each batch size, replayed after. ``tf32``: TF32 allowed in float32 CUDA matmuls."""
    with cuda_matmul_precision(tf32):
        return _pass(model, pairs, batch, backend, transformer_precision, graphs, graphed)


def _pass(model, pairs: dict[str, torch.Tensor], batch: int, backend: str, transformer_precision: str,
          graphs: bool, graphed: dict):
    model.config.transformer_precision = transformer_precision
    forward = functools.partial(model, backend=backend)
    if graphs:
        from vrnet_ext.model.cuda_graphs import CudaGraphForward

        if (backend, transformer_precision) not in graphed:
            graphed[backend, transformer_precision] = CudaGraphForward(model, backend)
        forward = graphed[backend, transformer_precision]
    rotations, translations = [], []
    with torch.no_grad():
        for start in range(0, len(pairs["src"]), batch):
            out = forward(pairs["src"][start:start + batch], pairs["tgt"][start:start + batch])
            rotations.append(out.rotation.float())
            translations.append(out.translation.float())
    synchronize(pairs["src"].device)
    return torch.cat(rotations), torch.cat(translations)


def reference_flops_per_pair(model, pairs: dict[str, torch.Tensor], batch: int = 16) -> float:
    """Floating-point operations per pair on the reference backend in float32, the mean over
    ``pairs`` (the pairs whose RCPs disagree with their first estimate take a second pass)."""
    model.config.transformer_precision = "fp32"

    def attention(query, key, value, *args, out_shape=None, **kwargs) -> int:  # torch counts no CPU flash attention
        return sdpa_flop_count(query, key, value)

    counter = FlopCounterMode(display=False, custom_mapping={
        torch.ops.aten._scaled_dot_product_flash_attention_for_cpu: attention})
    count = len(pairs["src"])
    with torch.no_grad(), counter:
        for start in range(0, count, batch):
            model(pairs["src"][start:start + batch], pairs["tgt"][start:start + batch], backend="torch")
    return float(counter.get_total_flops()) / count


def matmul_rate(device: torch.device, seconds: float = 1.0, size: int = 2048) -> float:
    """The float32 matrix-product rate (FLOP/s) of ``device`` (on a CPU: on the current threads)."""
    a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
    a @ b
    synchronize(device)
    start, products = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        a @ b
        synchronize(device)
        products += 1
    return 2.0 * size ** 3 * products / (time.perf_counter() - start)


def device_description(device: torch.device) -> str:
    """The machine a result was measured on: the CPU, and the GPU where it ran on one."""
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)}, host {cpu_description()}"
    return cpu_description()


def _ratio(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--model", default="vrnet-pv-upc-rcp", help="shipped name or checkpoint")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64], help="pairs per forward, each timed")
    parser.add_argument("--pairs", type=int, default=256, help="test pairs per pass (a multiple of every batch size)")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes per variant and batch size, in turns")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--device", type=device_name, default="cpu", help="where the model runs: cpu, cuda or cuda:N")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--json", default=None, help="write the record to this JSON file (none: print only)")
    parser.add_argument("--markdown", default=None, help="write the table to this Markdown file (none: print only)")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=None,
                        help="variants to time, beside the reference (torch); default: all (CUDA graphs and "
                             "TF32 on a GPU only)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    asked = args.variants or [name for name in VARIANTS if device.type == "cuda" or name not in GPU_ONLY]
    if device.type != "cuda" and GPU_ONLY & set(asked):
        parser.error(f"--variants {', '.join(sorted(GPU_ONLY & set(asked)))}: need --device cuda (CUDA graphs, TF32)")
    needed = set(asked) | {"torch"}
    variants = {name: settings for name, settings in VARIANTS.items() if name in needed}
    graphed: dict = {}
    torch.set_num_threads(args.threads)
    model = load_pretrained(args.model).eval().to(device)
    pairs = load_pairs(args.pairs, args.data_dir, device)
    count = len(pairs["src"])
    flops_per_pair = reference_flops_per_pair(model, pairs)
    gemm_rate = matmul_rate(device)
    seconds: dict[tuple[str, int], list[float]] = {}
    accuracy: dict[str, dict[str, float]] = {}
    for variant, settings in variants.items():  # warm-up (graphs: captured at every batch size) and accuracy
        for batch in args.batches if settings[2] else ():
            run_pass(model, pairs, batch, *settings, graphed)
        R, t = run_pass(model, pairs, max(args.batches), *settings, graphed)
        accuracy[variant] = {
            "rms_angle_deg": float(rotation_error_deg(R, pairs["rotation"]).square().mean().sqrt()),
            "rmse_t": float((t - pairs["translation"]).norm(dim=-1).square().mean().sqrt())}
    for _ in range(args.repeats):
        for batch in args.batches:
            for variant, settings in variants.items():
                start = time.perf_counter()
                run_pass(model, pairs, batch, *settings, graphed)
                seconds.setdefault((variant, batch), []).append(time.perf_counter() - start)
                print(f"batch {batch:>3}, {variant}: {count / seconds[(variant, batch)][-1]:.1f} pairs/s",
                      file=sys.stderr, flush=True)
    rows = []
    for (variant, batch), times in seconds.items():
        median = statistics.median(times)
        reference = statistics.median(seconds[("torch", batch)])
        same_precision = seconds.get((SAME_PRECISION_REFERENCE[VARIANTS[variant][1]], batch))
        vs_same_precision = statistics.median(same_precision) / median if same_precision else None
        rows.append({"variant": variant, "batch": batch, "pairs_per_s": count / median,
                     "vs_reference": reference / median, "vs_same_precision": vs_same_precision,
                     "gflop_per_s": flops_per_pair * count / median / 1e9, **accuracy[variant]})
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    peak_gpu_mb = torch.cuda.max_memory_allocated(device) / 2 ** 20 if device.type == "cuda" else None
    meta = {"model": args.model, "pairs": count, "threads": args.threads, "repeats": args.repeats,
            "torch": torch.__version__, "device": str(device), "machine": device_description(device),
            "date": time.strftime("%Y-%m-%d"), "peak_rss_mb": peak_mb, "peak_gpu_mb": peak_gpu_mb,
            "reference_gflop_per_pair": flops_per_pair / 1e9, "fp32_matmul_gflop_per_s": gemm_rate / 1e9,
            "fp32_bound_pairs_per_s": gemm_rate / flops_per_pair}
    lines = ["| variant | batch | pairs/s | x reference | x same precision | GFLOP/s | RMS angle error (deg) | RMSE(t) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {row['variant']} | {row['batch']} | {row['pairs_per_s']:.1f} | {row['vs_reference']:.2f} | "
              f"{_ratio(row['vs_same_precision'])} | {row['gflop_per_s']:.0f} | "
              f"{row['rms_angle_deg']:.4f} | {row['rmse_t']:.6f} |"
              for row in sorted(rows, key=lambda r: (r["batch"], r["variant"]))]
    lines.append(f"\n`{args.model}`, {count} test pairs (PV, UPC), {args.threads} threads, {meta['machine']}, torch "
                 f"{torch.__version__}, median of {args.repeats} passes; peak RSS {peak_mb:.0f} MB"
                 + (f", peak GPU memory {peak_gpu_mb:.0f} MB" if peak_gpu_mb is not None else "")
                 + " (all variants). "
                 f"Arithmetic: {flops_per_pair / 1e9:.2f} GFLOP per pair on the reference backend in float32; "
                 f"this {'GPU' if device.type == 'cuda' else 'CPU'}'s float32 matrix products "
                 f"{gemm_rate / 1e9:.0f} GFLOP/s, so at most "
                 f"{gemm_rate / flops_per_pair:.1f} pairs/s for float32 runs of those products.")
    write_outputs("\n".join(lines), {"meta": meta, "rows": rows}, args.markdown, args.json)


if __name__ == "__main__":
    main()
