"""Lazy package attributes: ``import vrnet_ext`` (and ``vrnet --help``) stays cheap; torch, h5py
and the compiled kernels load when something that needs them is first used."""
from __future__ import annotations

import importlib
from collections.abc import Callable


def lazy_attributes(package: str, exports: dict[str, str]) -> Callable[[str], object]:
    """A module-level ``__getattr__`` for ``package``: attribute ``name`` is imported on first access
    from the module ``exports[name]`` (the module itself when its last component is ``name``) and
    then cached in the package."""

    def __getattr__(name: str) -> object:
        target = exports.get(name)
        if target is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = importlib.import_module(target)
        value = module if target.rsplit(".", 1)[-1] == name else getattr(module, name)
        setattr(importlib.import_module(package), name, value)
        return value

    return __getattr__
