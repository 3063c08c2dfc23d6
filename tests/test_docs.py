"""Every code block of README.md and docs/*.md runs (Python in a fresh interpreter, shell with
bash), unless the line before it says ``<!-- not run: REASON -->``; the README stays short."""
from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"(?P<before>[^\n]*)\n```(?P<lang>\w*)\n(?P<code>.*?)\n```", re.S)
NOT_RUN = re.compile(r"<!-- not run: (?P<reason>.+?) -->")


def blocks():
    for path in DOCUMENTS:
        text = path.read_text()
        for number, match in enumerate(FENCE.finditer(text)):
            line = text[: match.start("code")].count("\n")
            skip = NOT_RUN.search(match["before"])
            yield pytest.param(path, match["lang"], match["code"], skip["reason"] if skip else None,
                               id=f"{path.name}:{line}")


def scans(folder: Path) -> None:
    """source.npy / target.npy for the README's example: a room corner seen from two places."""
    rng = np.random.default_rng(0)
    target = np.concatenate([rng.uniform(-1, 1, (4000, 3)) * [4.0, 3.0, 0.2] + [0, 0, 1],
                             rng.uniform(-1, 1, (2000, 3)) * [4.0, 0.05, 1.0] + [0, 3, 1],
                             rng.uniform(-1, 1, (2000, 3)) * [0.05, 3.0, 1.0] + [4, 0, 1]])
    angle = np.radians(20)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    np.save(folder / "target.npy", target)
    np.save(folder / "source.npy", (target - [0.3, 0.1, 0.0]) @ R)


@pytest.mark.parametrize("path, lang, code, not_run", list(blocks()))
def test_code_block_runs(path, lang, code, not_run, tmp_path):
    if not_run is not None:
        assert len(not_run.strip()) > 5, "say why the block is not run"
        pytest.skip(f"marked not run: {not_run}")
    scans(tmp_path)
    if lang == "python":
        command = [sys.executable, "-c", code]
    elif lang in ("bash", "sh", "shell"):
        command = ["bash", "-e", "-c", code]
    else:
        pytest.fail(f"{path.name}: a ```{lang} block is neither runnable nor marked <!-- not run: reason -->")
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"{path.name} block failed:\n{code}\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}"


def test_readme_is_short_and_has_no_history():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert "session" not in text.lower()
    for link in re.findall(r"\]\(([^)#]+)\)", text):
        if not link.startswith("http"):
            assert (ROOT / link).exists(), f"README links to a missing {link}"


def test_readme_results_table_is_rendered_from_its_json():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from results_table import render

    text = (ROOT / "README.md").read_text()
    (link,) = set(re.findall(r"\((benchmarks/results/[^)]+/real_pairs)\.md\)", text))
    record = json.loads((ROOT / f"{link}.json").read_text())
    assert render(record) in text


def test_readme_modelnet40_grid_is_rendered_from_its_json():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from modelnet40_summary import grid

    text = (ROOT / "README.md").read_text()
    (link,) = set(re.findall(r"\((benchmarks/results/[^)]+/modelnet40_summary)\.md\)", text))
    assert grid(json.loads((ROOT / f"{link}.json").read_text())["cells"]) in text


def test_benchmarks_page_is_rendered_from_the_results_folder():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from benchmarks_page import render

    assert (ROOT / "docs" / "benchmarks.md").read_text() == render(), \
        "regenerate: python benchmarks/benchmarks_page.py > docs/benchmarks.md"


def test_ops_reference_covers_every_op():
    """Every public op has a signature line and a table row in docs/ops.md, and a docstring."""
    from vrnet_ext import ops

    import inspect

    text = (ROOT / "docs" / "ops.md").read_text()
    for name in ops.__all__:
        assert f"ops.{name}(" in text and f"| `{name}` |" in text, f"docs/ops.md does not describe {name}"
        assert (getattr(ops, name).__doc__ or "").strip(), f"ops.{name} has no docstring"
    # the signature lines name the op's real parameters, in order, with its real defaults
    for line in re.findall(r"ops\.\w+\(.*", text):
        call = line.split("#")[0].strip()
        if "..." in call or "<name>" in call:
            continue
        node = ast.parse(call, mode="eval").body
        name = node.func.attr
        parameters = list(inspect.signature(getattr(ops, name)).parameters.values())
        assert [a.id for a in node.args] == [p.name for p in parameters[:len(node.args)]], (name, call)
        for keyword in node.keywords:
            default = next(p.default for p in parameters if p.name == keyword.arg)
            assert ast.literal_eval(keyword.value) == default, (name, keyword.arg)
