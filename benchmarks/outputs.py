"""How the benchmark scripts hand in their results: a Markdown table printed and optionally written
(``--markdown``), the full record as JSON (``--json``); docs/benchmarks.md is built from both."""
from __future__ import annotations

import json
from pathlib import Path


def write_outputs(table: str, record: dict, markdown: str | None, json_path: str | None) -> None:
    """Prints ``table``; writes it to ``markdown`` and ``record`` to ``json_path`` where given."""
    print(table)
    if markdown:
        Path(markdown).write_text(table + "\n")
    if json_path:
        Path(json_path).write_text(json.dumps(record, indent=1))
        print(f"wrote {json_path}")
