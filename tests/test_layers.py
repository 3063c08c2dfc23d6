"""The package's layout rules, checked on the import statements of every module (also those inside
functions): no import cycle between modules, and the wings depend on each other only downwards.

    ops        compiled kernels and their references: nothing of the package above them
    geometry   clouds, files, transforms, features: ops only
    nn, model  networks, checkpoints and the shipped weights: no data, no registration, no learning
    data       pair providers (ModelNet40 protocol, procedural scenes, scan views): no registration
    registration   global estimators, ICP, budgets: never learning, never data
    learning   training, losses, evaluation, export: never registration

Below them all, ``names`` (every name and default a user chooses from) imports nothing of the
package. No function is long or takes many positional parameters.
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "vrnet_ext"
WINGS = ("ops", "geometry", "nn", "model", "data", "registration", "learning")
# Modules below every wing that any wing may import (the names module imports nothing itself).
BASE = ("vrnet_ext", "vrnet_ext._extension", "vrnet_ext._lazy", "vrnet_ext.runtime", "vrnet_ext.names")
FORBIDDEN = {  # wing -> wings it must not import
    "ops": {"geometry", "nn", "model", "data", "registration", "learning"},
    "geometry": {"nn", "model", "data", "registration", "learning"},
    "nn": {"geometry", "model", "data", "registration", "learning"},
    "model": {"data", "registration", "learning"},
    "data": {"registration", "learning"},
    "registration": {"data", "learning"},
    "learning": {"registration"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The package modules ``path`` imports (``from a.b import c`` counts as a.b.c when that is a
    module, else a.b)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                base = ".".join(anchor[: len(anchor) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def import_graph() -> dict[str, set[str]]:
    paths = [p for p in PACKAGE.rglob("*.py")]
    modules = {module_name(p) for p in paths}
    return {module_name(p): imports_of(p, modules) for p in paths}


def wing(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in WINGS else None


def test_the_wings_exist():
    for name in WINGS:
        assert (PACKAGE / name / "__init__.py").is_file(), name


def test_no_import_cycle():
    graph = import_graph()
    # a package's __init__ re-exporting its own modules is not a cycle of the design
    edges = {m: {t for t in targets if not (m.startswith(t + ".") and graph.get(t) is not None)}
             for m, targets in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(module: str) -> None:
        state[module] = 1
        stack.append(module)
        for target in sorted(edges.get(module, ())):
            if state.get(target) == 1:
                cycle = stack[stack.index(target):] + [target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        stack.pop()
        state[module] = 2

    for module in sorted(edges):
        if module not in state:
            visit(module)


def test_wings_import_only_downwards():
    violations = []
    for module, targets in import_graph().items():
        own = wing(module)
        for target in targets:
            if own and wing(target) in FORBIDDEN[own]:
                violations.append(f"{module} imports {target}")
            if own and wing(target) is None and target not in BASE:
                violations.append(f"{module} imports {target}, outside the wings")
    assert not violations, "\n".join(sorted(violations))


MAX_LINES, MAX_POSITIONAL = 80, 6


def test_no_function_is_long_or_takes_many_positional_parameters():
    """No function over 80 lines; none outside ``ops/`` (whose signatures mirror the op schemas)
    with more than 6 positional parameters."""
    found = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            positional = [a for a in node.args.posonlyargs + node.args.args if a.arg not in ("self", "cls")]
            too_many = len(positional) > MAX_POSITIONAL and not relative.startswith("ops/")
            if node.end_lineno - node.lineno + 1 > MAX_LINES or too_many:
                found.add((relative, node.name))
    assert not found, sorted(found)
