"""How the benchmark scripts hand in their results: a Markdown table printed and optionally written
(``--markdown``), the full record as JSON (``--json``); docs/benchmarks.md is built from both."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from vrnet_ext.runtime import cpu_has_native_bf16


def write_outputs(table: str, record: dict, markdown: str | None, json_path: str | None) -> None:
    """Prints ``table``; writes it to ``markdown`` and ``record`` to ``json_path`` where given."""
    print(table)
    if markdown:
        Path(markdown).write_text(table + "\n")
    if json_path:
        Path(json_path).write_text(json.dumps(record, indent=1))
        print(f"wrote {json_path}")


def cpu_description() -> str:
    """The CPU a result was measured on, e.g. ``"x86_64, AMD EPYC, 2 cpus, no native bf16"``: the
    model name (Linux), the core count and whether it multiplies bfloat16 in hardware (speed ratios
    of the bf16 paths depend on it)."""
    name = ""
    try:
        with open("/proc/cpuinfo") as f:
            name = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    bf16 = "native bf16" if cpu_has_native_bf16() else "no native bf16"
    return ", ".join(part for part in (platform.machine(), name, f"{os.cpu_count()} cpus", bf16) if part)


def machine_and_date() -> tuple[str, str]:
    """What a run was measured on (:func:`cpu_description`, torch's version and threads) and the
    day, ISO: the stamp of a table's caption and record."""
    import datetime

    import torch

    return (f"{cpu_description()}, torch {torch.__version__}, {torch.get_num_threads()} threads",
            datetime.date.today().isoformat())
