"""Old module paths still import, as the module at the new path, with one DeprecationWarning."""
import json
import subprocess
import sys
from pathlib import Path

import vrnet_ext
from vrnet_ext._moved import MOVED

SCRIPT = r"""
import importlib, json, sys, warnings
from vrnet_ext._moved import MOVED
out = {}
for old, new in MOVED.items():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
        again = importlib.import_module(old)
    out[old] = {"same": module is importlib.import_module(new) and again is module,
                "warnings": [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]}
print(json.dumps(out))
"""


def test_every_moved_path_imports_the_new_module_and_warns_once_naming_it():
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    for old, new in MOVED.items():
        assert result[old]["same"], old
        assert [w for w in result[old]["warnings"] if w.startswith(old)] == [
            f"{old} moved to {new}; the old path will be removed in vrnet_ext 0.3"], (old, result[old])


def test_no_moved_path_is_shadowed_by_a_real_module():
    root = Path(vrnet_ext.__file__).parent.parent
    for old in MOVED:
        path = root / Path(*old.split("."))
        assert not path.with_suffix(".py").exists() and not (path / "__init__.py").exists(), old
