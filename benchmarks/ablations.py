"""The paper's ablations on ModelNet40 (PV / UPC test split), each one command writing JSON + PNG.

    python benchmarks/ablations.py iterations [--model vrnet-pv-upc-rcp] [--max-items N] [--out-dir DIR]
    python benchmarks/ablations.py outliers   [...]
    python benchmarks/ablations.py matches    [...]
    python benchmarks/ablations.py ransac     [...]

* ``iterations``: RMSE / MAE of rotation and translation and the time per pair after 1-6 passes of
  the network (each pass registers the source moved by the previous estimate; the paper's iteration
  table), on the paper's partial views (PRNet's far points).
* ``outliers``: the paper's symmetric partial views (the target's far point mirrors the source's),
  960 / 896 / 832 / 768 / 704 of 1,024 points kept (outlier ratios near 7-46 %): RMSE(R) and
  RMSE(t) of VRNet, of Kabsch on the same pass's VCPs (DCP-v2's estimator), of ICP from the identity
  and of FPFH + FGR (ours).
* ``matches``: on the same views, the share of source points whose correspondent lies within 0.15
  of its true position: the nearest target point ("target": what the data allow), the VCP, the RCP.
* ``ransac``: on the same views, VRNet alone against RANSAC on source <-> target FPFH matches, on
  source <-> VCP and on source <-> RCP pairs (every point paired with its own virtual point;
  inliers within 0.05).

VRNet runs as the paper's does: the configured passes only, never the second pass a shipped model
takes where its RCPs disagree with its estimate (``second_pass_below`` set to 0). The same
deterministic test pairs for every method (seed 1234). ``--max-items`` evaluates N test shapes
spread evenly over the split (the JSON says how many). Nothing here selects or tunes anything.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

sys.path.insert(0, str(Path(__file__).resolve().parent))
from modelnet40_tables import classical_estimates  # noqa: E402

from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter  # noqa: E402
from vrnet_ext import ops  # noqa: E402
from vrnet_ext.data import ModelNet40Pairs, PairSpec  # noqa: E402
from vrnet_ext.geometry.features import voxel_fpfh  # noqa: E402
from vrnet_ext.geometry.metrics import correct_match_ratio, summarize  # noqa: E402
from vrnet_ext.geometry.transforms import move  # noqa: E402
from vrnet_ext.model.pretrained import load_vrnet  # noqa: E402
from vrnet_ext.registration.fgr import fast_global_registration  # noqa: E402
from vrnet_ext.registration.ransac import fpfh_ransac, ransac  # noqa: E402

SIZES = (960, 896, 832, 768, 704)
MATCH_THRESHOLD = 0.15
RANSAC_INLIER_DISTANCE = 0.05
FPFH_VOXEL = 0.05
ICP_MAX_DISTANCE = 1.0
PAPER_ITERATIONS = {1: (0.982, 0.496, 0.00611, 0.00389), 2: (0.931, 0.447, 0.00563, 0.00327),
                    3: (0.904, 0.412, 0.00528, 0.00301), 4: (0.886, 0.398, 0.00501, 0.00292),
                    5: (0.884, 0.401, 0.00497, 0.00292), 6: (0.891, 0.399, 0.00495, 0.00291)}
COLUMNS = ("RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)")


def pairs(args, num_subsampled: int = 768, far_points: str = "prnet") -> ModelNet40Pairs:
    return ModelNet40Pairs(args.data_dir, partition="test", setting="PV", split="UPC", max_items=args.max_items,
                           seed=1234, spec=PairSpec(num_subsampled=num_subsampled, far_points=far_points))


def ground_truth(data) -> tuple[np.ndarray, np.ndarray]:
    return (np.stack([data[i]["rotation"].double().numpy() for i in range(len(data))]),
            np.stack([data[i]["translation"].double().numpy() for i in range(len(data))]))


def forward_all(model, data, batch_size: int):
    """Yields (batch, output, seconds of the forward pass) over ``data``."""
    with torch.no_grad():
        for batch in DataLoader(data, batch_size=batch_size, shuffle=False):
            started = time.perf_counter()
            out = model(batch["src"], batch["tgt"])
            yield batch, out, time.perf_counter() - started


def paper_columns(R, t, gt_R, gt_t) -> dict:
    row = summarize(np.concatenate(R), gt_R, np.concatenate(t), gt_t)
    return {c: row[c] for c in COLUMNS}


def run_iterations(model, args) -> dict:
    data = pairs(args)
    gt_R, gt_t = ground_truth(data)
    rows = []
    for iterations in range(1, 7):
        model.config.iterations = iterations
        R, t, seconds = [], [], 0.0
        for _, out, elapsed in forward_all(model, data, args.batch_size):
            R.append(out.rotation.double().numpy()); t.append(out.translation.double().numpy()); seconds += elapsed
        rows.append({"iterations": iterations, **paper_columns(R, t, gt_R, gt_t), "ms_per_pair": 1e3 * seconds / len(data),
                     "paper": dict(zip(COLUMNS, PAPER_ITERATIONS[iterations]))})
        print(json.dumps(rows[-1]), flush=True)
    model.config.iterations = 1
    return {"pairs": len(data), "rows": rows}


def fgr_estimates(data) -> tuple[np.ndarray, np.ndarray]:
    rotations, translations = [], []
    for i in range(len(data)):
        src, tgt = data[i]["src"].double(), data[i]["tgt"].double()
        try:
            T = fast_global_registration(src, tgt, voxel_fpfh(src, FPFH_VOXEL), voxel_fpfh(tgt, FPFH_VOXEL),
                                         max_distance=1.5 * FPFH_VOXEL, seed=i).numpy()
        except ValueError:
            T = np.eye(4)
        rotations.append(T[:3, :3]); translations.append(T[:3, 3])
    return np.stack(rotations), np.stack(translations)


def outlier_ratio(data) -> float:
    return float(np.mean([(data[i]["gt_idx"] < 0).double().mean() for i in range(len(data))]))


def run_outliers(model, args) -> dict:
    rows = []
    for size in SIZES:
        data = pairs(args, size, "symmetric")
        gt_R, gt_t = ground_truth(data)
        R = {"VRNet": [], "VCP-only (DCP-v2 estimator)": []}
        t = {name: [] for name in R}
        for batch, out, _ in forward_all(model, data, args.batch_size):
            R_vcp, t_vcp = ops.kabsch(batch["src"], out.vcp)
            for name, (rot, trans) in (("VRNet", (out.rotation, out.translation)),
                                       ("VCP-only (DCP-v2 estimator)", (R_vcp, t_vcp))):
                R[name].append(rot.double().numpy()); t[name].append(trans.double().numpy())
        methods = {name: paper_columns(R[name], t[name], gt_R, gt_t) for name in R}
        icp_R, icp_t, _, _ = classical_estimates(data, "icp", ICP_MAX_DISTANCE, FPFH_VOXEL)
        methods["ICP"] = paper_columns([icp_R], [icp_t], gt_R, gt_t)
        fgr_R, fgr_t = fgr_estimates(data)
        methods["FPFH + FGR"] = paper_columns([fgr_R], [fgr_t], gt_R, gt_t)
        rows.append({"points": size, "outlier_ratio": outlier_ratio(data), "methods": methods})
        print(json.dumps(rows[-1]), flush=True)
    return {"pairs": len(pairs(args)), "rows": rows}


def run_matches(model, args) -> dict:
    rows = []
    for size in SIZES:
        data = pairs(args, size, "symmetric")
        ratios = {"target (nearest point)": [], "VCP": [], "RCP": []}
        for batch, out, _ in forward_all(model, data, args.batch_size):
            truth = move(batch["src"], batch["rotation"], batch["translation"])
            nearest, _ = ops.knn(truth, batch["tgt"], 1)
            ratios["target (nearest point)"] += (nearest[..., 0] < MATCH_THRESHOLD ** 2).double().mean(1).tolist()
            for name, points in (("VCP", out.vcp), ("RCP", out.rcp)):
                ratios[name] += correct_match_ratio(points, batch["src"], batch["rotation"], batch["translation"],
                                                    MATCH_THRESHOLD).tolist()
        rows.append({"points": size, "outlier_ratio": outlier_ratio(data),
                     "correct_match_ratio": {k: float(np.mean(v)) for k, v in ratios.items()}})
        print(json.dumps(rows[-1]), flush=True)
    return {"pairs": len(pairs(args)), "threshold": MATCH_THRESHOLD, "rows": rows}


def run_ransac(model, args) -> dict:
    rows = []
    for size in SIZES:
        data = pairs(args, size, "symmetric")
        gt_R, gt_t = ground_truth(data)
        R = {"VRNet": [], "RANSAC source-target (FPFH)": [], "RANSAC source-VCP": [], "RANSAC source-RCP": []}
        t = {name: [] for name in R}
        index = 0
        for batch, out, _ in forward_all(model, data, args.batch_size):
            R["VRNet"].append(out.rotation.double().numpy()); t["VRNet"].append(out.translation.double().numpy())
            for b in range(batch["src"].shape[0]):
                src, tgt = batch["src"][b].double(), batch["tgt"][b].double()
                own = torch.arange(src.shape[0])
                estimates = {"RANSAC source-target (FPFH)": lambda: fpfh_ransac(src, tgt, FPFH_VOXEL, seed=index)[0]}
                for name, points in (("RANSAC source-VCP", out.vcp[b]), ("RANSAC source-RCP", out.rcp[b])):
                    estimates[name] = (lambda p=points: ransac(src, p.double(), torch.stack([own, own], 1),
                                                               RANSAC_INLIER_DISTANCE, seed=index)[0])
                for name, estimate in estimates.items():
                    try:
                        T = estimate().numpy()
                    except ValueError:
                        T = np.eye(4)
                    R[name].append(T[None, :3, :3]); t[name].append(T[None, :3, 3])
                index += 1
        methods = {name: paper_columns(R[name], t[name], gt_R, gt_t) for name in R}
        rows.append({"points": size, "outlier_ratio": outlier_ratio(data), "methods": methods})
        print(json.dumps(rows[-1]), flush=True)
    return {"pairs": len(pairs(args)), "inlier_distance": RANSAC_INLIER_DISTANCE, "rows": rows}


def plot(name: str, result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    if name == "iterations":
        fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
        x = [r["iterations"] for r in rows]
        for ax, column in zip(axes, ("RMSE(R)", "RMSE(t)")):
            ax.plot(x, [r[column] for r in rows], marker="o", label="ours")
            ax.plot(x, [r["paper"][column] for r in rows], marker="s", linestyle="--", label="paper")
            ax.set_xlabel("iterations"); ax.set_title(column); ax.legend(); ax.grid(alpha=0.3)
        axes[2].plot(x, [r["ms_per_pair"] for r in rows], marker="o")
        axes[2].set_xlabel("iterations"); axes[2].set_title("ms per pair (ours)"); axes[2].grid(alpha=0.3)
    elif name == "matches":
        fig, ax = plt.subplots(figsize=(6, 4))
        x = [100 * r["outlier_ratio"] for r in rows]
        for key in rows[0]["correct_match_ratio"]:
            ax.plot(x, [r["correct_match_ratio"][key] for r in rows], marker="o", label=key)
        ax.set_xlabel("outlier ratio (%)"); ax.set_ylabel(f"correct matches (< {result['threshold']})")
        ax.legend(); ax.grid(alpha=0.3)
    else:
        fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
        x = [100 * r["outlier_ratio"] for r in rows]
        for ax, column in zip(axes, COLUMNS):
            for method in rows[0]["methods"]:
                ax.plot(x, [r["methods"][method][column] for r in rows], marker="o", label=method)
            ax.set_xlabel("outlier ratio (%)"); ax.set_title(column); ax.set_yscale("log"); ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
    fig.suptitle(f"{name} ({result['pairs']} ModelNet40 PV/UPC test pairs, model {result['model']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


RUNNERS = {"iterations": run_iterations, "outliers": run_outliers, "matches": run_matches, "ransac": run_ransac}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=DefaultsHelpFormatter)
    parser.add_argument("ablation", choices=sorted(RUNNERS),
                        help="iterations: errors against passes; outliers: errors against the outlier ratio; "
                             "matches: correct-match ratios of VCPs and RCPs; ransac: RANSAC on source-RCP, "
                             "source-VCP and source-target pairs against VRNet alone")
    parser.add_argument("--model", default="vrnet-pv-upc-rcp", help="shipped name or checkpoint")
    parser.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    parser.add_argument("--max-items", type=int, default=None, help="N test shapes spread evenly over the split (default: all)")
    parser.add_argument("--batch-size", type=int, default=16, help="pairs per network forward")
    parser.add_argument("--out-dir", type=Path, default=Path("."), help="where ablation_NAME.json and .png go")
    args = parser.parse_args(argv)
    model, _ = load_vrnet(args.model)
    model.config.second_pass_below = 0.0
    result = RUNNERS[args.ablation](model, args)
    result.update(ablation=args.ablation, model=args.model, date=time.strftime("%Y-%m-%d"),
                  machine=f"{platform.machine()}, {torch.get_num_threads()} threads, torch {torch.__version__}")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    json_path, png_path = args.out_dir / f"ablation_{args.ablation}.json", args.out_dir / f"ablation_{args.ablation}.png"
    json_path.write_text(json.dumps(result, indent=1))
    plot(args.ablation, result, png_path)
    print(f"wrote {json_path} and {png_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
