"""``vrnet register-batch``: a manifest of pairs registered in one run, resumable, sharded by
``torchrun`` (:mod:`vrnet_ext.registration.batch`)."""
from __future__ import annotations

import os
import sys

from vrnet_ext.cli.common import DefaultsHelpFormatter, Switch, positive_float, writable_path
from vrnet_ext.cli.registering import add_registration_options, add_success_options, registration_arguments


def add_register_batch(sub) -> None:
    p = sub.add_parser(
        "register-batch", help="register every pair of a manifest (CSV, TSV or JSON Lines), resumable, torchrun-ready",
        description="Registers every pair of MANIFEST as `vrnet register` does (the same options, the same result "
                    "for the same seed) and writes one JSON Lines record per pair to --out as each finishes: the "
                    "transform, fitness, consensus, warnings, time, and with a ground truth its errors and whether it "
                    "counts as registered; a pair that fails gets its error. A run stopped or killed resumes with "
                    "the same command. Under `torchrun --nproc-per-node N -m vrnet_ext.cli register-batch ...` each "
                    "process takes every N-th pair and rank 0 merges the records in manifest order. MANIFEST "
                    "columns: source, target, optional gt (a 4x4 file or a 3DMatch gt.log) and id; paths relative "
                    "to the manifest's folder.",
        formatter_class=DefaultsHelpFormatter)
    p.add_argument("manifest", help="pairs: CSV / TSV with a header (source, target[, gt][, id]) or JSON Lines")
    p.add_argument("--out", type=writable_path, required=True,
                   help="the JSON Lines file of records (resumed if it exists)")
    add_success_options(p, "a pair with ground truth")
    p.add_argument("--progress", action=Switch, default=True, help="progress bar")
    add_registration_options(p)


def rank_device(device: str, local_rank: int, gpus: int) -> str:
    """The device a torchrun rank registers on: with ``--device cuda`` (no index) GPU ``local_rank %
    gpus`` of its machine (each rank its own where there are enough, else ranks share them in turn:
    several processes keep one GPU busy); any other device as given."""
    return f"cuda:{local_rank % gpus}" if device == "cuda" and gpus > 0 else device


def run_register_batch(args) -> int:
    from datetime import timedelta

    from vrnet_ext.registration.batch import BatchOptions, Shard, merge, register_batch, summary

    world, rank = int(os.environ.get("WORLD_SIZE", "1")), int(os.environ.get("RANK", "0"))
    distributed = world > 1
    if distributed:
        import torch
        import torch.distributed as dist

        dist.init_process_group("gloo", timeout=timedelta(days=7))  # ranks wait for the slowest at the end
        gpus = torch.cuda.device_count() if args.device == "cuda" else 0
        args.device = rank_device(args.device, int(os.environ.get("LOCAL_RANK", "0")), gpus)
    try:
        options = BatchOptions(register=registration_arguments(args), success_rotation_deg=args.success_rotation,
                               success_translation=args.success_translation)
        mine = register_batch(args.manifest, args.out, options, shard=Shard(rank, world),
                              progress=args.progress)
        if distributed:
            dist.barrier()
        if rank == 0:
            records = merge(args.manifest, args.out)
            total = summary(records)
            line = ", ".join(f"{key} {value:.4g}" if isinstance(value, float) else f"{key} {value}"
                             for key, value in total.items())
            rate = f"; this run {mine['pairs_per_second']:.2f} pairs/s" if "pairs_per_second" in mine else ""
            print(f"{line}{rate}\nwrote {args.out}")
            failed = [r for r in records if "error" in r]
            for record in failed[:5]:
                print(f"vrnet register-batch: warning: pair {record['id']}: {record['error']}", file=sys.stderr)
    finally:
        if distributed:
            dist.destroy_process_group()
    return 0
