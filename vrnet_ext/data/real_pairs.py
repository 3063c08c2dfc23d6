"""Real scan pairs with ground truth (a ``real_pairs/`` folder: ``MANIFEST.tsv``, ``clouds/*.npy``,
``gt/*.txt``; see ../shared/data/scenes/README.md) as training pairs of the scene model.

:data:`VALIDATION_PAIRS` fixes which pairs training never sees: every third 3DMatch / 3DLoMatch
pair of the manifest's order and the KITTI pairs of sequences 01 and 02. A model is selected on
those; the rest (:func:`split`) are its training pairs, named in its model card.

A training pair (:meth:`RealPairProvider.__call__`) turns each scan by its own random rotation
about its sensor (the origin) and voxel-downsamples it on its own randomly shifted grid, as the
self-supervised views of :mod:`vrnet_ext.data.scans` do; the ground truth follows the turns.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vrnet_ext.data.scans import ScanPair, synthetic_pair, view
from vrnet_ext.geometry.features import describe
from vrnet_ext.geometry.io import read_points, read_transform

MAX_MANIFEST_ROWS = 10_000
MANIFEST_COLUMNS = ("pair_id", "source_file", "target_file", "gt_file", "kind")
SUBSETS = {"indoor-3DMatch": "3DMatch", "indoor-3DLoMatch": "3DLoMatch", "outdoor-lidar-kitti": "KITTI"}
# A registration succeeds below these (rotation error in degrees, translation error in metres): the
# registration literature's thresholds for indoor (3DMatch) and outdoor (KITTI) scans.
SUCCESS_THRESHOLDS = {"indoor": (15.0, 0.30), "outdoor": (5.0, 2.0)}


@dataclass(frozen=True)
class RealPair:
    """One manifest row: files, kind (``indoor-3DMatch``, ``indoor-3DLoMatch``, ``outdoor-lidar-kitti``), overlap."""

    pair_id: str
    source: Path
    target: Path
    gt: Path
    kind: str
    overlap: float

    @property
    def outdoor(self) -> bool:
        return self.kind.startswith("outdoor")

    @property
    def subset(self) -> str:
        """3DMatch, 3DLoMatch or KITTI (the kind itself for any other)."""
        return SUBSETS.get(self.kind, self.kind)

    def registered(self, rotation_error_deg: float, translation_error: float) -> bool:
        """Whether an estimate with these errors counts as a success (:data:`SUCCESS_THRESHOLDS`)."""
        max_re, max_te = SUCCESS_THRESHOLDS["outdoor" if self.outdoor else "indoor"]
        return rotation_error_deg < max_re and translation_error < max_te


def read_manifest(folder: str | Path) -> list[RealPair]:
    """The pairs listed in ``folder``/MANIFEST.tsv (tab-separated, a header naming at least
    :data:`MANIFEST_COLUMNS`), in file order. Paths are relative to ``folder``."""
    folder = Path(folder)
    manifest = folder / "MANIFEST.tsv"
    if not manifest.is_file():
        raise FileNotFoundError(f"{manifest}: no such file (a real_pairs folder holds MANIFEST.tsv)")
    pairs = []
    with manifest.open(newline="") as f:
        reader = csv.DictReader(f, delimiter="\t")
        missing = [c for c in MANIFEST_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{manifest}: the header lacks the columns {missing}")
        for row in reader:
            if len(pairs) >= MAX_MANIFEST_ROWS:
                raise ValueError(f"{manifest}: more than {MAX_MANIFEST_ROWS} pairs")
            try:
                overlap = float(row.get("overlap_frac") or "nan")
            except ValueError:
                raise ValueError(f"{manifest}: pair {row['pair_id']!r} has overlap_frac {row['overlap_frac']!r}, "
                                 f"not a number") from None
            pairs.append(RealPair(row["pair_id"], folder / row["source_file"], folder / row["target_file"],
                                  folder / row["gt_file"], row["kind"], overlap))
    return pairs


def _is_validation(pair: RealPair, index_among_indoor: int) -> bool:
    if pair.outdoor:
        return not pair.pair_id.startswith("kitti00")
    return index_among_indoor % 3 == 2


def split(pairs: list[RealPair]) -> tuple[list[RealPair], list[RealPair]]:
    """(training pairs, validation pairs) by the rule of :data:`VALIDATION_PAIRS`."""
    training, validation, indoor = [], [], 0
    for pair in pairs:
        chosen = _is_validation(pair, indoor)
        indoor += not pair.outdoor
        (validation if chosen else training).append(pair)
    return training, validation


VALIDATION_PAIRS = "every third indoor pair of the manifest (the 3rd, 6th, ...) and the KITTI pairs outside sequence 00"


@dataclass
class RealPairProvider:
    """Training pairs for :func:`vrnet_ext.learning.scene_training.train_scene_model` from real pairs:
    called with a pair id (the scans dict maps each id to its source cloud), it returns that pair
    with both scans turned and resampled (module docstring), or, with probability ``synthetic_share``,
    a self-supervised pair cut from the source scan alone; called with a name in ``self_supervised``
    (a single scan of the same run), always the latter."""

    pairs: list[RealPair]
    synthetic_share: float = 0.5
    self_supervised: set[str] = field(default_factory=set)
    _targets: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    _truths: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 <= self.synthetic_share <= 1.0:
            raise ValueError(f"synthetic_share must be in [0, 1], got {self.synthetic_share}")

    def scans(self) -> dict[str, np.ndarray]:
        """pair id -> source cloud (N, 3) float64, for ``train_scene_model``'s scans argument."""
        return {pair.pair_id: read_points(pair.source).astype(np.float64) for pair in self.pairs}

    def _target(self, pair: RealPair) -> tuple[np.ndarray, np.ndarray]:
        if pair.pair_id not in self._targets:
            self._targets[pair.pair_id] = read_points(pair.target).astype(np.float64)
            self._truths[pair.pair_id] = read_transform(pair.gt)
        return self._targets[pair.pair_id], self._truths[pair.pair_id]

    def __call__(self, name: str, source: np.ndarray, voxel: float, rng: np.random.Generator) -> ScanPair:
        from scipy.spatial.transform import Rotation  # training only

        if name in self.self_supervised or rng.uniform() < self.synthetic_share:
            return synthetic_pair(source, voxel, rng)
        pair = next(p for p in self.pairs if p.pair_id == name)
        target, T_target_source = self._target(pair)
        turn_src, turn_tgt = (Rotation.random(random_state=rng).as_matrix() for _ in range(2))
        size = voxel * rng.uniform(0.8, 1.25)
        src_view = describe(view(source, turn_src, size, rng), size)
        tgt_view = describe(view(target, turn_tgt, size, rng), size)
        T = np.eye(4)
        T[:3, :3] = turn_tgt @ T_target_source[:3, :3] @ turn_src.T
        T[:3, 3] = turn_tgt @ T_target_source[:3, 3]
        return ScanPair(src_view, tgt_view, T)
