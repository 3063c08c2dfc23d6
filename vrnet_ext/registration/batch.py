"""Many pairs in one run: :func:`register_batch` reads a manifest of pairs, registers each with
:func:`~vrnet_ext.registration.register` and writes one JSON Lines record per pair as it finishes,
so that a stopped run resumes where it stopped. Under ``torchrun`` each rank takes every
``world``-th pair and writes its own part; rank 0 merges the parts into one file in manifest order
once all ranks are done. A pair that fails (an unreadable file, too few points) gets a record with
its error; the run goes on.

Manifest: CSV / TSV with a header (columns ``source``, ``target``, optional ``gt`` and ``id``; the
real-pairs layout ``pair_id``, ``source_file``, ``target_file``, ``gt_file`` too) or JSON Lines of
objects with the same keys; relative paths are relative to the manifest's folder. The ground
truth is a 4x4 file or a 3DMatch log (:func:`~vrnet_ext.geometry.io.read_ground_truth`).
"""
from __future__ import annotations

import csv
import io
import json
import os
import statistics
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vrnet_ext.geometry.atomic import read_json_lines, write_json_lines
from vrnet_ext.geometry.io import PointCloudError, read_ground_truth, read_points
from vrnet_ext.registration.pipeline import register
from vrnet_ext.names import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION
from vrnet_ext.registration.result import is_registered, transform_errors

MAX_MANIFEST_BYTES = 1 << 26  # 64 MB: some hundred thousand pairs
COLUMNS = {"source": ("source", "source_file"), "target": ("target", "target_file"), "gt": ("gt", "gt_file"),
           "id": ("id", "pair_id")}
CACHED_SCANS = 8  # scans kept in memory: fragments that take part in several pairs are read once


@dataclass(frozen=True)
class PairTask:
    """One line of a manifest: ``index`` its position (0-based), paths resolved."""

    index: int
    id: str
    source: Path
    target: Path
    gt: Path | None = None


@dataclass(frozen=True)
class BatchOptions:
    """How :func:`register_batch` registers and judges each pair: ``register`` holds the keyword
    arguments of :func:`~vrnet_ext.registration.register` (method, global_points, icp_settings,
    seed, device, backend, max_memory, ...); a pair with ground truth counts as registered when its
    rotation error is below ``success_rotation_deg`` and its translation error below
    ``success_translation`` (the scans' unit: 15 degrees and 0.3 m are 3DMatch's)."""

    register: dict[str, Any] = field(default_factory=dict)
    success_rotation_deg: float = SUCCESS_ROTATION_DEG
    success_translation: float = SUCCESS_TRANSLATION


@dataclass(frozen=True)
class Shard:
    """Which pairs this process registers: those whose index % ``world`` == ``rank``."""

    rank: int = 0
    world: int = 1

    def takes(self, index: int) -> bool:
        return index % self.world == self.rank


def read_manifest(path: str | os.PathLike) -> list[PairTask]:
    """The pairs of a manifest (see the module), each checked to name a source and a target."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such manifest")
    if path.stat().st_size > MAX_MANIFEST_BYTES:
        raise ValueError(f"{path}: {path.stat().st_size} bytes is too large for a manifest of pairs")
    text = path.read_text(encoding="utf-8")
    if path.suffix.lower() in (".jsonl", ".json"):
        rows = []
        for number, line in enumerate(text.splitlines(), start=1):
            if line.strip():
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError as error:
                    raise ValueError(f"{path}: line {number} is not JSON ({error.msg})") from None
    else:
        delimiter = "\t" if path.suffix.lower() == ".tsv" or "\t" in text.split("\n", 1)[0] else ","
        rows = list(csv.DictReader(io.StringIO(text), delimiter=delimiter))
    tasks = []
    for index, row in enumerate(rows):
        if not isinstance(row, dict):
            raise ValueError(f"{path}: pair {index + 1} is not a record with source and target")
        values = {key: next((str(row[name]) for name in names if row.get(name) not in (None, "")), None)
                  for key, names in COLUMNS.items()}
        if values["source"] is None or values["target"] is None:
            raise ValueError(f"{path}: pair {index + 1} needs a source and a target (columns source, target)")
        resolve = (lambda name: (path.parent / name).resolve() if name is not None else None)
        tasks.append(PairTask(index, values["id"] or str(index), resolve(values["source"]), resolve(values["target"]),
                              resolve(values["gt"])))
    if not tasks:
        raise ValueError(f"{path}: no pairs")
    return tasks


def part_path(out: Path, shard: Shard) -> Path:
    """Where rank ``shard.rank`` writes its records before the merge."""
    return out.with_name(f"{out.name}.part{shard.rank}of{shard.world}")


def _parts(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f"{out.name}.part*of*"))


def done_indices(out: Path) -> set[int]:
    """The pairs that already have a record, in ``out`` or in any rank's part."""
    return {record["index"] for path in [out, *_parts(out)] for record in read_json_lines(path)}


class _Scans:
    """Scans read once and kept for the next pairs (an LRU of :data:`CACHED_SCANS`)."""

    def __init__(self) -> None:
        self._kept: OrderedDict[Path, np.ndarray] = OrderedDict()

    def __call__(self, path: Path) -> np.ndarray:
        if path in self._kept:
            self._kept.move_to_end(path)
            return self._kept[path]
        points = read_points(path)
        self._kept[path] = points
        if len(self._kept) > CACHED_SCANS:
            self._kept.popitem(last=False)
        return points


def _read_pair(scans: _Scans, task: PairTask) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | Exception:
    """The pair's scans and ground truth (None without one), or the error that stopped reading them
    (recorded with the pair by :func:`register_pair`, not raised)."""
    try:
        truth = read_ground_truth(task.gt, task.source, task.target) if task.gt is not None else None
        return scans(task.source), scans(task.target), truth
    except (PointCloudError, FileNotFoundError, ValueError) as error:
        return error


def register_pair(task: PairTask, read: tuple | Exception, options: BatchOptions) -> dict:
    """One pair's record from what :func:`_read_pair` gave (the scans and ground truth, or the error
    reading them): the result (or the error that stopped it) and, with ground truth, its errors and
    whether it counts as registered."""
    record: dict[str, Any] = {"index": task.index, "id": task.id, "source": str(task.source),
                              "target": str(task.target)}
    started = time.perf_counter()
    try:
        if isinstance(read, Exception):
            raise read
        src, tgt, truth = read
        result = register(src, tgt, **options.register)
    except (PointCloudError, FileNotFoundError, ValueError, RuntimeError) as error:
        return dict(record, error=f"{type(error).__name__}: {error}", seconds=time.perf_counter() - started)
    record.update({key: value for key, value in result.to_dict().items() if key not in ("seconds", "initial")})
    record["seconds"] = time.perf_counter() - started
    if truth is not None:
        errors = transform_errors(result.T_target_source, truth)
        record["errors"] = errors
        record["registered"] = is_registered(errors, options.success_rotation_deg, options.success_translation)
    return record


def register_batch(manifest: str | os.PathLike, out: str | os.PathLike, options: BatchOptions = BatchOptions(), *,
                   shard: Shard = Shard(), progress: bool = True) -> dict:
    """Registers the pairs of ``manifest`` that ``out`` (and the parts of an earlier run) have no
    record of yet, this process's share of them per ``shard``, appending a record per pair to its
    part as each finishes -> this process's summary (:func:`summary`). The next pair's scans are
    read while the current one registers. Merging the parts: :func:`merge`."""
    from tqdm import tqdm

    tasks, out = read_manifest(manifest), Path(out)
    done = done_indices(out)
    mine = [task for task in tasks if shard.takes(task.index) and task.index not in done]
    part = part_path(out, shard)
    write_json_lines(part, read_json_lines(part))  # drop a line a kill left unfinished
    scans, records, started = _Scans(), [], time.perf_counter()
    with ThreadPoolExecutor(max_workers=1) as reader, open(part, "a") as sink:
        pending = reader.submit(_read_pair, scans, mine[0]) if mine else None
        for position, task in enumerate(tqdm(mine, desc=f"pairs (rank {shard.rank})" if shard.world > 1 else "pairs",
                                             unit="pair", disable=not progress)):
            read = pending.result()
            pending = reader.submit(_read_pair, scans, mine[position + 1]) if position + 1 < len(mine) else None
            record = register_pair(task, read, options)
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            records.append(record)
    return summary(records, time.perf_counter() - started)


def merge(manifest: str | os.PathLike, out: str | os.PathLike) -> list[dict]:
    """Every record of ``out`` and of the ranks' parts, one per pair in manifest order, written to
    ``out`` (atomically; the parts are removed) -> the records."""
    out = Path(out)
    order = {task.index for task in read_manifest(manifest)}
    by_index = {}
    for path in [out, *_parts(out)]:
        for record in read_json_lines(path):
            if record["index"] in order:
                by_index.setdefault(record["index"], record)
    records = [by_index[index] for index in sorted(by_index)]
    write_json_lines(out, records)
    for path in _parts(out):
        path.unlink()
    return records


def summary(records: list[dict], seconds: float | None = None) -> dict:
    """Counts, failures, recall and median errors over the pairs with ground truth, pairs per second."""
    judged = [r for r in records if "registered" in r]
    result = {"pairs": len(records), "failed": sum("error" in r for r in records), "with_ground_truth": len(judged)}
    if judged:
        result["recall"] = sum(r["registered"] for r in judged) / len(judged)
        result["median_rotation_error_deg"] = statistics.median(r["errors"]["rotation_error_deg"] for r in judged)
        result["median_translation_error"] = statistics.median(r["errors"]["translation_error"] for r in judged)
    if seconds is not None and records:
        result["seconds"] = seconds
        result["pairs_per_second"] = len(records) / max(seconds, 1e-9)
    return result
