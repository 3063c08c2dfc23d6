"""How much a per-point weighting of the VCPs could gain: Procrustes on the VCPs of a checkpoint's
forward pass, unweighted, weighted by the matching's row peak, with Cauchy IRLS, and with two
oracles that know the ground truth (inliers only; VCPs within 0.03 of their true position).

    python benchmarks/probe_vcp_weights.py CHECKPOINT [--pairs 160] [--data-dir DIR]

Runs on validation pairs (held out of the training split), never on the test split.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from torch.utils.data import DataLoader

from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter
from vrnet_ext.model.pretrained import load_vrnet
from vrnet_ext.data import ModelNet40Pairs, PairSpec
from vrnet_ext.geometry.metrics import euler_zyx_deg, rotation_error_deg
from vrnet_ext.ops import kabsch, robust_kabsch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("checkpoint", help="a VRNet checkpoint (its setting and split choose the pairs)")
    parser.add_argument("--pairs", type=int, default=160, help="validation pairs to probe")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    args = parser.parse_args()
    model, state = load_vrnet(args.checkpoint)
    cfg = state["config"]
    data = ModelNet40Pairs(args.data_dir, partition="val", setting=cfg.get("setting", "PV"), split=cfg.get("split", "UPC"),
                           max_items=args.pairs, spec=PairSpec(num_points=cfg.get("num_points", 1024),
                                                               num_subsampled=cfg.get("num_subsampled", 768)))
    rotations: dict[str, list[torch.Tensor]] = {}
    truths, close = [], []
    with torch.no_grad():
        for batch in DataLoader(data, batch_size=16):
            src, vcp = batch["src"], None
            out = model(src, batch["tgt"], return_matching=True)
            vcp = out.vcp
            truth = src @ batch["rotation"].mT + batch["translation"].unsqueeze(1)
            error = (vcp - truth).norm(dim=-1)
            close.append(float((error < 0.03).double().mean()))
            weightings = {
                "unweighted (DCP-v2)": None,
                "row peak of the matching": out.matching.max(dim=-1).values,
                "oracle: inliers": (batch["gt_idx"] >= 0).to(src.dtype) + 1e-9,
                "oracle: within 0.03": (error < 0.03).to(src.dtype) + 1e-9,
            }
            for name, weights in weightings.items():
                rotations.setdefault(name, []).append(kabsch(src, vcp, weights)[0])
            rotations.setdefault("Cauchy IRLS (5 steps)", []).append(robust_kabsch(src, vcp, None, 5)[0])
            truths.append(batch["rotation"])
    gt = torch.cat(truths)
    print(f"{args.checkpoint}: {len(data)} validation pairs; {100 * np.mean(close):.1f} % of VCPs within 0.03")
    for name, parts in rotations.items():
        R = torch.cat(parts)
        euler = euler_zyx_deg(R) - euler_zyx_deg(gt)
        re = rotation_error_deg(R, gt)
        print(f"{name:<28} RMSE(R) {np.sqrt((euler ** 2).mean()):7.3f}  RE mean {float(re.mean()):7.3f}  "
              f"RE median {float(re.median()):7.3f}")


if __name__ == "__main__":
    main()
