"""Module paths that moved, kept importable for at least one minor version: importing an old path
returns the module at its new path (the same object) and warns once with a DeprecationWarning
that names the new path. The list of moves is written once, here; the CHANGELOG says when each
path will go."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {  # old path -> new path
    "vrnet_ext.io": "vrnet_ext.geometry.io",
    "vrnet_ext.atomic": "vrnet_ext.geometry.atomic",
    "vrnet_ext.transforms": "vrnet_ext.geometry.transforms",
    "vrnet_ext.preprocessing": "vrnet_ext.geometry.preprocessing",
    "vrnet_ext.metrics": "vrnet_ext.geometry.metrics",
    "vrnet_ext.geometry.robust": "vrnet_ext.ops.kabsch",
    "vrnet_ext.checkpoints": "vrnet_ext.model.checkpoints",
    "vrnet_ext.pretrained": "vrnet_ext.model.pretrained",
    "vrnet_ext.evaluate": "vrnet_ext.learning.evaluate",
    "vrnet_ext.losses": "vrnet_ext.learning.losses",
    "vrnet_ext.train": "vrnet_ext.learning.train",
    "vrnet_ext.train_config": "vrnet_ext.learning.config",
    "vrnet_ext.warm_start": "vrnet_ext.learning.warm_start",
    "vrnet_ext.scene_training": "vrnet_ext.learning.scene_training",
    "vrnet_ext.memory_plan": "vrnet_ext.registration.budget",
    "vrnet_ext.global_registration": "vrnet_ext.registration.ransac",
    "vrnet_ext.registration.methods": "vrnet_ext.names",
    "vrnet_ext.registration.estimators": "vrnet_ext.registration.icp_steps",
}


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds the old paths of :data:`MOVED` and loads each as the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} moved to {new}; the old path will be removed in vrnet_ext 0.3",
                      DeprecationWarning, stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):
        """The module at the new path is already executed."""


def install() -> None:
    """Puts the alias finder on ``sys.meta_path`` (once)."""
    if not any(isinstance(finder, _Alias) for finder in sys.meta_path):
        sys.meta_path.append(_Alias())
