"""Where a chain of warm-started ``vrnet train`` runs began and what it has cost.

A run started with ``--features-from`` (else ``--walk-from``) records its :class:`Lineage` in every
checkpoint it writes, read when it starts: the shipped model (or run from scratch) the chain began
from, the seconds of the runs between, and what that shipped model's own card said then. A model
card built from a run (:func:`vrnet_ext.learning.export.training_facts`) reads it back, so replacing
a shipped file later cannot change what an earlier start counted. Run checkpoints written before
runs recorded it are followed back through their ``features_from`` / ``walk_from`` paths as they
are now.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

from vrnet_ext.model.checkpoints import read_checkpoint
from vrnet_ext.model.pretrained import FORMAT, card_runs_seconds

MAX_LINEAGE = 16  # run checkpoints followed back by path before a shipped model or a run from scratch


@dataclass(frozen=True)
class Lineage:
    """``starting_point``: the shipped model's name (its file's stem), ``None`` for a chain begun
    from scratch, or the path of a start that no longer exists; ``seconds``: wall time of the runs
    after the starting point; ``start_training``: ``{"starting_point", "runs_seconds"}`` of the
    starting point's card when the chain began (``None`` when not recorded)."""

    starting_point: str | None
    seconds: float
    start_training: dict | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: object, source: str) -> "Lineage":
        """A lineage record read from an untrusted checkpoint; ValueError naming ``source`` when malformed."""
        problem = f"{source}: malformed 'lineage' record"
        if not isinstance(values, dict) or set(values) != {"starting_point", "seconds", "start_training"}:
            raise ValueError(problem)
        start, seconds, before = values["starting_point"], values["seconds"], values["start_training"]
        if not (start is None or isinstance(start, str)) or not _is_seconds(seconds):
            raise ValueError(problem)
        if before is not None:
            if not isinstance(before, dict) or set(before) - {"starting_point", "runs_seconds"}:
                raise ValueError(problem)
            if not (before.get("starting_point") is None or isinstance(before.get("starting_point"), str)) \
                    or not (before.get("runs_seconds") is None or _is_seconds(before["runs_seconds"])):
                raise ValueError(problem)
        return cls(start, float(seconds), before)


def _is_seconds(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0


def run_seconds(state: dict) -> float:
    """A run checkpoint's own wall time in training (``train_seconds``; 0 when absent)."""
    return float(state.get("train_seconds") or 0.0)


def lineage_before(start: str | None, source: str, depth: int = 0) -> Lineage:
    """The lineage a run inherits when it starts from the checkpoint at ``start`` (``None``: from
    scratch); ``source`` names the run in the error about too long a chain. A start's malformed
    record is refused naming the start's file; a shipped start's card values that are no number of
    seconds are recorded as unknown (``None``)."""
    if not start:
        return Lineage(None, 0.0)
    if not Path(start).is_file():
        return Lineage(str(start), 0.0)
    state = read_checkpoint(start)
    if state.get("format") == FORMAT:
        training = state.get("card", {}).get("training", {}) if isinstance(state.get("card"), dict) else {}
        training = training if isinstance(training, dict) else {}
        runs = card_runs_seconds(training)
        before = {"runs_seconds": runs if _is_seconds(runs) else None}
        if "starting_point" in training and (training["starting_point"] is None
                                             or isinstance(training["starting_point"], str)):
            before["starting_point"] = training["starting_point"]
        return Lineage(Path(start).stem, 0.0, before)
    if depth >= MAX_LINEAGE:
        raise ValueError(f"{source}: more than {MAX_LINEAGE} runs of warm starts before a shipped model or a run "
                         "from scratch")
    return lineage_of(state, str(start), depth + 1)


def lineage_of(state: dict, source: str, depth: int = 0) -> Lineage:
    """A run checkpoint's lineage, its own seconds included: its record, else followed by path."""
    if "lineage" in state:
        inherited = Lineage.from_dict(state["lineage"], source)
    else:
        config = state["config"]
        inherited = lineage_before(config.get("features_from") or config.get("walk_from"), source, depth)
    return Lineage(inherited.starting_point, inherited.seconds + run_seconds(state), inherited.start_training)
