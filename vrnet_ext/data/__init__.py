"""Datasets and the ModelNet40 registration protocol (the protocol imports without torch)."""
from vrnet_ext._lazy import lazy_attributes

__all__ = ["ModelNet40Pairs", "PairSpec", "SETTINGS", "default_root", "load_h5", "make_pair"]
__getattr__ = lazy_attributes(__name__, {
    "ModelNet40Pairs": "vrnet_ext.data.modelnet", "default_root": "vrnet_ext.data.modelnet",
    "load_h5": "vrnet_ext.data.modelnet", "SETTINGS": "vrnet_ext.data.protocol", "PairSpec": "vrnet_ext.data.protocol",
    "make_pair": "vrnet_ext.data.protocol",
})
