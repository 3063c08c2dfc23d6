"""The ModelNet40 files ``vrnet eval`` / ``vrnet train`` read, made from the public release of the
PointNet authors (``modelnet40_ply_hdf5_2048``: ``ply_data_train*.h5`` / ``ply_data_test*.h5``,
each with ``data`` (S, 2048, 3) and ``label`` (S, 1), and ``shape_names.txt``), as a folder or as
its zip archive. Each shape keeps its first 1024 points (the protocol of DCP, PRNet and VRNet),
centred and scaled to the unit sphere as the release already is; the official train / test split
is kept. Untrusted input: every file is checked (datasets present, shapes, sizes bounded) before
its points are read."""
from __future__ import annotations

import io
import re
import zipfile
from pathlib import Path

import h5py
import numpy as np

from vrnet_ext.geometry.atomic import atomic_output, write_text_atomically

POINTS = 1024
MAX_SHAPES = 100_000  # the release holds 12,311; a header asking for more is not ModelNet40
_PART = re.compile(r"ply_data_(train|test)(\d+)\.h5$")


def _parts(source: Path) -> dict[str, list[tuple[str, bytes | Path]]]:
    """The release's HDF5 parts by split, in numeric order: (name, path or the file's bytes in a zip)."""
    found: dict[str, list[tuple[int, str, bytes | Path]]] = {"train": [], "test": []}
    if source.is_dir():
        for path in source.rglob("ply_data_*.h5"):
            match = _PART.search(path.name)
            if match:
                found[match.group(1)].append((int(match.group(2)), path.name, path))
    elif zipfile.is_zipfile(source):
        with zipfile.ZipFile(source) as archive:
            for info in archive.infolist():
                match = _PART.search(info.filename)
                if match:
                    found[match.group(1)].append((int(match.group(2)), info.filename, archive.read(info)))
    else:
        raise ValueError(f"{source}: not a folder or a zip archive of the modelnet40_ply_hdf5_2048 release")
    if not found["train"] or not found["test"]:
        raise ValueError(f"{source}: no ply_data_train*.h5 and ply_data_test*.h5 files (the modelnet40_ply_hdf5_2048 "
                         f"release of PointNet)")
    return {split: [(name, content) for _, name, content in sorted(parts)] for split, parts in found.items()}


def _read_part(name: str, content: bytes | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (S, 1024, 3) float32, labels (S, 1) uint8) of one release file."""
    try:
        with h5py.File(io.BytesIO(content) if isinstance(content, bytes) else content, "r") as f:
            if not {"data", "label"} <= set(f.keys()):
                raise ValueError(f"{name}: lacks 'data' or 'label' (not a PointNet-layout HDF5 file)")
            data, label = f["data"], f["label"]
            if data.ndim != 3 or data.shape[2] != 3 or data.shape[1] < POINTS or not 0 < data.shape[0] <= MAX_SHAPES:
                raise ValueError(f"{name}: 'data' must be (shapes, >= {POINTS}, 3), got {data.shape}")
            if label.shape[0] != data.shape[0] or label.size != data.shape[0]:
                raise ValueError(f"{name}: 'label' must hold one class per shape, got {label.shape}")
            points = np.asarray(data[:, :POINTS, :], dtype=np.float32)
            labels = np.asarray(label[:]).reshape(-1, 1)
    except OSError as error:
        raise ValueError(f"{name}: cannot read it as HDF5 ({error})") from None
    if not np.isfinite(points).all() or labels.min() < 0 or labels.max() >= 40:
        raise ValueError(f"{name}: points must be finite and labels in 0-39")
    return points, labels.astype(np.uint8)


def convert_modelnet40(source: str | Path, out_dir: str | Path) -> dict[str, int]:
    """Writes ``modelnet40_1024_train.h5`` and ``modelnet40_1024_test.h5`` into ``out_dir`` from the
    release at ``source`` (folder or zip) -> the number of shapes of each split."""
    source, out_dir = Path(source), Path(out_dir)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such file or folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    counts = {}
    for split, parts in _parts(source).items():
        read = [_read_part(name, content) for name, content in parts]
        points, labels = np.concatenate([p for p, _ in read]), np.concatenate([lab for _, lab in read])
        with atomic_output(out_dir / f"modelnet40_{POINTS}_{split}.h5") as temporary:
            with h5py.File(temporary, "w") as f:
                f.create_dataset("data", data=points)
                f.create_dataset("label", data=labels)
        counts[split] = len(points)
    write_text_atomically(out_dir / "README.md",
                          f"ModelNet40, {POINTS} points per shape (the first {POINTS} of each shape of {source.name}, "
                          f"the modelnet40_ply_hdf5_2048 release), written by `vrnet data modelnet40`: "
                          f"{counts['train']} train and {counts['test']} test shapes.\n")
    return counts
