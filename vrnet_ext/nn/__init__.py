"""Layers built on the fused ops."""
from vrnet_ext.nn.edge_conv import EdgeConv

__all__ = ["EdgeConv"]
