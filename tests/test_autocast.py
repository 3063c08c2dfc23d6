"""Every op accepts bfloat16 / float16 inputs, as autocast produces them, and computes in float32."""
import pytest
import torch

from vrnet_ext import VRNet, VRNetConfig, ops
from vrnet_ext.learning.losses import correspondence_loss


def _inputs(generator):
    """Float inputs (rounded to the low dtype by the test) and an int64 graph; the cases only call ops."""
    floats = {
        "points": torch.rand(2, 37, 3, generator=generator),
        "features": torch.randn(2, 37, 5, generator=generator),
        "features_cn": torch.randn(2, 5, 37, generator=generator),
        "matrices": torch.randn(6, 3, 3, generator=generator),
        "weights": torch.rand(2, 37, generator=generator) + 0.1,
    }
    floats["moved"] = floats["points"].flip(1)
    return floats, torch.randint(0, 37, (2, 37, 4), generator=generator)


CASES = {
    "knn_points": lambda f, i, b: ops.knn(f["points"], f["moved"], 6, backend=b)[0],
    "knn_features": lambda f, i, b: ops.knn(f["features"], f["features"], 6, backend=b)[0],
    "edge_features": lambda f, i, b: ops.edge_features(f["features_cn"], i, backend=b),
    "gather_reduce": lambda f, i, b: ops.gather_reduce(f["features_cn"], i, "max", backend=b),
    "svd3x3": lambda f, i, b: ops.svd3x3(f["matrices"], backend=b)[1],
    "kabsch": lambda f, i, b: ops.kabsch(f["points"], f["moved"], f["weights"], backend=b)[1],
    "pairwise_distance_loss": lambda f, i, b: ops.pairwise_distance_loss(f["points"], f["moved"], backend=b),
}


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("backend", ["ext", "torch"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_low_precision_inputs_are_computed_in_float32(case, backend, dtype):
    floats, idx = _inputs(torch.Generator().manual_seed(0))
    low = {name: t.to(dtype) for name, t in floats.items()}
    expected = CASES[case]({name: t.float() for name, t in low.items()}, idx, backend)  # same rounded values, float32
    leaves = {name: t.clone().requires_grad_() for name, t in low.items()}
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = CASES[case](leaves, idx, backend)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    got.square().sum().backward()
    used = [leaf for leaf in leaves.values() if leaf.grad is not None]
    assert used and all(leaf.grad.dtype == dtype and torch.isfinite(leaf.grad.float()).all() for leaf in used)


def test_custom_ops_do_not_lower_their_own_matrix_products_under_autocast():
    # knn with C != 3 runs GEMM tiles inside the kernel: autocast must be off in there, or the
    # distances would come out of a bfloat16 product (errors ~1e-2 on these values).
    features = torch.randn(1, 300, 16, generator=torch.Generator().manual_seed(1)) * 10
    expected = ops.knn(features, features, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = ops.knn(features, features, 8)
    torch.testing.assert_close(got[0], expected[0])
    assert torch.equal(got[1], expected[1])


def test_vrnet_trains_under_bf16_autocast_with_a_float32_matching():
    torch.manual_seed(0)
    model = VRNet(VRNetConfig.small(k=6, dgcnn_channels=(8, 8), emb_dims=16, heads=2, ff_dims=16,
                                    walk_channels=(8, 3)))
    src, tgt = torch.rand(2, 40, 3), torch.rand(2, 40, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(src, tgt, return_matching=True)
        loss = correspondence_loss(out.matching, torch.arange(40).expand(2, 40))
    assert out.matching.dtype == out.vcp.dtype == out.rotation.dtype == torch.float32
    torch.testing.assert_close(out.matching.sum(-1), torch.ones(2, 40))
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.features.parameters())
