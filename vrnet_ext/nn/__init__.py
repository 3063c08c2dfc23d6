"""Layers built on the fused ops."""
from vrnet_ext.nn.edge_conv import EdgeConv
from vrnet_ext.nn.pointwise import PointwiseMLP, folded_affine

__all__ = ["EdgeConv", "PointwiseMLP", "folded_affine"]
