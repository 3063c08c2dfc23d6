"""How often the tensor-core kNN proves its ranking, modelled on the CPU: the share of query rows it does not scan whole.

    python benchmarks/knn_proof_rate.py [--models vrnet-pv-upc-rcp ...] [--pairs 8] [--json F] [--markdown F]

On a GPU with TF32 tensor cores, ``ops.knn`` of float32 feature rows keeps candidates by approximate
(TF32) distances, four lists of 16 a row, ranks them by exact distance, and proves the ranking with a
bound on the products' error; a row without the proof is scanned exhaustively, which costs a full
row of exact distances (docs/gpu.md). How many rows need that scan depends on the data, and this script
measures it without a GPU by modelling the kernel's arithmetic: the centred rows' operands rounded to
TF32 as ``cvt.rna`` does, the products accumulated in float64 (the proof's bound covers any float32
accumulation), the lists and the proof's test as the kernel writes them. Data: the DGCNN feature
graphs (k = 20, the point itself included) of shipped models on ModelNet40 validation pairs, standard
normal rows of the same sizes, and of the paper preset's widths.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from outputs import cpu_description, write_outputs  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DATA_DIR_HELP, DefaultsHelpFormatter
from vrnet_ext.data.modelnet import ModelNet40Pairs
from vrnet_ext.model import dgcnn
from vrnet_ext.model.pretrained import load_pretrained

LANES, LANE_CANDIDATES = 4, 16  # csrc/knn/knn_kernels.cuh: a row's four lanes, the candidates each keeps
PAPER_PRESET_WIDTHS = (64, 128)  # the paper preset's feature graphs (dgcnn_channels 64, 64, 128, 256)


def to_tf32(x: torch.Tensor) -> torch.Tensor:
    """float32 ``x`` rounded to TF32 (10 mantissa bits, to nearest, ties away from zero), as ``cvt.rna``."""
    bits = x.contiguous().view(torch.int32)
    return ((bits + 0x1000) & ~0x1FFF).view(torch.float32)


def proven_rows(query: torch.Tensor, ref: torch.Tensor, k: int) -> torch.Tensor:
    """(N,) bool: which rows of ``query`` (N, C) the tensor-core kNN proves against ``ref`` (M, C)."""
    channels = query.shape[1]
    mean = ref.double().mean(0, keepdim=True)
    query_c, ref_c = (query.double() - mean).float(), (ref.double() - mean).float()
    query_norm, ref_norm = query_c.square().sum(-1), ref_c.square().sum(-1)
    dots = (to_tf32(query_c).double() @ to_tf32(ref_c).double().T).float()
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
    error = (2**-10 + (4 * channels + 32) * 2**-23) * (query_norm + ref_norm.max()) + channels * 2**-100
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["vrnet-pv-upc-rcp", "vrnet-pv-nd-rcp"],
                        help="shipped model names or checkpoints")
    parser.add_argument("--data-dir", type=Path, default=None, help=DATA_DIR_HELP)
    parser.add_argument("--pairs", type=int, default=8, help="validation pairs per model")
    parser.add_argument("--k", type=int, default=20, help="neighbours per row (the DGCNN's)")
    parser.add_argument("--json", default=None, help="write the rows here")
    parser.add_argument("--markdown", default=None, help="write the table here")
    args = parser.parse_args(argv)
    rows = []
    generator = torch.Generator().manual_seed(0)
    for model_name in args.models:
        by_width: dict[int, list[torch.Tensor]] = {}
        for features in feature_graphs(model_name, args.data_dir, args.pairs):
            by_width.setdefault(features.shape[1], []).append(proven_rows(features, features, args.k))
        for width, proofs in sorted(by_width.items()):
            shape = (len(proofs[0]), width)
            normal = [proven_rows(x, x, args.k) for x in torch.randn(len(proofs), *shape, generator=generator)]
            for source, results in ((f"{model_name} feature graphs", proofs), ("standard normal rows", normal)):
                proven = torch.cat(results)
                rows.append({"source": source, "C": width, "graphs": len(results), "rows": len(proven),
                             "proven": int(proven.sum()), "proven_share": float(proven.float().mean())})
    for width in PAPER_PRESET_WIDTHS:  # the paper preset's graphs in a training step: 1,024 points
        proven = torch.cat([proven_rows(x, x, args.k) for x in torch.randn(4, 1024, width, generator=generator)])
        rows.append({"source": "standard normal rows, 1,024 a graph", "C": width, "graphs": 4, "rows": len(proven),
                     "proven": int(proven.sum()), "proven_share": float(proven.float().mean())})
    note = (f"The tensor-core kNN's proof modelled on the CPU ({cpu_description()}), k = {args.k}, "
            f"{args.pairs} ModelNet40 validation pairs per model, {time.strftime('%Y-%m-%d')}.")
    lines = [note, "", "| data | C | graphs | rows | proven |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {r['source']} | {r['C']} | {r['graphs']} | {r['rows']} | {100 * r['proven_share']:.2f} % |"
              for r in rows]
    write_outputs("\n".join(lines), {"note": note, "rows": rows}, args.markdown, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
