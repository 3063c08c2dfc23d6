"""Inputs every op refuses the same way, naming the argument: tensors without data (meta)."""
import pytest
import torch

from vrnet_ext import ops

META = torch.device("meta")
CLOUD = torch.rand(1, 50, 3)
INDEX = torch.zeros(1, 50, 4, dtype=torch.long)
CALLS = {
    "knn": (lambda: ops.knn(CLOUD.to(META), CLOUD, 4), "query"),
    "svd3x3": (lambda: ops.svd3x3(torch.rand(4, 3, 3, device=META)), "A"),
    "kabsch": (lambda: ops.kabsch(CLOUD.to(META), CLOUD), "src"),
    "normals": (lambda: ops.normals(CLOUD[0].to(META)), "points"),
    "voxel_downsample": (lambda: ops.voxel_downsample(CLOUD[0].to(META), 0.1), "points"),
    "spatial_consistency": (lambda: ops.spatial_consistency(CLOUD[0].to(META), CLOUD[0], 0.1, 0.1), "src"),
    "soft_match": (lambda: ops.soft_match(CLOUD.to(META), CLOUD, CLOUD), "query"),
    "gather_reduce": (lambda: ops.gather_reduce(CLOUD.to(META), INDEX), "values"),
    "edge_features": (lambda: ops.edge_features(CLOUD.to(META), INDEX), "x"),
    "pairwise_distance_loss": (lambda: ops.pairwise_distance_loss(CLOUD.to(META), CLOUD), "x"),
    "fpfh": (lambda: ops.fpfh(CLOUD[0].to(META), CLOUD[0], 0.3), "points"),
}


@pytest.mark.parametrize("op", sorted(CALLS))
def test_a_meta_tensor_is_refused_naming_the_argument(op):
    call, argument = CALLS[op]
    with pytest.raises(ValueError, match=f"^{argument} is a meta tensor"):
        call()
