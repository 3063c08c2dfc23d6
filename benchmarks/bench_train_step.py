"""Time one training step of a VRNet preset with the compiled ops vs ``backend="torch"``.

    python benchmarks/bench_train_step.py [--preset paper] [--steps 2] [--stage 1 2] [--json PATH]
                                          [--device cuda] [--inference-points 768] [--impls ext ext-bf16]

Implementations: ``ext`` (compiled ops, float32), ``torch`` (pure PyTorch, float32) and ``ext-bf16``
(compiled ops under bfloat16 autocast, as ``vrnet train --precision bf16`` runs them).

Both backends run in this process on the same random pair batch (settings: the preset's batch
size and point counts), one warm-up step each, then ``--steps`` timed steps with the backends
taking turns step by step (a slow spell of a shared machine falls on both), median per backend (on
CUDA the clock reads follow a device synchronisation). ``--inference-points N`` also times the
eval-mode forward of one pair of N points (the paper reports 19.9 ms for 768 on a GTX 1080 Ti).
Denormal flushing (``vrnet_ext.set_flush_denormal``) is on for both backends unless
``--no-flush-denormal``. Stage 1 = full backward through DGCNN + Transformer with L0; stage 2 = frozen features, hybrid
loss through the correction walk and Kabsch.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import torch

from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.learning.losses import HybridLossWeights, correspondence_loss, hybrid_loss
from vrnet_ext.model import VRNet, VRNetConfig
from vrnet_ext.runtime import set_flush_denormal
from vrnet_ext.learning.config import PRESETS
from vrnet_ext.learning.train import set_stage, stage_train_mode
from outputs import cpu_description  # benchmarks/, the script's folder

IMPLS = {"ext": ("ext", False), "torch": ("torch", False), "ext-bf16": ("ext", True)}  # name: (backend, bf16)


def _batch(batch_size: int, points: int, generator: torch.Generator) -> dict:
    src = torch.randn(batch_size, points, 3, generator=generator)
    src = src / src.norm(dim=-1, keepdim=True).amax(dim=1, keepdim=True)
    q = torch.linalg.qr(torch.randn(batch_size, 3, 3, generator=generator)).Q
    rotation = q * torch.sign(torch.linalg.det(q)).view(-1, 1, 1)
    translation = torch.rand(batch_size, 3, generator=generator) - 0.5
    perm = torch.randperm(points, generator=generator)
    tgt = (src @ rotation.mT + translation.unsqueeze(1))[:, perm]
    gt_idx = torch.argsort(perm).expand(batch_size, points).contiguous()
    return dict(src=src, tgt=tgt, rotation=rotation, translation=translation, gt_idx=gt_idx)


def _now(device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def make_step(model: VRNet, batch: dict, stage: int, impl: str) -> Callable[[int], float]:
    """A closure that runs training step ``i`` of ``stage`` with ``impl`` and returns its seconds."""
    backend, bf16 = IMPLS[impl]
    optimizer = torch.optim.Adam(set_stage(model, stage), lr=1e-4)
    device = batch["src"].device

    def step(i: int) -> float:
        stage_train_mode(model, stage)
        start = _now(device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            out = model(batch["src"], batch["tgt"], backend=backend, return_matching=stage == 1)
            if stage == 1:
                loss = correspondence_loss(out.matching, batch["gt_idx"])
            else:
                loss, _ = hybrid_loss(out, batch["src"], batch["rotation"], batch["translation"], HybridLossWeights(),
                                      generator=torch.Generator().manual_seed(i), backend=backend)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return _now(device) - start

    return step


def step_seconds(model: VRNet, batch: dict, stage: int, steps: int, impls: list[str]) -> dict[str, float]:
    """Median seconds per step for each implementation, after one warm-up step each.

    The implementations take turns step by step, so that a slow spell of the machine falls on all.
    """
    steppers = {impl: make_step(model, batch, stage, impl) for impl in impls}
    times = {impl: [] for impl in impls}
    for i in range(steps + 1):
        for backend, step in steppers.items():
            seconds = step(i)
            if i > 0:
                times[backend].append(seconds)
    return {backend: statistics.median(values) for backend, values in times.items()}


@torch.no_grad()
def inference_seconds(model: VRNet, src: torch.Tensor, tgt: torch.Tensor, backend: str, bf16: bool = False,
                      repeats: int = 20) -> float:
    """Median eval-mode forward time of one pair src (1, N, 3), tgt (1, N, 3) after 3 warm-ups."""
    model.eval()
    times = []
    for i in range(repeats + 3):
        start = _now(src.device)
        with torch.autocast(src.device.type, dtype=torch.bfloat16, enabled=bf16):
            model(src, tgt, backend=backend)
        if i >= 3:
            times.append(_now(src.device) - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS),
                        help="`vrnet train` preset whose step is timed")
    parser.add_argument("--steps", type=int, default=2, help="timed steps per stage and implementation")
    parser.add_argument("--stage", type=int, nargs="+", default=[1, 2], help="training stages to time")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--json", default=None, help="write the records to this JSON file (none: print only)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where the steps run")
    parser.add_argument("--inference-points", type=int, default=0,
                        help="also time the forward of one pair of this many points (0: skip)")
    parser.add_argument("--impls", nargs="+", choices=sorted(IMPLS), default=["ext", "torch"],
                        help="implementations to time (the first is the baseline of the printed ratios)")
    parser.add_argument("--no-flush-denormal", action="store_true",
                        help="leave denormal floats on (slow softmax tails; see vrnet_ext.set_flush_denormal)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    flush = not args.no_flush_denormal and set_flush_denormal(True)
    preset = PRESETS[args.preset]
    torch.manual_seed(0)
    device = torch.device(args.device)
    model = VRNet(VRNetConfig.from_dict(preset["model"])).to(device)
    batch = _batch(preset["batch_size"], preset["num_subsampled"], torch.Generator().manual_seed(0))
    batch = {key: value.to(device) for key, value in batch.items()}
    common = {"preset": args.preset, "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
              "threads": args.threads, "flush_denormal": flush, "torch": torch.__version__}
    records = []
    for stage in args.stage:
        row = step_seconds(model, batch, stage, args.steps, args.impls)
        for impl in args.impls:
            records.append({"stage": stage, "impl": impl, "median_s": row[impl],
                            "batch_size": preset["batch_size"], "points": preset["num_subsampled"], **common})
            print(f"stage {stage} {impl:<8} {row[impl]:.2f} s/step", flush=True)
        base = args.impls[0]
        for impl in args.impls[1:]:
            print(f"stage {stage}: {impl} takes {row[impl] / row[base]:.2f}x the time of {base}")
    if args.inference_points:
        pair = _batch(1, args.inference_points, torch.Generator().manual_seed(1))
        for impl in args.impls:
            seconds = inference_seconds(model, pair["src"].to(device), pair["tgt"].to(device), *IMPLS[impl])
            records.append({"stage": "inference", "impl": impl, "median_s": seconds, "batch_size": 1,
                            "points": args.inference_points, **common})
            print(f"inference, one pair of {args.inference_points} points, {impl:<8} {seconds * 1e3:.2f} ms")
    print(f"machine: {cpu_description()}, device {common['device']}, threads {args.threads}, preset {args.preset} "
          f"(batch {preset['batch_size']}, {preset['num_subsampled']} points), flush_denormal={flush}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)


if __name__ == "__main__":
    main()
