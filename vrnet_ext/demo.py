"""``vrnet demo``: register pairs with a shipped model, no data or arguments needed.

Pairs follow the paper's protocol (PairSpec: 1024-point shapes, R = Rx Ry Rz with each angle in
[0, 45) degrees, t in [-0.5, 0.5]^3, both clouds cut to the 768 points nearest a far point). The
shapes are procedural chairs (:mod:`vrnet_ext.data.procedural`), or with ``data_dir`` ModelNet40
test shapes spread over the whole test file.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from vrnet_ext.data import PairSpec, load_h5, make_pair
from vrnet_ext.data.procedural import chair
from vrnet_ext.geometry.metrics import rotation_error_deg, translation_error
from vrnet_ext.geometry.transforms import move
from vrnet_ext.model import VRNet
from vrnet_ext.ops import kabsch


def demo_shapes(count: int, seed: int, data_dir: str | Path | None) -> tuple[list[np.ndarray], str]:
    """(``count`` (1024, 3) shapes, a description of where they came from)."""
    if data_dir is None:
        rng = np.random.default_rng(seed)
        return [chair(rng) for _ in range(count)], "procedural chairs"
    path = Path(data_dir) / "modelnet40_1024_test.h5"
    points, _ = load_h5(path)
    picks = np.linspace(0, len(points) - 1, count).round().astype(int)
    return [points[i] for i in picks], f"ModelNet40 test shapes {picks.tolist()} of {path}"


def run_demo(model: VRNet, pairs: int = 4, seed: int = 0, data_dir: str | Path | None = None,
             plot_path: str | Path | None = "demo.png") -> dict:
    """Registers ``pairs`` pairs one at a time and returns the errors, times and plot path."""
    if pairs < 1:
        raise ValueError(f"pairs must be >= 1, got {pairs}")
    shapes, origin = demo_shapes(pairs, seed, data_dir)
    spec = PairSpec(setting="PV")
    rows, first = [], None
    with torch.no_grad():
        for i, shape in enumerate(shapes):
            pair = make_pair(shape, spec, np.random.default_rng([seed, i]))
            src, tgt = torch.from_numpy(pair["src"])[None], torch.from_numpy(pair["tgt"])[None]
            R_gt, t_gt = torch.from_numpy(pair["rotation"])[None], torch.from_numpy(pair["translation"])[None]
            if i == 0:
                model(src, tgt)  # warm-up: the first call allocates
            started = time.perf_counter()
            out = model(src, tgt)
            seconds = time.perf_counter() - started
            R_vcp, _ = kabsch(src, out.vcp)
            rows.append({"pair": i, "rotation_error_deg": float(rotation_error_deg(out.rotation, R_gt)),
                         "translation_error": float(translation_error(out.translation, t_gt)),
                         "vcp_only_rotation_error_deg": float(rotation_error_deg(R_vcp, R_gt)),
                         "true_angle_deg": float(rotation_error_deg(torch.eye(3)[None], R_gt)),
                         "seconds": seconds})
            if i == 0:
                first = (pair, out)
    result = {"shapes": origin, "pairs": rows,
              "mean_rotation_error_deg": float(np.mean([r["rotation_error_deg"] for r in rows])),
              "mean_translation_error": float(np.mean([r["translation_error"] for r in rows])),
              "median_seconds_per_pair": float(np.median([r["seconds"] for r in rows]))}
    if plot_path is not None:
        from vrnet_ext.plots import plot_pair

        pair, out = first
        R_gt, t_gt = pair["rotation"], pair["translation"]
        R, t = out.rotation[0].numpy(), out.translation[0].numpy()
        row = rows[0]
        title = (f"pair 0 ({origin.split(' of ')[0]}): true motion {row['true_angle_deg']:.1f} deg; "
                 f"error {row['rotation_error_deg']:.2f} deg / {row['translation_error']:.3f}")
        result["plot"] = str(plot_pair(pair["src"], pair["tgt"], truth=move(pair["src"], R_gt, t_gt),
                                       vcp=out.vcp[0].numpy(), rcp=out.rcp[0].numpy(), estimate=move(pair["src"], R, t),
                                       path=plot_path, title=title))
    return result


__all__ = ["demo_shapes", "run_demo"]
