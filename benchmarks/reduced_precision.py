"""What reduced-precision matrix products (TF32, bfloat16) do to a shipped model's errors, on the CPU.

    python benchmarks/reduced_precision.py [--model vrnet-pv-upc-rcp] [--partition val] [--json F] [--markdown F]

On a GPU, torch runs float32 matrix products on TF32 tensor cores where
``torch.set_float32_matmul_precision("high")`` allows it (cuDNN's convolutions do by default), and
in bfloat16 under autocast. Whether the model keeps its errors there is a question of numerics,
answered here without a GPU: the model runs as it runs on a GPU (the soft matching by dense products;
the DGCNN's feature graphs by the compiled kNN, whose tensor-core candidates are ranked by exact
distance, as on the CPU; the compiled Procrustes solves in float64) while a ``TorchFunctionMode``
rounds every float32 operand of torch's matrix products (``mm``, ``bmm``, ``matmul``, ``linear``,
``conv1d/2d``, ``einsum``, ``baddbmm``, ``addmm``, SDPA) to TF32's 10 or bfloat16's 7 mantissa bits (round to nearest
even), the products accumulated in float32, as the tensor cores do; in the TF32 rows the point
transforms take the multiply-adds a GPU allowing TF32 takes (``geometry.transforms``), but where a
row says they are products. The Transformer runs in float32
in every row but one, which runs it under bfloat16 autocast for real (the CPU's default). Reports the paper's
columns, recall and the median rotation error per precision, on validation pairs by default (a
precision is a choice: never made on the test split).
"""
from __future__ import annotations

import argparse
import json
import time
from contextlib import ExitStack
from pathlib import Path
from unittest import mock

import torch
from torch.overrides import TorchFunctionMode

from outputs import cpu_description  # benchmarks/, the script's folder
from vrnet_ext.cli.common import DefaultsHelpFormatter
from vrnet_ext.data import ModelNet40Pairs, PairSpec
from vrnet_ext.geometry import transforms
from vrnet_ext.learning.evaluate import evaluate
from vrnet_ext.model import vrnet
from vrnet_ext.model.pretrained import load_vrnet

F = torch.nn.functional
PRODUCTS = {torch.mm, torch.bmm, torch.matmul, torch.Tensor.__matmul__, torch.Tensor.matmul, torch.Tensor.mm,
            torch.Tensor.bmm, torch.baddbmm, torch.addmm, torch.einsum, F.linear, F.conv1d, F.conv2d,
            F.scaled_dot_product_attention}
# (name, mantissa bits of the rounded operands, which products, the Transformer's precision, whether points
# are moved and motions composed by matrix products): float32; TF32 in one part only (the soft matching,
# the DGCNN, the Transformer, the correction walk, outside the networks: the
# points moved by estimates and the motions composed); TF32 everywhere as a GPU allowing it runs now
# (the transforms as float32 multiply-adds, geometry.transforms) and as before (by products); the
# Transformer under bfloat16 autocast (really run: its outputs are bfloat16 too); bfloat16 operands in
# the matching only, everywhere
VARIANTS = (("fp32", None, "all", "fp32", True), ("tf32 matching", 10, "matching", "fp32", False),
            ("tf32 DGCNN", 10, "features", "fp32", False),
            ("tf32 Transformer", 10, "transformer", "fp32", False), ("tf32 walk", 10, "walk", "fp32", False),
            ("tf32 transforms as products", 10, "outside", "fp32", True), ("tf32", 10, "all", "fp32", False),
            ("tf32, transforms as products", 10, "all", "fp32", True),
            ("bf16 Transformer (autocast)", None, "all", "bf16", True), ("bf16 matching", 7, "matching", "fp32", True),
            ("bf16", 7, "all", "fp32", True))
_INSIDE = {"matching": 0, "features": 0, "transformer": 0, "walk": 0}  # how deep the running code is in each


def round_mantissa(x: torch.Tensor, bits: int) -> torch.Tensor:
    """float32 ``x`` rounded to ``bits`` explicit mantissa bits, to nearest even (Inf / NaN kept)."""
    shift = 23 - bits
    raw = x.contiguous().view(torch.int32)
    bias = ((raw >> shift) & 1) + ((1 << (shift - 1)) - 1)
    rounded = ((raw + bias) >> shift) << shift
    finite = torch.isfinite(x)
    return torch.where(finite, rounded.view(torch.float32), x)


class RoundedProducts(TorchFunctionMode):
    """Rounds the float32 tensor operands of torch's matrix products to ``bits`` mantissa bits:
    ``scope`` "all", "outside" (products outside every scope of ``_INSIDE``) or one of ``_INSIDE`` (the
    products inside the soft matching, the DGCNN, the Transformer or the correction walk)."""

    def __init__(self, bits: int, scope: str):
        super().__init__()
        self.bits, self.scope = bits, scope

    def _applies(self, func) -> bool:
        if self.scope == "outside" and any(_INSIDE.values()):
            return False
        if self.scope in _INSIDE and not _INSIDE[self.scope]:
            return False
        return func in PRODUCTS

    def _round(self, value):
        if isinstance(value, torch.Tensor) and value.dtype == torch.float32:
            return round_mantissa(value, self.bits)
        if isinstance(value, (list, tuple)):
            return type(value)(self._round(v) for v in value)
        return value

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if not self._applies(func):
            return func(*args, **kwargs)
        args, kwargs = self._round(args), {k: self._round(v) for k, v in kwargs.items()}
        return func(*args, **kwargs)


def as_on_a_gpu():
    """The model's GPU paths on the CPU: soft matching by dense products (the feature graphs are the
    compiled kNN's on either device)."""
    stack = ExitStack()
    dense, match_clouds = vrnet.soft_match, vrnet.match_clouds
    stack.enter_context(mock.patch.object(vrnet, "soft_match",
                                          lambda *args, **kwargs: dense(*args, **{**kwargs, "backend": "torch"})))

    def matching(*args, **kwargs):  # the soft matching, inside its scope
        _INSIDE["matching"] += 1
        try:
            return match_clouds(*args, **kwargs)
        finally:
            _INSIDE["matching"] -= 1

    stack.enter_context(mock.patch.object(vrnet, "match_clouds", matching))
    return stack


def run(model_name: str, data_dir: Path | None, partition: str, max_items: int | None, batch_size: int,
        variants: list[str]) -> list[dict]:
    model, state = load_vrnet(model_name, "cpu")
    cfg = state["config"]
    for scope, module in (("features", model.features), ("transformer", model.transformer), ("walk", model.walk)):
        module.register_forward_pre_hook(lambda *_, scope=scope: _INSIDE.__setitem__(scope, _INSIDE[scope] + 1))
        module.register_forward_hook(lambda *_, scope=scope: _INSIDE.__setitem__(scope, _INSIDE[scope] - 1))
    spec = PairSpec(num_points=cfg.get("num_points", 1024), num_subsampled=cfg.get("num_subsampled", 768))
    data = ModelNet40Pairs(data_dir, partition=partition, setting=cfg["setting"], split=cfg["split"],
                           max_items=max_items, spec=spec, val_fraction=cfg.get("val_fraction", 0.1))
    rows = []
    for name, bits, scope, transformer_precision, transforms_as_products in VARIANTS:
        if name not in variants:
            continue
        model.config.transformer_precision = transformer_precision
        start = time.perf_counter()
        with (as_on_a_gpu(), torch.no_grad(), (RoundedProducts(bits, scope) if bits else ExitStack()),
              mock.patch.object(transforms, "_matmul_would_round",
                                lambda x, fallback=not transforms_as_products: fallback and torch.is_tensor(x))):
            result = evaluate(model, data, batch_size=batch_size, backend="ext", progress=False)
        rows.append({"precision": name, "mantissa_bits": bits or 23, "scope": scope,
                     "transformer_precision": transformer_precision, "transforms_as_products": transforms_as_products,
                     "seconds": time.perf_counter() - start,
                     **{k: v for k, v in result.items() if isinstance(v, (int, float))}})
        print(f"{name}: RMSE(R) {result['RMSE(R)']:.4f}, RE median {result['RE median (deg)']:.4f}, "
              f"recall {result['recall(RE<5,TE<0.1)']:.4f}", flush=True)
    return rows


COLUMNS = ("RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)", "RE median (deg)", "recall(RE<5,TE<0.1)")


def markdown(rows: list[dict], note: str) -> str:
    lines = [note, "", "| operands of the products | " + " | ".join(COLUMNS) + " | RMSE(R) / fp32 |",
             "|---|" + "---:|" * (len(COLUMNS) + 1)]
    base = rows[0]["RMSE(R)"]
    for row in rows:
        cells = [f"{row[c]:.4g}" if c in row else "" for c in COLUMNS]
        lines.append(f"| {row['precision']} | " + " | ".join(cells)
                     + f" | {row['RMSE(R)'] / base:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--model", default="vrnet-pv-upc-rcp", help="shipped model name or checkpoint")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="folder of modelnet40_1024_{train,test}.h5 (None: as `vrnet eval` finds it)")
    parser.add_argument("--partition", default="val", choices=("val", "test"), help="which pairs")
    parser.add_argument("--max-items", type=int, default=None, help="N shapes spread evenly over the split only")
    parser.add_argument("--batch-size", type=int, default=16, help="pairs per forward")
    parser.add_argument("--variants", nargs="+", choices=[v[0] for v in VARIANTS], default=[v[0] for v in VARIANTS],
                        metavar="NAME", help="rows to run, by name (fp32 first: the ratios are to it)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    parser.add_argument("--markdown", type=Path, default=None, help="write the table here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.variants[0] != "fp32":
        parser.error("--variants: fp32 must come first (every ratio is to it)")
    rows = run(args.model, args.data_dir, args.partition, args.max_items, args.batch_size, args.variants)
    note = (f"{args.model} on ModelNet40 {args.partition} pairs ({rows[0]['pairs']}), the model's own protocol; "
            f"GPU paths run on the CPU ({cpu_description()}, {args.threads} threads), matrix-product operands "
            f"rounded (benchmarks/reduced_precision.py), {time.strftime('%Y-%m-%d')}.")
    print(markdown(rows, note))
    if args.json:
        args.json.write_text(json.dumps({"note": note, "rows": rows}, indent=1))
    if args.markdown:
        args.markdown.write_text(markdown(rows, note))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
