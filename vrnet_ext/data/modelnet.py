"""ModelNet40 registration pairs (HDF5 in the official PointNet layout: ``data``, ``label``)."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from vrnet_ext.data.protocol import PairSpec, make_pair
from vrnet_ext.names import DEFAULT_SETTING, DEFAULT_SPLIT, SPLITS

PARTITIONS = ("train", "val", "test")
_FILES = {"train": "modelnet40_1024_train.h5", "test": "modelnet40_1024_test.h5"}


def written_root() -> Path:
    """Where ``vrnet data modelnet40`` writes by default: ``$VRNET_DATA/modelnet40`` when set, else
    ``$XDG_DATA_HOME/vrnet_ext/modelnet40`` (``~/.local/share/vrnet_ext/modelnet40``)."""
    env = os.environ.get("VRNET_DATA")
    if env:
        return Path(env) / "modelnet40"
    return Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share") / "vrnet_ext" / "modelnet40"


def default_root() -> Path:
    """``$VRNET_DATA/modelnet40`` when set; else ``../shared/data/modelnet40`` beside a source
    checkout when that exists; else where ``vrnet data modelnet40`` writes (:func:`written_root`)."""
    beside = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "modelnet40"
    if not os.environ.get("VRNET_DATA") and beside.is_dir():
        return beside
    return written_root()


def load_h5(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(points (S, P, 3) float32, labels (S,) int64) from one or more PointNet-layout HDF5 files."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"ModelNet40 file not found: {path} (make it from the public release with `vrnet "
                                f"data modelnet40`, docs/data.md; or set data_dir to the folder holding it, or "
                                f"VRNET_DATA to the data folder that holds modelnet40/)")
    try:
        with h5py.File(path, "r") as f:
            missing = {"data", "label"} - set(f.keys())
            if missing:
                raise ValueError(f"{path} lacks dataset(s) {sorted(missing)}: not a PointNet-layout HDF5 file")
            points = np.asarray(f["data"][:], dtype=np.float32)
            labels = np.asarray(f["label"][:]).reshape(-1).astype(np.int64)
    except OSError as exc:
        raise ValueError(f"cannot read {path} as HDF5: {exc}") from exc
    if points.ndim != 3 or points.shape[2] != 3 or points.shape[0] != labels.shape[0]:
        raise ValueError(f"{path}: expected data (S, P, 3) and label (S,), got {points.shape} and {labels.shape}")
    return points, labels


def spread_positions(count: int, wanted: int) -> np.ndarray:
    """``min(wanted, count)`` of the positions 0 .. count - 1, evenly spaced from 0: a sample of a list
    sorted by class holds every class in proportion (ModelNet40's files list their shapes by class,
    so their first 100 test shapes are all airplanes)."""
    if wanted >= count:
        return np.arange(count)
    return np.arange(wanted) * count // wanted


# The val / train division of TRAIN is drawn with this seed in every run, whatever the run's own
# seed: a model warm-started from another run never trains on that run's validation shapes.
HOLDOUT_SEED = 1234


class ModelNet40Pairs(Dataset):
    """Registration pairs from ModelNet40 following DCP / PRNet / VRNet.

    Args:
        root: folder with ``modelnet40_1024_{train,test}.h5`` (default: :func:`default_root`).
        partition: ``"train"``, ``"val"`` (held out of TRAIN, for model selection) or ``"test"``.
        setting: ``"CO"``, ``"PV"``, ``"RS"`` or ``"PV+RS"``.
        split: ``"UPC"`` (official), ``"UC"`` (train labels 0-19, test 20-39) or ``"ND"`` (UPC + noise).
        val_fraction: share of the train shapes held out as ``val`` (drawn with :data:`HOLDOUT_SEED`,
            disjoint from train).
        classes: optional subset of labels to keep (after the split's own filter).
        max_items: keep at most this many shapes (after filtering), for small runs and samples: spread
            evenly over the list (:func:`spread_positions`), whose files hold the shapes class by class.
        seed: seed of the pairs. Test and val pairs are fixed per (seed, item); train pairs vary
            with :meth:`set_epoch` and are reproducible from (seed, epoch, index).
        spec: :class:`PairSpec` overrides (point counts, angles).

    Items are dicts of tensors: ``src (N, 3)``, ``tgt (M, 3)``, ``rotation (3, 3)``,
    ``translation (3,)``, ``euler (3,)`` (z, y, x degrees), ``gt_idx (N,)`` int64 (-1 = no match),
    ``label`` int64.
    """

    def __init__(self, root: str | os.PathLike | None = None, *, partition: str = "train",
                 setting: str = DEFAULT_SETTING, split: str = DEFAULT_SPLIT, val_fraction: float = 0.1, classes: list[int] | None = None,
                 max_items: int | None = None, seed: int = 1234, spec: PairSpec | None = None) -> None:
        if partition not in PARTITIONS:
            raise ValueError(f"partition must be one of {PARTITIONS}, got {partition!r}")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        self.root = Path(root) if root is not None else default_root()
        self.partition, self.split, self.seed = partition, split, seed
        self.spec = spec or PairSpec(setting=setting)
        self.spec.setting = setting
        self.spec.noise = split == "ND"
        self.spec.__post_init__()
        points, labels = load_h5(self.root / _FILES["test" if partition == "test" else "train"])
        keep = np.arange(points.shape[0])
        if partition != "test":
            order = np.random.default_rng(HOLDOUT_SEED).permutation(points.shape[0])
            n_val = int(round(val_fraction * points.shape[0]))
            keep = np.sort(order[:n_val] if partition == "val" else order[n_val:])
        if split == "UC":
            wanted = labels[keep] >= 20 if partition == "test" else labels[keep] < 20
            keep = keep[wanted]
        if classes is not None:
            keep = keep[np.isin(labels[keep], classes)]
        if max_items is not None:
            keep = keep[spread_positions(keep.size, max_items)]
        if keep.size == 0:
            raise ValueError(f"no shapes left for partition={partition} split={split} classes={classes}")
        self.points = points[keep]
        self.points.setflags(write=False)
        self.labels = labels[keep]
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Selects the random pairs of a training epoch (ignored for val/test, which are fixed)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return self.points.shape[0]

    def __getitem__(self, index: int) -> dict:
        stream = [self.seed, index] if self.partition != "train" else [self.seed, self.epoch, index]
        rng = np.random.default_rng(stream)
        pair = make_pair(self.points[index], self.spec, rng)
        item = {key: torch.from_numpy(np.ascontiguousarray(value)) for key, value in pair.items()}
        item["label"] = torch.tensor(int(self.labels[index]))
        return item
