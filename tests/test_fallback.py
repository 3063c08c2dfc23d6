"""Without the compiled module the package imports, warns once, and every op runs its reference."""
import subprocess
import sys
import textwrap


def test_ops_fall_back_to_reference_when_extension_is_missing():
    script = textwrap.dedent(
        """
        import sys, warnings
        sys.modules["vrnet_ext._C"] = None  # makes `from vrnet_ext import _C` raise ImportError
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            import torch
            import vrnet_ext
            from vrnet_ext import ops
            from vrnet_ext.nn import EdgeConv
            assert not vrnet_ext.has_extension()
            pts = torch.randn(2, 40, 3)
            dist, idx = ops.knn(pts, pts, 5)
            assert torch.equal(idx[..., 0], torch.arange(40).expand(2, 40))
            feats = ops.edge_features(pts.mT, idx)
            out = ops.gather_reduce(pts.mT, idx, "mean")
            R, t = ops.kabsch(pts, pts + 1)
            assert torch.allclose(R, torch.eye(3).expand(2, 3, 3), atol=1e-5)
            U, S, V = ops.svd3x3(torch.randn(4, 3, 3))
            loss = ops.pairwise_distance_loss(pts, pts)
            EdgeConv(3, 8)(pts.mT, idx)
        messages = [str(w.message) for w in caught if "compiled kernels unavailable" in str(w.message)]
        assert len(messages) == 1, messages
        print("fallback ok")
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "fallback ok" in result.stdout
