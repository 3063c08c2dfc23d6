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


FLAT = 0.15  # a view flatter than this (height / width: the side of a LiDAR scan) is stretched vertically
STRETCHED = 0.3  # to this height / width


def registration_figure(src, tgt, transforms: dict, *, title: str = "", max_points: int = 20000, seed: int = 0):
    """A figure of one row per named 4x4 transform (e.g. "input (no motion)", "result", "ground
    truth"), each with a top view (x, y) and a side view (x, z) of the target (orange) and the source
    moved by it (blue), both half transparent so that neither hides the other; ``title`` above all.
    src (N, 3), tgt (M, 3) numpy arrays, randomly thinned to ``max_points`` for drawing. Each view is
    cropped to where the clouds are (0.5-99.5 percentiles: a stray point does not shrink the scene
    to a corner) and sized to its shape; a flat view (the side of a LiDAR scan) is stretched
    vertically, and its title says by how much."""
    import numpy as np

    rng = np.random.default_rng(seed)

    def thin(points):
        return points[rng.choice(len(points), max_points, replace=False)] if len(points) > max_points else points

    src, tgt = thin(src), thin(tgt)
    moved = {label: apply(T, src) for label, T in transforms.items()}
    shown = np.concatenate([tgt, *moved.values()])
    low, high = np.percentile(shown, 0.5, axis=0), np.percentile(shown, 99.5, axis=0)
    extent = np.maximum(high - low, 1e-9)
    margin = 0.03 * extent
    views = [("top view (x, y)", 0, 1), ("side view (x, z)", 0, 2)]
    shapes = [extent[b] / extent[a] for _, a, b in views]  # height / width of each view
    stretch = [STRETCHED / shape if shape < FLAT else 1.0 for shape in shapes]
    drawn = [min(3.0, shape * factor) for shape, factor in zip(shapes, stretch)]
    widths = [1.0 / shape for shape in drawn]
    row_height = 12.0 / sum(widths)
    fig, axes = plt.subplots(len(transforms), 2, figsize=(13, 0.8 + (row_height + 0.7) * len(transforms)),
                             squeeze=False, gridspec_kw={"width_ratios": widths})
    for row, (label, points) in enumerate(moved.items()):
        for col, (view, a, b) in enumerate(views):
            ax = axes[row][col]
            ax.scatter(points[:, a], points[:, b], s=0.3, c="tab:blue", alpha=0.45, label="source", rasterized=True)
            ax.scatter(tgt[:, a], tgt[:, b], s=0.3, c="tab:orange", alpha=0.45, label="target", rasterized=True)
            ax.set_xlim(low[a] - margin[a], high[a] + margin[a])
            ax.set_ylim(low[b] - margin[b], high[b] + margin[b])
            ax.set_aspect(stretch[col])
            note = f", height stretched x{stretch[col]:.1f}" if stretch[col] > 1.0 else ""
            ax.set_title(f"{label}: {view}{note}")
    fig.legend(*axes[0][0].get_legend_handles_labels(), loc="upper right", markerscale=15)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_registration(src, tgt, transforms: dict, path: str | Path, *, title: str = "", max_points: int = 20000,
                      seed: int = 0) -> Path:
    """:func:`registration_figure` written to ``path`` (a picture format by its suffix)."""
    return _save(registration_figure(src, tgt, transforms, title=title, max_points=max_points, seed=seed), path,
                 dpi=110)


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


def scene_figure(scans: list, poses, names: list[str], edges: list, *, title: str = "",
                 points_per_scan: int = 4000, seed: int = 0):
    """A top view of a registered scene (``vrnet register-scene --plot``): each placed scan's points
    (``scans``: (N_i, 3) arrays, None for a scan not placed) moved by its pose (``poses`` (P, 4, 4))
    in its own colour, the scan origins joined in scan order (the trajectory), and the pairwise
    edges: grey where the pose graph kept them, red dashed where it dropped them (``edges``: objects
    with ``source``, ``target``, ``kept``). "Top" is the direction the scene is thinnest in (its
    least principal axis), so rooms, floors and LiDAR sweeps are seen from above whatever their frame."""
    import numpy as np

    rng = np.random.default_rng(seed)
    placed = [i for i, scan in enumerate(scans) if scan is not None]
    moved = {}
    for i in placed:
        picked = scans[i][rng.choice(len(scans[i]), min(points_per_scan, len(scans[i])), replace=False)]
        moved[i] = apply(poses[i], picked)
    every = np.concatenate(list(moved.values()))
    centre = every.mean(axis=0)
    _, _, axes_rows = np.linalg.svd(every - centre, full_matrices=False)
    plane = axes_rows[:2].T  # the two widest directions: (3, 2)

    def top(points):
        return (np.asarray(points) - centre) @ plane

    origins = {i: top(poses[i][None, :3, 3])[0] for i in placed}
    fig, ax = plt.subplots(figsize=(9, 9))
    colours = plt.get_cmap("tab20")
    for k, i in enumerate(placed):
        flat = top(moved[i])
        ax.scatter(flat[:, 0], flat[:, 1], s=0.4, color=colours(k % 20), alpha=0.5, rasterized=True)
    for edge in edges:
        if edge.source in origins and edge.target in origins:
            a, b = origins[edge.source], origins[edge.target]
            ax.plot([a[0], b[0]], [a[1], b[1]], color="0.55" if edge.kept else "tab:red",
                    linestyle="-" if edge.kept else "--", linewidth=0.6 if edge.kept else 1.0, zorder=2)
    path = np.array([origins[i] for i in placed])
    ax.plot(path[:, 0], path[:, 1], "-o", color="black", markersize=4, linewidth=1.2, zorder=3)
    for k, i in enumerate(placed):
        ax.annotate(names[i], origins[i], fontsize=7, color=colours(k % 20), xytext=(3, 3), textcoords="offset points")
    dropped = sum(not edge.kept for edge in edges)
    ax.plot([], [], color="0.55", label="pair kept")
    ax.plot([], [], color="tab:red", linestyle="--", label=f"pair dropped ({dropped})")
    ax.plot([], [], "-o", color="black", markersize=4, label="scan origins, in order")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_title(title or f"{len(placed)} scans, top view")
    fig.tight_layout()
    return fig


def plot_scene(scans: list, poses, names: list[str], edges: list, path: str | Path, *, title: str = "") -> Path:
    """:func:`scene_figure` written to ``path`` (a picture format by its suffix)."""
    return _save(scene_figure(scans, poses, names, edges, title=title), path, dpi=110)
