"""Pictures of registrations a person can look at (``vrnet register --plot``, ``vrnet demo``)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after selecting the file backend)

from vrnet_ext.geometry.atomic import atomic_output  # noqa: E402
from vrnet_ext.geometry.transforms import apply  # noqa: E402


def _save(fig, path: str | Path, dpi: int) -> Path:
    """Writes ``fig`` to ``path`` atomically and closes it."""
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path) as temporary:
        fig.savefig(temporary, dpi=dpi)
    plt.close(fig)
    return path


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
    return _save(fig, path, dpi=110)


def plot_pair(src, tgt, *, truth, vcp, rcp, estimate, path: str | Path, title: str = "") -> Path:
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
    return _save(fig, path, dpi=100)
