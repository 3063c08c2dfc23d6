"""Training curves a person can look at: ``vrnet plot RUN_DIR`` writes ``RUN_DIR/curves.png``."""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after selecting the file backend)
from matplotlib.ticker import MaxNLocator  # noqa: E402

from vrnet_ext.geometry.atomic import atomic_output  # noqa: E402


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
        raise FileNotFoundError(f"no metrics.jsonl in {run_dir}: is it the out_dir of a training run (`vrnet train`)?")
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
