"""Training curves a person can look at: ``vrnet plot RUN_DIR`` writes ``RUN_DIR/curves.png``."""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after selecting the file backend)
from matplotlib.ticker import MaxNLocator  # noqa: E402

from vrnet_ext.atomic import atomic_output  # noqa: E402
from vrnet_ext.transforms import apply  # noqa: E402

PANELS = (
    ("training loss terms (stage 1: L0; stage 2: L1-L4)", ("train_L0", "train_L1", "train_L2", "train_L3", "train_L4")),
    ("validation rotation error (deg)", ("val_RMSE(R)", "val_MAE(R)")),
    ("validation translation error", ("val_RMSE(t)", "val_MAE(t)")),
    ("Chamfer distance to the aligned source", ("val_CD(src,VCP)", "val_CD(src,RCP)", "val_CD(src,tgt)")),
)


def plot_metrics(run_dir: str | Path) -> Path:
    """Reads ``metrics.jsonl`` of a training run and writes ``curves.png`` beside it."""
    run_dir = Path(run_dir)
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"no metrics.jsonl in {run_dir}: is it a `vrnet train --out-dir`?")
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not records:
        raise ValueError(f"{path} is empty: no epoch has finished yet")
    epochs = list(range(1, len(records) + 1))
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for ax, (title, keys) in zip(axes.flat, PANELS):
        for key in keys:
            ys = [r.get(key) for r in records]
            if any(y is not None for y in ys):
                ax.plot(epochs, [float("nan") if y is None else y for y in ys], marker="o", label=key)
        stage_change = next((i for i, r in enumerate(records) if r["stage"] == 2), None)
        if stage_change:
            ax.axvline(stage_change + 0.5, color="grey", linestyle="--", linewidth=1)
        ax.set_title(title)
        ax.set_xlabel("epoch (dashed line: stage 1 -> stage 2)")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"VRNet training: {run_dir.name}")
    fig.tight_layout()
    out = run_dir / "curves.png"
    with atomic_output(out) as temporary:
        fig.savefig(temporary, dpi=110)
    plt.close(fig)
    return out


def plot_registration(src, tgt, transforms: dict, path: str | Path, max_points: int = 20000, seed: int = 0) -> Path:
    """Top and side views of the target (grey) with the source moved by each named 4x4 transform.

    src (N, 3), tgt (M, 3) numpy arrays; ``transforms`` maps a label ("initial", "final", ...) to a
    (4, 4) array. Clouds are randomly thinned to ``max_points`` for drawing.
    """
    import numpy as np

    rng = np.random.default_rng(seed)

    def thin(points):
        return points[rng.choice(len(points), max_points, replace=False)] if len(points) > max_points else points

    src, tgt = thin(src), thin(tgt)
    views = (("top view (x, y)", 0, 1), ("side view (x, z)", 0, 2))
    fig, axes = plt.subplots(len(transforms), 2, figsize=(12, 5.5 * len(transforms)), squeeze=False)
    for row, (label, T) in enumerate(transforms.items()):
        moved = apply(T, src)
        for col, (title, a, b) in enumerate(views):
            ax = axes[row][col]
            ax.scatter(tgt[:, a], tgt[:, b], s=0.2, c="0.6", label="target", rasterized=True)
            ax.scatter(moved[:, a], moved[:, b], s=0.2, c="tab:red", label=f"source ({label})", rasterized=True)
            ax.set_aspect("equal")
            ax.set_title(f"{label}: {title}")
            ax.legend(loc="upper right", markerscale=20)
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path) as temporary:
        fig.savefig(temporary, dpi=110)
    plt.close(fig)
    return path


def plot_pair(src, tgt, truth, vcp, rcp, estimate, path: str | Path, title: str = "") -> Path:
    """Three 3-D panels of one registered pair (numpy arrays, all (N, 3) but ``tgt`` (M, 3)).

    1. the input: source (red) and target (green);
    2. the correspondences in the target's frame: where the source points truly are (``truth``,
       purple), their VCPs (grey) and RCPs (blue), a red line from each VCP to its RCP (the walk);
    3. the result: the source moved by the estimate (red) over the target (green).
    """
    import numpy as np

    fig = plt.figure(figsize=(15, 5.2))
    panels = (
        ("input: source (red), target (green)", [(src, "tab:red"), (tgt, "tab:green")]),
        ("true positions (purple), VCPs (grey), RCPs (blue)", [(truth, "tab:purple"), (vcp, "0.55"), (rcp, "tab:blue")]),
        ("result: moved source (red), target (green)", [(estimate, "tab:red"), (tgt, "tab:green")]),
    )
    everything = np.concatenate([src, tgt, truth, vcp, rcp, estimate])
    low, high = everything.min(axis=0), everything.max(axis=0)
    for i, (panel_title, clouds) in enumerate(panels):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        for points, colour in clouds:
            ax.scatter(points[:, 0], points[:, 2], points[:, 1], s=2, c=colour, depthshade=False)
        if i == 1:
            moved = np.linalg.norm(rcp - vcp, axis=1) > 1e-3
            for a, b in zip(vcp[moved], rcp[moved]):
                ax.plot([a[0], b[0]], [a[2], b[2]], [a[1], b[1]], c="tab:red", linewidth=0.5)
        ax.set_xlim(low[0], high[0]); ax.set_ylim(low[2], high[2]); ax.set_zlim(low[1], high[1])
        ax.set_box_aspect(high[[0, 2, 1]] - low[[0, 2, 1]])
        ax.view_init(elev=20, azim=-60)
        ax.set_title(panel_title, fontsize=10)
        ax.set_xticklabels([]); ax.set_yticklabels([]); ax.set_zticklabels([])
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path) as temporary:
        fig.savefig(temporary, dpi=100)
    plt.close(fig)
    return path
