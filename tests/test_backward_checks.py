"""Registered backward kernels check their arguments: inconsistent direct calls raise, never crash.

The calls run in a subprocess, so a crash (the defect this guards against) fails the test with the
child's exit status instead of killing the test session."""
import subprocess
import sys
import textwrap

from conftest import requires_ext

HOSTILE_CALLS = textwrap.dedent('''
    import torch
    import vrnet_ext.ops  # loads the compiled module: registers torch.ops.vrnet_ext
    ops = torch.ops.vrnet_ext
    f, l = torch.randn, torch.long
    idx = torch.randint(0, 10, (2, 10, 4))
    far = torch.full((2, 10, 4), 10**9, dtype=l)
    w3 = torch.ones(2, 3)
    calls = {
        "knn_backward idx out of range": lambda: ops.knn_backward(f(2, 10, 4), f(2, 10, 3), f(2, 10, 3), far),
        "knn_backward grad shape": lambda: ops.knn_backward(f(2, 10, 7), f(2, 10, 3), f(2, 10, 3), idx),
        "knn_backward ref batch": lambda: ops.knn_backward(f(2, 10, 4), f(2, 10, 3), f(1, 10, 3), idx),
        "knn_backward dtype": lambda: ops.knn_backward(f(2, 10, 4).double(), f(2, 10, 3), f(2, 10, 3), idx),
        "edge_features_backward num_points": lambda: ops.edge_features_backward(f(2, 6, 10, 4), idx, 10**6),
        "edge_features_backward grad shape": lambda: ops.edge_features_backward(f(2, 6, 3, 4), idx, 10),
        "edge_features_backward idx": lambda: ops.edge_features_backward(f(2, 6, 10, 4), far, 10),
        "gather_reduce_backward idx": lambda: ops.gather_reduce_backward(f(2, 3, 10), far, torch.zeros(2, 3, 10, dtype=l), "max", 10),
        "gather_reduce_backward arg": lambda: ops.gather_reduce_backward(f(2, 3, 10), idx, torch.full((2, 3, 10), 99, dtype=l), "max", 10),
        "gather_reduce_backward arg shape": lambda: ops.gather_reduce_backward(f(2, 3, 10), idx, torch.zeros(1, 3, 10, dtype=l), "min", 10),
        "gather_reduce_backward num_values": lambda: ops.gather_reduce_backward(f(2, 3, 10), idx, torch.zeros(0, 3, 10, dtype=l), "sum", 0),
        "gather_reduce_backward grad": lambda: ops.gather_reduce_backward(f(2, 3, 99), idx, torch.zeros(0, 3, 10, dtype=l), "sum", 10),
        "kabsch_backward weights": lambda: ops.kabsch_backward(f(2, 3, 3), f(2, 3), f(2, 5, 3), f(2, 5, 3), w3),
        "kabsch_backward grad_R": lambda: ops.kabsch_backward(f(1, 3, 3), f(2, 3), f(2, 5, 3), f(2, 5, 3), torch.ones(2, 5)),
        "kabsch_backward grad_t": lambda: ops.kabsch_backward(f(2, 3, 3), f(2, 2), f(2, 5, 3), f(2, 5, 3), torch.ones(2, 5)),
        "svd3x3_backward S": lambda: ops.svd3x3_backward(f(4, 3, 3), f(4, 3), f(4, 3, 3), f(4, 3, 3), f(1, 3), f(4, 3, 3)),
        "svd3x3_backward grad_V": lambda: ops.svd3x3_backward(f(4, 3, 3), f(4, 3), f(2, 3, 3), f(4, 3, 3), f(4, 3), f(4, 3, 3)),
        "pairwise_distance_loss_backward loss": lambda: ops.pairwise_distance_loss_backward(f(2), f(2, 5, 3), f(2, 5, 3), f(1)),
        "pairwise_distance_loss_backward grad": lambda: ops.pairwise_distance_loss_backward(f(9), f(2, 5, 3), f(2, 5, 3), f(2)),
    }
    for name, call in calls.items():
        try:
            call()
        except (ValueError, TypeError) as error:
            print("raised", name, "|", str(error).splitlines()[0], flush=True)
        else:
            print("ACCEPTED", name, flush=True)
''')


@requires_ext
def test_inconsistent_backward_calls_raise_clear_errors_and_never_crash():
    result = subprocess.run([sys.executable, "-c", HOSTILE_CALLS], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"the child died (status {result.returncode}):\n{result.stdout}\n{result.stderr[-2000:]}"
    lines = result.stdout.splitlines()
    assert len(lines) == 19 and all(line.startswith("raised") for line in lines), result.stdout
