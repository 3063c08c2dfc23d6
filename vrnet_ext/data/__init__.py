"""Datasets and the ModelNet40 registration protocol."""
from vrnet_ext.data.modelnet import ModelNet40Pairs, default_root, load_h5
from vrnet_ext.data.protocol import SETTINGS, PairSpec, make_pair

__all__ = ["ModelNet40Pairs", "PairSpec", "SETTINGS", "default_root", "load_h5", "make_pair"]
