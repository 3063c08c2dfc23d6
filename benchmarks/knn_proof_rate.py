"""How often the tensor-core kNN proves its ranking (modelled on the CPU): the share of rows it does not scan whole.

    python benchmarks/knn_proof_rate.py [--models vrnet-pv-upc-rcp ...] [--pairs 8] [--json F] [--markdown F]

On a GPU with TF32 tensor cores, ``ops.knn`` of float32 feature rows keeps candidates by approximate
distances from tensor-core products, four lists of 16 a row, ranks them by exact distance, and proves
the ranking with a bound on the products' error; a row without the proof is scanned exhaustively,
which costs a full row of exact distances (docs/gpu.md). How many rows need that scan depends on the
data, and this script measures it without a GPU by modelling the kernel's arithmetic: each centred
operand split into two TF32 parts as ``cvt.rna`` rounds them, the three products of the parts (all but
small x small) accumulated in float64 (the proof's bound covers any float32 accumulation), the lists
and the proof's test as the kernel writes them; and, for comparison, with one TF32 product per pair.
Data: the DGCNN feature graphs (k = 20, the point itself included) of shipped models on ModelNet40
validation pairs, standard normal rows of the same sizes and of the paper preset's widths, and the
FPFH descriptors of two kitchen fragments (k = 1: the registration pipeline's matching).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder
from vrnet_ext import ops
from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter, device_name
from vrnet_ext.data.modelnet import ModelNet40Pairs
from vrnet_ext.geometry.features import describe
from vrnet_ext.geometry.io import read_points
from vrnet_ext.model import dgcnn
from vrnet_ext.model.pretrained import load_pretrained
from vrnet_ext.ops.knn import tensor_core_unproven_rows

LANES, LANE_CANDIDATES = 4, 16  # csrc/knn/knn_kernels.cuh: a row's four lanes, the candidates each keeps
KERNEL_PASSES = 3  # csrc/knn/knn_kernels.cuh: kKnnTensorCorePasses
PASSES = (KERNEL_PASSES, 1)  # the kernel's products, and one TF32 product for comparison
PAPER_PRESET_WIDTHS = (64, 128)  # the paper preset's feature graphs (dgcnn_channels 64, 64, 128, 256)
DEFAULT_SCENES = Path(__file__).resolve().parents[2] / "shared" / "data" / "scenes"
KITCHEN_PAIR = ("cloud_bin_0.ply", "cloud_bin_4.ply")


def to_tf32(x: torch.Tensor) -> torch.Tensor:
    """float32 ``x`` rounded to TF32 (10 mantissa bits, to nearest, ties away from zero), as ``cvt.rna``."""
    bits = x.contiguous().view(torch.int32)
    return ((bits + 0x1000) & ~0x1FFF).view(torch.float32)


def tf32_products(a: torch.Tensor, b: torch.Tensor, passes: int) -> torch.Tensor:
    """a (N, C) bᵀ (C, M) as the tensor cores compute it in ``passes`` (1: TF32 operands; 3: each operand
    split into TF32 parts hi + lo, the products hi hi + hi lo + lo hi), accumulated in float64."""
    a_hi, b_hi = to_tf32(a), to_tf32(b)
    products = a_hi.double() @ b_hi.double().T
    if passes == 3:
        a_lo, b_lo = to_tf32(a - a_hi), to_tf32(b - b_hi)
        products += a_hi.double() @ b_lo.double().T + a_lo.double() @ b_hi.double().T
    return products.float()


def relative_error(channels: int, passes: int) -> float:
    """The kernel's bound on an approximate distance's error, per |q|^2 + max |r|^2 (knn_kernels.cuh)."""
    return (8 * channels + 64) * 2**-23 if passes == 3 else 2**-10 + (4 * channels + 32) * 2**-23


def proven_rows(query: torch.Tensor, ref: torch.Tensor, k: int, passes: int = 3) -> torch.Tensor:
    """(N,) bool: which rows of ``query`` (N, C) the tensor-core kNN proves against ``ref`` (M, C) with
    ``passes`` products per operand pair."""
    channels = query.shape[1]
    mean = ref.double().mean(0, keepdim=True)
    query_c, ref_c = (query.double() - mean).float(), (ref.double() - mean).float()
    query_norm, ref_norm = query_c.square().sum(-1), ref_c.square().sum(-1)
    dots = tf32_products(query_c, ref_c, passes)
    approx = (query_norm[:, None] + ref_norm[None] - 2 * dots).clamp_min(0)
    exact = torch.cdist(query.double(), ref.double()).square().float()
    lane = (torch.arange(ref.shape[0]) % 8) // 2
    candidates, dropped_from = [], torch.full((query.shape[0],), float("inf"))
    for column in range(LANES):
        columns = (lane == column).nonzero().flatten()
        order = approx[:, columns].sort(dim=1, stable=True).indices[:, :LANE_CANDIDATES]
        candidates.append(columns[order])
        if len(columns) > LANE_CANDIDATES:
            dropped_from = torch.minimum(dropped_from, approx[:, columns].gather(1, order[:, -1:]).squeeze(1))
    kth = exact.gather(1, torch.cat(candidates, dim=1)).sort(dim=1).values[:, k - 1]
    error = relative_error(channels, passes) * (query_norm + ref_norm.max()) + channels * 2**-100
    rounding = (channels + 16) * 2**-23
    return (dropped_from - error) * (1 - rounding) > kth


def feature_graphs(model_name: str, data_dir: Path | None, pairs: int) -> list[torch.Tensor]:
    """The (N, C) feature rows each DGCNN graph of ``model_name`` is built over, C > 3, for ``pairs``
    validation pairs (source and target clouds)."""
    model = load_pretrained(model_name).eval()
    data = ModelNet40Pairs(data_dir, partition="val", setting="PV", max_items=pairs)
    seen, knn = [], dgcnn.knn

    def recording(query, ref, k, backend="ext"):
        if query.shape[-1] > 3:
            seen.extend(query.detach().unbind(0))
        return knn(query, ref, k, backend=backend)

    dgcnn.knn = recording
    try:
        with torch.no_grad():
            for item in (data[i] for i in range(len(data))):
                model(item["src"][None], item["tgt"][None])
    finally:
        dgcnn.knn = knn
    return seen


def fpfh_descriptors(scenes: Path, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The FPFH descriptors (float32, 33 values) of two 3DMatch kitchen fragments at ``voxel``: what the
    registration pipeline matches (each point's nearest descriptor, k = 1)."""
    views = []
    for name in KITCHEN_PAIR:
        points = torch.as_tensor(read_points(scenes / "3dmatch_redkitchen" / name), dtype=torch.float64)
        views.append(describe(ops.voxel_downsample(points, voxel).numpy(), voxel).descriptors.float())
    return views[0], views[1]


def summary(source: str, width: int, k: int, proofs_by_passes: dict[int, list[torch.Tensor]],
            on_gpu: list[torch.Tensor]) -> list[dict]:
    """One row per pass count: the modelled proofs, and (three passes) the GPU kernel's where it ran."""
    rows = []
    for passes, results in proofs_by_passes.items():
        proven = torch.cat(results)
        row = {"source": source, "C": width, "k": k, "passes": passes, "graphs": len(results), "rows": len(proven),
               "proven": int(proven.sum()), "proven_share": float(proven.float().mean())}
        if on_gpu and passes == KERNEL_PASSES:
            row["proven_on_gpu"] = int(torch.cat(on_gpu).sum())
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="*", default=["vrnet-pv-upc-rcp", "vrnet-pv-nd-rcp"],
                        help="shipped models (names or checkpoints) whose feature graphs are measured (none: none)")
    parser.add_argument("--data-dir", type=Path, default=None, help=DATA_DIR_HELP)
    parser.add_argument("--scenes", type=Path, default=DEFAULT_SCENES, help="the shared scenes folder (FPFH rows)")
    parser.add_argument("--fpfh-voxels", type=float, nargs="*", default=[0.05, 0.025],
                        help="voxel sizes (m) of the FPFH rows (none: no FPFH rows)")
    parser.add_argument("--pairs", type=int, default=8, help="validation pairs per model")
    parser.add_argument("--k", type=int, default=20, help="neighbours per row of the feature graphs (the DGCNN's)")
    parser.add_argument("--device", type=device_name, default="cpu",
                        help="cuda: also count the rows the kernel proves there (ops.knn.tensor_core_unproven_rows)")
    parser.add_argument("--json", default=None, help="write the rows here")
    parser.add_argument("--markdown", default=None, help="write the table here")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    rows = []
    generator = torch.Generator().manual_seed(0)

    def collect(source, width, k, cases):
        proofs, on_gpu = {passes: [] for passes in PASSES}, []
        for query, ref in cases:
            for passes in PASSES:
                proofs[passes].append(proven_rows(query, ref, k, passes))
            if device.type == "cuda":
                on_gpu.append(~tensor_core_unproven_rows(query[None].to(device), ref[None].to(device), k)[0].cpu())
        rows.extend(summary(source, width, k, proofs, on_gpu))

    for model_name in args.models:
        by_width: dict[int, list[torch.Tensor]] = {}
        for features in feature_graphs(model_name, args.data_dir, args.pairs):
            by_width.setdefault(features.shape[1], []).append(features)
        for width, graphs in sorted(by_width.items()):
            collect(f"{model_name} feature graphs", width, args.k, [(x, x) for x in graphs])
            normal = torch.randn(len(graphs), *graphs[0].shape, generator=generator)
            collect("standard normal rows", width, args.k, [(x, x) for x in normal])
    for width in PAPER_PRESET_WIDTHS:  # the paper preset's graphs in a training step: 1,024 points
        collect("standard normal rows, 1,024 a graph", width, args.k,
                [(x, x) for x in torch.randn(4, 1024, width, generator=generator)])
    for voxel in args.fpfh_voxels:
        source, target = fpfh_descriptors(args.scenes, voxel)
        collect(f"FPFH, kitchen fragments, {100 * voxel:g} cm voxels", source.shape[1], 1, [(source, target)])
    where = f", the kernel's own on {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""
    note = (f"The tensor-core kNN's proof modelled on the CPU ({cpu_description()}){where}, "
            f"{args.pairs} ModelNet40 validation pairs per model, {time.strftime('%Y-%m-%d')}.")
    lines = [note, "", "| data | C | k | passes | graphs | rows | proven | proven on the GPU |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['source']} | {r['C']} | {r['k']} | {r['passes']} | {r['graphs']} | {r['rows']} | "
              f"{100 * r['proven_share']:.2f} % | "
              + (f"{100 * r['proven_on_gpu'] / r['rows']:.2f} % |" if "proven_on_gpu" in r else "|") for r in rows]
    write_outputs("\n".join(lines), {"note": note, "rows": rows}, args.markdown, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
