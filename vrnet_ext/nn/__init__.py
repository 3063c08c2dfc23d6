"""Layers built on the fused ops."""
from vrnet_ext.nn.autocast_weights import AutocastLinear, autocast_parameter
from vrnet_ext.nn.edge_conv import EdgeConv
from vrnet_ext.nn.inference_cache import inference_cached
from vrnet_ext.nn.pointwise import PointwiseMLP, folded_affine

__all__ = ["AutocastLinear", "EdgeConv", "PointwiseMLP", "autocast_parameter", "folded_affine", "inference_cached"]
