"""Public ops. Each takes ``backend="ext"`` (compiled kernel, the default) or ``"torch"``
(the pure-PyTorch reference, same signature). ``trusted_values()``: a region in which they skip
the checks that read tensor values (``__all__`` lists the ops only)."""
from vrnet_ext.ops._checks import trusted_values
from vrnet_ext.ops.attention import attention
from vrnet_ext.ops.edge_features import edge_features
from vrnet_ext.ops.edge_norm_max import edge_norm_max
from vrnet_ext.ops.fpfh import fpfh
from vrnet_ext.ops.gather_reduce import gather_reduce
from vrnet_ext.ops.kabsch import kabsch, robust_kabsch
from vrnet_ext.ops.knn import knn
from vrnet_ext.ops.normals import normals
from vrnet_ext.ops.pairwise_distance_loss import pairwise_distance_loss
from vrnet_ext.ops.soft_match import soft_match
from vrnet_ext.ops.spatial_consistency import spatial_consistency
from vrnet_ext.ops.svd3x3 import svd3x3
from vrnet_ext.ops.voxel_downsample import voxel_downsample

__all__ = ["knn", "edge_features", "gather_reduce", "edge_norm_max", "svd3x3", "kabsch", "robust_kabsch", "pairwise_distance_loss",
           "soft_match", "attention", "normals", "fpfh", "voxel_downsample", "spatial_consistency"]
