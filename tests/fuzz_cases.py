"""Property-based fuzz cases (hypothesis) for every op, the file readers and the checkpoint loader.

Run by ``tests/test_fuzz.py``, one subprocess per target, so that a crash in compiled code reports
as a failed test instead of killing the test session:

    python tests/fuzz_cases.py TARGET EXAMPLES      # e.g. knn 1500

Each op is compared with float64 brute force within the precision limits its docstring states
(``PRECISION`` below mirrors them), on random shapes, dtypes, layouts (non-contiguous views),
degenerate geometry (duplicate, collinear, coincident points), offsets and scales; malformed
arguments must raise ``ValueError`` or ``TypeError`` naming the argument. Readers and the
checkpoint loader get mutated files and must return a valid result or raise their own error type;
text clouds are also read by an independent strict parser (``strict_xyz``) and must agree with it;
checkpoints get weights of odd strides, element counts and dtypes; outputs get every kind of path
(devices, FIFOs, folders, symlinks and their loops); training runs get killed before any write and
must resume to the files of a run never killed; spatial consistency gets copies and coincident
points and must agree with its reference.
"""
from __future__ import annotations

import io
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vrnet_ext import ops

EPS = {torch.float32: float(torch.finfo(torch.float32).eps), torch.float64: float(torch.finfo(torch.float64).eps)}


def _settings(examples: int):
    return settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))


@st.composite
def clouds(draw, max_batch=3, max_points=40, channels=None, min_points=1):
    """(B, N, C) float tensors: offsets, scales, duplicates, collinear or coincident points, and
    sometimes a non-contiguous view."""
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    B = draw(st.integers(1, max_batch))
    N = draw(st.integers(min_points, max_points))
    C = draw(st.sampled_from(channels or [1, 2, 3, 4, 7, 33]))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    points = torch.randn(B, N, C, generator=g, dtype=torch.float64)
    shape = draw(st.sampled_from(["random", "duplicates", "collinear", "coincident", "grid"]))
    if shape == "duplicates" and N > 1:
        points[:, N // 2:] = points[:, : N - N // 2].clone()
    elif shape == "collinear":
        points = torch.linspace(-1, 1, N, dtype=torch.float64).view(1, N, 1) * torch.randn(B, 1, C, generator=g,
                                                                                              dtype=torch.float64)
    elif shape == "coincident":
        points = points[:, :1].expand(B, N, C).clone()
    elif shape == "grid":
        points = torch.round(points * 2) / 2
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3]))
    offset = draw(st.sampled_from([0.0, 1e2, -1e3] + ([1e5] if dtype == torch.float64 else [])))
    points = (points * scale + offset).to(dtype)
    if draw(st.booleans()):  # a non-contiguous view with the same values
        points = points.transpose(1, 2).contiguous().transpose(1, 2)
    return points


def _brute_knn(query, ref, k, exclude_self):
    d = ((query.double()[:, :, None] - ref.double()[:, None]) ** 2).sum(-1)
    if exclude_self:
        d = d + torch.diag_embed(torch.full(d.shape[:2], float("inf"), dtype=torch.float64))
    return d.sort(dim=-1).values[..., :k]


@st.composite
def knn_case(draw):
    query = draw(clouds())
    same = draw(st.booleans())
    ref = query if same else draw(clouds(channels=[query.shape[2]], max_batch=query.shape[0])).to(query.dtype)
    if ref.shape[0] != query.shape[0]:
        ref = ref[:1].expand(query.shape[0], -1, -1)
    exclude_self = same and query.shape[1] > 1 and draw(st.booleans())
    k = draw(st.integers(1, ref.shape[1] - int(exclude_self)))
    return query, ref, k, exclude_self


def check_knn(query, ref, k, exclude_self):
    dist2, idx = ops.knn(query, ref, k, exclude_self=exclude_self)
    assert dist2.shape == idx.shape == (query.shape[0], query.shape[1], k)
    assert int(idx.min()) >= 0 and int(idx.max()) < ref.shape[1]
    assert all(len(set(row.tolist())) == k for row in idx.reshape(-1, k))
    if exclude_self:
        assert not (idx == torch.arange(query.shape[1]).view(1, -1, 1)).any()
    gathered = ref.double().gather(1, idx.reshape(idx.shape[0], -1, 1).expand(-1, -1, ref.shape[2]))
    true_of_ours = ((query.double()[:, :, None] - gathered.reshape(*idx.shape, -1)) ** 2).sum(-1)
    # documented limit: distances are exact sums of squared differences in the input dtype, so
    # they (and the ranking) may differ from float64 by a few ulps of the squared extent
    magnitude = (query.double() - ref.double().mean(dim=1, keepdim=True)).abs().amax() ** 2
    magnitude = magnitude + (ref.double() - ref.double().mean(dim=1, keepdim=True)).abs().amax() ** 2
    tolerance = 64 * query.shape[2] * EPS[query.dtype] * float(magnitude) + 1e-300
    expected = _brute_knn(query, ref, k, exclude_self)
    assert float((true_of_ours - expected).abs().max()) <= tolerance
    assert float((dist2.double() - true_of_ours).abs().max()) <= tolerance
    assert bool((dist2[..., 1:] >= dist2[..., :-1]).all())


@st.composite
def graph_case(draw):
    values = draw(clouds(channels=[1, 2, 5, 16])).transpose(1, 2)  # (B, C, M)
    B, _, M = values.shape
    N = draw(st.integers(1, 30))
    k = draw(st.integers(1, 8))
    seed = draw(st.integers(0, 2**31 - 1))
    idx = torch.randint(0, M, (B, N, k), generator=torch.Generator().manual_seed(seed))
    return values, idx, draw(st.sampled_from(["max", "min", "sum", "mean"]))


def check_gather_reduce(values, idx, reduce):
    got = ops.gather_reduce(values, idx, reduce)
    expected = ops.gather_reduce(values.double(), idx, reduce, backend="torch")
    tolerance = 8 * idx.shape[2] * EPS[values.dtype] * float(values.double().abs().amax())
    assert float((got.double() - expected).abs().max()) <= tolerance
    if idx.shape[1] == values.shape[2]:
        features = ops.edge_features(values, idx)
        assert torch.equal(features, ops.edge_features(values, idx, backend="torch"))


@st.composite
def edge_norm_max_case(draw):
    """Projections (B, 2O, N) from the cloud strategy (offsets, scales, coincident values), a graph
    into the same N points, BN parameters of either sign, batch or running statistics."""
    values = draw(clouds(channels=[2, 4, 16])).transpose(1, 2)  # (B, 2O, N)
    B, _, N = values.shape
    k = draw(st.integers(1, 8))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    idx = torch.randint(0, N, (B, N, k), generator=g)
    O = values.shape[1] // 2
    weight = (torch.rand(O, generator=g, dtype=torch.float64) * 4 - 2).to(values.dtype)
    bias = torch.randn(O, generator=g, dtype=torch.float64).to(values.dtype)
    running = None
    if draw(st.booleans()) or B * N * k == 1:
        running = (values[:, :O].mean(dim=(0, 2)) + values[:, O:].mean(dim=(0, 2)), torch.rand(O, generator=g, dtype=torch.float64).to(values.dtype) + 0.1)
    slope = draw(st.sampled_from([0.2, 0.0, 1.0, 3.0, -0.2, -1e-9]))
    return values, idx, weight, bias, running, slope


def check_edge_norm_max(projections, idx, weight, bias, running, slope):
    from vrnet_ext.ops.edge_norm_max import edge_norm_max_reference

    stats = running or (None, None)
    if slope < 0:  # the max is taken before the activation: refused on every path, naming the argument
        for backend in ("ext", "torch"):
            try:
                ops.edge_norm_max(projections, idx, weight, bias, *stats, negative_slope=slope, backend=backend)
            except ValueError as error:
                assert "negative_slope" in str(error)
            else:
                raise AssertionError(f"negative_slope {slope} accepted by backend {backend}")
        return
    out, mean, var = ops.edge_norm_max(projections, idx, weight, bias, *stats, negative_slope=slope)
    wide = [t.double() if t is not None else None for t in (projections, weight, bias, *stats)]
    expected, expected_mean, expected_var = edge_norm_max_reference(wide[0], idx, *wide[1:], negative_slope=slope)
    # float32 storage of a value of size |v| is off by |v| eps; normalised, that is |v| eps |w| / sqrt(var + eps)
    spread = float(projections.double().abs().amax()) + float(expected_mean.abs().amax())
    gain = float(weight.double().abs().amax() / (expected_var.amin() + 1e-5).sqrt())
    tolerance = 64 * idx.shape[2] * EPS[projections.dtype] * (spread * gain + float(bias.double().abs().amax()) + 1) \
        * max(1.0, slope)
    assert float((out.double() - expected).abs().max()) <= tolerance
    assert float((mean.double() - expected_mean).abs().max()) <= 64 * EPS[projections.dtype] * spread
    assert float((var.double() - expected_var).abs().max()) <= 64 * EPS[projections.dtype] * (
        spread * spread + float(expected_var.amax()))


@st.composite
def matrices(draw):
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    B = draw(st.integers(1, 20))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, 3, 3, generator=g, dtype=torch.float64)
    kind = draw(st.sampled_from(["random", "rank1", "rank2", "zero", "repeated", "rotation"]))
    if kind == "rank1":
        A = torch.randn(B, 3, 1, generator=g, dtype=torch.float64) @ torch.randn(B, 1, 3, generator=g, dtype=torch.float64)
    elif kind == "rank2":
        A[:, 2] = A[:, 0] + A[:, 1]
    elif kind == "zero":
        A = torch.zeros_like(A)
    elif kind == "repeated":
        A = torch.diag_embed(torch.ones(B, 3, dtype=torch.float64) * 2.0)
    elif kind == "rotation":
        A = torch.linalg.qr(A).Q
    return (A * draw(st.sampled_from([1e-8, 1.0, 1e8]))).to(dtype)


def check_svd3x3(A):
    U, S, V = ops.svd3x3(A)
    scale = float(A.double().abs().amax()) + 1e-300
    tolerance = 64 * EPS[A.dtype]
    eye = torch.eye(3, dtype=torch.float64)
    assert float((U.double().mT @ U.double() - eye).abs().max()) <= tolerance
    assert float((V.double().mT @ V.double() - eye).abs().max()) <= tolerance
    assert bool((S[:, :-1] >= S[:, 1:]).all()) and bool((S >= 0).all())
    rebuilt = U.double() @ torch.diag_embed(S.double()) @ V.double().mT
    assert float((rebuilt - A.double()).abs().max()) <= tolerance * scale


@st.composite
def kabsch_case(draw):
    src = draw(clouds(channels=[3], min_points=3, max_points=30))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    R = torch.linalg.qr(torch.randn(src.shape[0], 3, 3, generator=g, dtype=torch.float64)).Q
    R = R * torch.linalg.det(R).sign().view(-1, 1, 1)
    noise = draw(st.sampled_from([0.0, 0.01, 1.0]))
    tgt = src.double() @ R.mT + torch.randn(src.shape[0], 1, 3, generator=g, dtype=torch.float64)
    tgt = (tgt + noise * torch.randn(tgt.shape, generator=g, dtype=torch.float64)).to(src.dtype)
    weights = None
    if draw(st.booleans()):
        weights = torch.rand(src.shape[:2], generator=g, dtype=torch.float64)
        weights[:, 0] += 0.1  # never all zero
        weights = (weights * draw(st.sampled_from([1e-30, 1.0, 1e30]))).to(src.dtype)
    return src, tgt, weights


def check_kabsch(src, tgt, weights):
    R, t = ops.kabsch(src, tgt, weights)
    eye = torch.eye(3, dtype=torch.float64)
    assert float((R.double().mT @ R.double() - eye).abs().max()) <= 64 * EPS[src.dtype]
    assert bool((torch.linalg.det(R.double()) > 0).all())
    w = torch.ones(src.shape[:2], dtype=torch.float64) if weights is None else weights.double()
    w = w / w.sum(dim=1, keepdim=True)

    def cost(R_, t_):
        return (w * ((src.double() @ R_.mT + t_.unsqueeze(1) - tgt.double()) ** 2).sum(-1)).sum(-1)

    R_ref, t_ref = ops.kabsch(src.double(), tgt.double(), None if weights is None else weights.double(),
                              backend="torch")
    centred = src.double() - src.double().mean(dim=1, keepdim=True)
    spread = float(centred.abs().amax() + tgt.double().abs().amax()) ** 2
    # documented limit: the minimum cost is reached to ~1e3 ulps of the squared extent (degenerate
    # inputs have many minimisers; any of them is right)
    assert float((cost(R.double(), t.double()) - cost(R_ref, t_ref)).max()) <= 1e3 * EPS[src.dtype] * spread


@st.composite
def robust_kabsch_case(draw):
    src, tgt, weights = draw(kabsch_case())
    return (src, tgt, weights, draw(st.integers(0, 30)), draw(st.sampled_from(["cauchy", "geman_mcclure", "welsch"])),
            draw(st.sampled_from([1e-3, 0.07, 0.75, 3.0, 1e3])), draw(st.sampled_from([1e-30, 1e-3, 1.0])))


def check_robust_kabsch(src, tgt, weights, iterations, kernel, scale, min_scale):
    R, t = ops.robust_kabsch(src, tgt, weights, iterations, kernel, scale, min_scale)
    assert bool(torch.isfinite(R).all()) and bool(torch.isfinite(t).all())
    eye = torch.eye(3, dtype=torch.float64)
    assert float((R.double().mT @ R.double() - eye).abs().max()) <= 64 * EPS[src.dtype]
    assert bool((torch.linalg.det(R.double()) > 0).all())
    # no steps: the kabsch op's own solve, bit for bit
    for a, b in zip(ops.robust_kabsch(src, tgt, weights, 0, kernel, scale, min_scale), ops.kabsch(src, tgt, weights)):
        assert torch.equal(a, b)


@st.composite
def pdl_case(draw):
    x = draw(clouds(channels=[3], min_points=2, max_points=40))
    seed = draw(st.integers(0, 2**31 - 1))
    y = x + torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=x.dtype) * 0.1
    return x, y


def check_pairwise_distance_loss(x, y):
    got = ops.pairwise_distance_loss(x, y)
    expected = ops.pairwise_distance_loss(x.double(), y.double(), backend="torch")
    scale = float(torch.cat([x, y], 1).double().std()) + 1e-300
    assert float((got.double() - expected).abs().max()) <= 1e3 * EPS[x.dtype] * (scale + float(expected.abs().max()))


MALFORMED = [
    lambda: ops.knn(torch.randn(2, 5), torch.randn(2, 5, 3), 1),
    lambda: ops.knn(torch.randn(2, 5, 3), torch.randn(3, 5, 3), 1),
    lambda: ops.knn(torch.randn(2, 5, 3), torch.randn(2, 5, 3), 9),
    lambda: ops.knn(torch.randint(0, 3, (2, 5, 3)), torch.randn(2, 5, 3), 1),
    lambda: ops.knn(torch.full((1, 5, 3), float("nan")), torch.randn(1, 5, 3), 1),
    lambda: ops.edge_features(torch.randn(2, 3, 5), torch.full((2, 5, 2), 7)),
    lambda: ops.edge_features(torch.randn(2, 3, 5), torch.zeros(2, 5, 2)),
    lambda: ops.gather_reduce(torch.randn(2, 3, 5), torch.zeros(2, 4, 2, dtype=torch.long), "median"),
    lambda: ops.gather_reduce(torch.randn(2, 3, 0), torch.zeros(2, 4, 2, dtype=torch.long)),
    lambda: ops.edge_norm_max(torch.randn(2, 3, 5), torch.zeros(2, 5, 2, dtype=torch.long)),
    lambda: ops.edge_norm_max(torch.randn(2, 4, 5), torch.zeros(2, 5, 2, dtype=torch.long), torch.ones(3)),
    lambda: ops.svd3x3(torch.randn(2, 3, 4)),
    lambda: ops.svd3x3(torch.full((2, 3, 3), float("inf"))),
    lambda: ops.kabsch(torch.randn(2, 2, 3), torch.randn(2, 2, 3)),
    lambda: ops.kabsch(torch.randn(2, 5, 3), torch.randn(2, 5, 3), -torch.ones(2, 5)),
    lambda: ops.kabsch(torch.randn(2, 5, 3), torch.randn(2, 5, 3), torch.zeros(2, 5)),
    lambda: ops.pairwise_distance_loss(torch.randn(2, 5, 3), torch.randn(2, 4, 3)),
    lambda: ops.pairwise_distance_loss(torch.randn(2, 1, 3), torch.randn(2, 1, 3)),
]


def run_malformed(examples: int) -> None:
    @_settings(examples)
    @given(st.integers(0, len(MALFORMED) - 1), st.sampled_from(["ext", "torch"]))
    def malformed(case, backend):
        try:
            MALFORMED[case]()
        except (ValueError, TypeError):
            return
        raise AssertionError(f"malformed call {case} was accepted")

    malformed()


def _sample_files(folder: Path) -> list[Path]:
    from vrnet_ext.geometry.io import write_ply

    points = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)
    write_ply(folder / "a.ply", points)
    (folder / "b.ply").write_text("ply\nformat ascii 1.0\nelement vertex 20\nproperty float x\nproperty float y\n"
                                  "property float z\nend_header\n" + "".join(f"{x} {y} {z}\n" for x, y, z in points))
    (folder / "c.pcd").write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 20\nHEIGHT 1\n"
                                  "POINTS 20\nDATA ascii\n" + "".join(f"{x} {y} {z}\n" for x, y, z in points))
    np.save(folder / "d.npy", points)
    (folder / "e.xyz").write_text("".join(f"{x} {y} {z}\n" for x, y, z in points))
    np.concatenate([points, np.ones((20, 1), np.float32)], 1).tofile(folder / "f.bin")
    return [folder / n for n in ("a.ply", "b.ply", "c.pcd", "d.npy", "e.xyz", "f.bin")]


def run_readers(examples: int) -> None:
    from vrnet_ext.geometry.io import PointCloudError, read_points

    folder = Path(tempfile.mkdtemp())
    originals = [(path, path.read_bytes()) for path in _sample_files(folder)]

    @_settings(examples)
    @given(st.integers(0, len(originals) - 1), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)),
                                                        max_size=6),
           st.one_of(st.none(), st.integers(0, 10**6)), st.sampled_from([b"", b"-", b"9999999999", b"nan", b"\xff"]))
    def mutated(which, flips, cut, insert):
        path, data = originals[which]
        data = bytearray(data)
        for position, value in flips:
            if data:
                data[position % len(data)] = value
        if insert and data:
            spot = flips[0][0] % len(data) if flips else 0
            data[spot:spot] = insert
        if cut is not None and data:
            data = data[: cut % (len(data) + 1)]
        target = folder / f"m{path.suffix}"
        target.write_bytes(bytes(data))
        try:
            points = read_points(target)
        except PointCloudError as error:
            assert str(target) in str(error)
            return
        assert points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3
        assert points.shape[0] >= 3 and np.isfinite(points).all()

    mutated()


def run_checkpoints(examples: int) -> None:
    from vrnet_ext import VRNet, VRNetConfig
    from vrnet_ext.model.checkpoints import CheckpointError
    from vrnet_ext.model.pretrained import load_model

    config = VRNetConfig.small(k=4, dgcnn_channels=(8, 8), emb_dims=16, heads=2, ff_dims=16, walk_channels=(8, 3))
    buffer = io.BytesIO()
    torch.save({"model": VRNet(config).state_dict(), "config": {"model": config.to_dict()}}, buffer)
    original = buffer.getvalue()
    folder = Path(tempfile.mkdtemp())

    @_settings(examples)
    @given(st.lists(st.tuples(st.integers(0, 10**7), st.integers(0, 255)), min_size=1, max_size=8),
           st.one_of(st.none(), st.integers(0, 10**7)))
    def mutated(flips, cut):
        data = bytearray(original)
        for position, value in flips:
            data[position % len(data)] = value
        if cut is not None:
            data = data[: cut % (len(data) + 1)]
        path = folder / "m.pt"
        path.write_bytes(bytes(data))
        try:
            model, _ = load_model(path)
        except CheckpointError as error:
            assert "weights_only=False" not in str(error)
            return
        assert isinstance(model, VRNet)

    mutated()


SECOND_ORDER_OPS = {
    "knn": lambda p: ops.knn(p, p.detach() + 0.1, 2)[0],
    "kabsch": lambda p: ops.kabsch(p, p.detach().flip(1))[0],
    "svd3x3": lambda p: ops.svd3x3(p[:, :3])[1],
    "pairwise_distance_loss": lambda p: ops.pairwise_distance_loss(p, p.detach() * 1.1),
    "soft_match": lambda p: ops.soft_match(p, p.detach(), p.detach()),
    "edge_features": lambda p: ops.edge_features(p.transpose(1, 2), torch.zeros(p.shape[0], p.shape[1], 2,
                                                                                   dtype=torch.long)),
    "gather_reduce": lambda p: ops.gather_reduce(p.transpose(1, 2), torch.zeros(p.shape[0], p.shape[1], 2,
                                                                                  dtype=torch.long), "max"),
}


def run_second_order(examples: int) -> None:
    """Every op under create_graph: the second derivative exists (and gradgradcheck holds) or a
    NotImplementedError names the op; never a silent None."""

    @_settings(examples)
    @given(st.sampled_from(sorted(SECOND_ORDER_OPS)), st.integers(4, 12), st.integers(0, 2**31 - 1))
    def second_order(name, points, seed):
        p = torch.randn(1, points, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed),
                        requires_grad=True)
        fn = SECOND_ORDER_OPS[name]
        try:
            (grad,) = torch.autograd.grad(fn(p).sin().sum(), p, create_graph=True)
        except NotImplementedError as error:
            assert f"vrnet_ext.ops.{name}" in str(error)
            return
        (second,) = torch.autograd.grad(grad.square().sum(), p, allow_unused=True)
        assert second is not None and torch.isfinite(second).all(), name
        assert torch.autograd.gradgradcheck(lambda t: fn(t).sin(), (p,))

    second_order()


def run_memory_plan(examples: int) -> None:
    """Scene models of any size a file may hold, any budget and scan size: the plan stays within the
    budget or is refused at once (MemoryBudgetError), never a plan predicted above the budget."""
    from types import SimpleNamespace

    from vrnet_ext.registration import PointCounts, SceneNetwork
    from vrnet_ext.registration.budget import MB, MemoryBudgetError, plan_registration
    from vrnet_ext.model.scene import SCENE_LIMITS, SceneConfig

    sizes = {name: st.integers(max(low, 1) if name != "neighbours" else low, high)
             for name, (low, high) in SCENE_LIMITS.items() if name != "descriptor_dims"}

    @_settings(examples)
    @given(st.fixed_dictionaries(sizes), st.integers(50, 20_000), st.integers(1_000, 5_000_000),
           st.integers(3, 200_000))
    def plan_fits(config, budget_mb, scan_points, global_points):
        estimator = SceneNetwork(SimpleNamespace(config=SceneConfig(**config)))  # the planner reads its config
        try:
            plan = plan_registration(budget_mb * MB, estimator, scan_points, scan_points,
                                     PointCounts(global_points=global_points))
        except MemoryBudgetError as error:
            assert "cannot be met" in str(error)
            return
        assert plan.predicted_peak_mb <= budget_mb and plan.counts.global_points <= global_points

    plan_fits()


def run_georeferenced(examples: int) -> None:
    """A pair shifted by a georeferenced offset (up to 1e7 per axis) registers like the unshifted pair,
    and the transform comes back in the shifted clouds' own frame."""
    from vrnet_ext.data.procedural import room_scan
    from vrnet_ext.registration import IcpSettings, register, transform_errors

    scan = room_scan(4000, 0)
    angle = np.deg2rad(4.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = R, [0.05, -0.03, 0.02]
    target = scan @ R.T + truth[:3, 3]
    settings_ = IcpSettings(voxel_size=0.05)
    clean = register(scan, target, method="icp", icp_settings=settings_).T_target_source

    @_settings(examples)
    @given(st.lists(st.floats(-1e7, 1e7, allow_nan=False), min_size=3, max_size=3))
    def shifted_alike(offset):
        offset = np.asarray(offset)
        moved = np.eye(4)
        moved[:3, 3] = offset  # both clouds in a frame shifted by offset: T' = M T M^-1
        result = register(scan + offset, target + offset, method="icp", icp_settings=settings_).T_target_source
        expected = moved @ clean @ np.linalg.inv(moved)
        errors = transform_errors(result, expected)
        assert errors["rotation_error_deg"] < 0.05 and errors["translation_error"] < 0.01, (offset, errors)

    shifted_alike()


def run_full_disk(examples: int) -> None:
    """`vrnet register --out --json` under a random file-size limit (a full disk): success with complete
    files, or one error line naming the file, a non-zero exit and nothing at the final paths."""
    import json
    import subprocess

    from vrnet_ext.geometry.io import read_points, write_ply

    folder = Path(tempfile.mkdtemp())
    write_ply(folder / "a.ply", np.random.default_rng(0).normal(size=(2000, 3)))
    script = ("import resource, sys; limit = int(sys.argv[1]); resource.setrlimit(resource.RLIMIT_FSIZE, "
              "(limit, limit)); from vrnet_ext.cli import run; sys.argv = ['vrnet'] + sys.argv[2:]; run()")

    @_settings(min(examples, 6))
    @given(st.integers(0, 200_000))
    def complete_or_absent(limit):
        out, report = folder / "moved.ply", folder / "result.json"
        out.unlink(missing_ok=True), report.unlink(missing_ok=True)
        done = subprocess.run([sys.executable, "-c", script, str(limit), "register", str(folder / "a.ply"),
                               str(folder / "a.ply"), "--method", "icp", "--out", str(out), "--json", str(report)],
                              capture_output=True, text=True, timeout=300)
        if done.returncode == 0:
            assert len(read_points(out)) == 2000 and "T_target_source" in json.loads(report.read_text())
            return
        errors = [line for line in done.stderr.splitlines() if line.strip()]
        assert done.returncode == 1 and len(errors) == 1 and "File too large" in errors[0], done.stderr
        assert not (out.exists() and report.exists()) and not list(folder.glob(".*"))
        for path in (out, report):
            if path.exists():  # written before the limit bit: complete
                assert (len(read_points(path)) == 2000 if path.suffix == ".ply"
                        else "T_target_source" in json.loads(path.read_text()))

    complete_or_absent()


def run_spatial_consistency(examples: int) -> None:
    """Correspondences of a motion among outliers, with copies, coincident points and any scale: a
    finite rigid transform and a (K,) mask from both backends, equal; copies share their flag."""
    from vrnet_ext.ops.spatial_consistency import spatial_consistency_reference

    @_settings(examples)
    @given(st.integers(3, 120), st.floats(0.0, 0.9), st.integers(0, 40), st.sampled_from([1e-3, 1.0, 1e3]),
           st.floats(0.01, 0.5), st.integers(0, 10**6), st.booleans())
    def fits(K, outliers, copies, scale, tolerance, seed, coincide):
        g = torch.Generator().manual_seed(seed)
        p = torch.rand(K, 3, generator=g, dtype=torch.float64) * scale
        if coincide:
            p[: K // 2] = p[0]
        R = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64)).Q
        R = R * torch.sign(torch.det(R))
        q = p @ R.T + 0.3 * scale
        wrong = torch.rand(K, generator=g) < outliers
        q[wrong] = torch.rand(int(wrong.sum()), 3, generator=g, dtype=torch.float64) * scale
        if copies:
            p, q = torch.cat([p, p[-1:].expand(copies, 3)]), torch.cat([q, q[-1:].expand(copies, 3)])
        T, mask = ops.spatial_consistency(p, q, tolerance * scale, tolerance * scale, seeds=10, consensus=5)
        assert T.shape == (4, 4) and T.dtype == torch.float64 and torch.isfinite(T).all()
        assert torch.allclose(T[:3, :3] @ T[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-9)
        assert mask.shape == (len(p),) and mask.dtype == torch.bool
        if copies:
            assert bool((mask[K - 1:] == mask[K - 1]).all())
        reference = ops.spatial_consistency(p, q, tolerance * scale, tolerance * scale, seeds=10, consensus=5,
                                            backend="torch")
        assert torch.equal(mask, reference[1])
        spread = torch.linalg.svdvals(p[mask] - p[mask].mean(0)) if int(mask.sum()) >= 3 else torch.zeros(3)
        if spread[1] > 1e-6 * scale:  # inliers that determine a rotation (not coincident or collinear)
            assert torch.allclose(T, reference[0], atol=1e-6 * max(1.0, scale)), (T, reference[0])

    assert spatial_consistency_reference is not None
    fits()


def strict_xyz(text: str) -> np.ndarray | None:
    """An independent reading of a whitespace-separated text cloud: comment lines ('#') and blank
    ones skipped; a first line of words only is a header; every other line has 3 or more numbers
    (the first three kept); None where the reader must refuse (a mixed or short line, no rows, a
    non-finite value, fewer than 3 points)."""
    rows, header_allowed = [], True
    for line in text.splitlines():
        body = line.split("#")[0].strip()
        if not body:
            continue
        tokens = body.split()
        numeric = []
        for token in tokens:
            try:
                numeric.append(float(token))
            except ValueError:
                numeric.append(None)
        if header_allowed and all(value is None for value in numeric):
            header_allowed = False
            continue
        header_allowed = False
        if any(value is None for value in numeric) or len(numeric) < 3:
            return None
        rows.append(numeric[:3])
    if len(rows) < 3 or len({len(r) for r in rows}) > 1:
        return None
    table = np.array(rows, dtype=np.float64)
    return table if np.isfinite(table).all() else None


def run_strict_readers(examples: int) -> None:
    """Mutated text clouds (exponent case, words, short rows, header lines) read by read_points and
    by :func:`strict_xyz`: the same points, or both refuse."""
    from vrnet_ext.geometry.io import PointCloudError, read_points

    folder = Path(tempfile.mkdtemp())
    token = st.one_of(st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: f"{v:.6E}"),
                      st.floats(-1e3, 1e3, allow_nan=False).map(lambda v: f"{v:.4f}"),
                      st.sampled_from(["x", "y", "z", "nan", "inf", "1e", "--1", "1.0E+00", "#c"]))
    line = st.lists(token, min_size=0, max_size=5).map(" ".join)

    @_settings(examples)
    @given(st.lists(line, min_size=0, max_size=12))
    def same(lines):
        text = "\n".join(lines) + "\n"
        path = folder / "m.xyz"
        path.write_text(text)
        expected = strict_xyz(text)
        try:
            points = read_points(path)
        except PointCloudError as error:
            assert str(path) in str(error)
            assert expected is None or len(expected) < 3, (text, expected)
            return
        assert expected is not None, (text, points)
        np.testing.assert_array_equal(points, expected)

    same()


def run_checkpoint_tensors(examples: int) -> None:
    """A checkpoint whose one weight is a tensor of odd strides, element counts or dtype: refused
    naming the weight, or loaded with exactly those values when shape and dtype fit."""
    from vrnet_ext import VRNet, VRNetConfig
    from vrnet_ext.model.checkpoints import CheckpointError
    from vrnet_ext.model.pretrained import load_model

    config = VRNetConfig.small(k=4, dgcnn_channels=(8, 8), emb_dims=16, heads=2, ff_dims=16, walk_channels=(8, 3))
    state = VRNet(config).state_dict()
    names = sorted(k for k, v in state.items() if v.is_floating_point() and v.dim() >= 1)
    folder = Path(tempfile.mkdtemp())

    @_settings(examples)
    @given(st.sampled_from(names), st.sampled_from(["expand", "transpose", "strided", "numel", "dtype", "huge"]),
           st.sampled_from([torch.float16, torch.float32, torch.float64, torch.int32]))
    def loads_or_refuses(name, kind, dtype):
        want = state[name]
        base = torch.randn(want.numel() * 2 + 8).to(dtype) if dtype.is_floating_point else \
            torch.arange(want.numel() * 2 + 8, dtype=dtype)
        if kind == "expand":
            value = base[:1].expand(want.shape)
        elif kind == "transpose":
            value = base[:want.numel()].reshape(want.shape[::-1]).permute(*reversed(range(want.dim())))
        elif kind == "strided":
            value = base[: 2 * want.numel()].as_strided(want.shape, [2 * s for s in want.stride()])
        elif kind == "numel":
            value = base[: want.numel() + 1]
        elif kind == "dtype":
            value = base[:want.numel()].reshape(want.shape).to(torch.int64)
        else:
            value = base[:1].expand(2 ** 24)
        weights = dict(state, **{name: value})
        path = folder / "m.pt"
        torch.save({"model": weights, "config": {"model": config.to_dict()}}, path)
        try:
            model, _ = load_model(path)
        except CheckpointError as error:
            assert name in str(error) and str(path) in str(error), str(error)
            return
        assert value.shape == want.shape and value.dtype in (torch.float16, torch.float32)
        torch.testing.assert_close(model.state_dict()[name], value.float(), rtol=0, atol=0)

    loads_or_refuses()


def run_output_paths(examples: int) -> None:
    """Writes to a regular file, through a symlink, to a dangling symlink, to /dev/null, a FIFO with a
    reader, a folder, a symlink loop or a missing folder: the content lands where the path leads, or
    OutputError names the path; devices and FIFOs stay what they were; no temporary file is left."""
    import os
    import stat
    import threading

    from vrnet_ext.geometry.atomic import OutputError, write_text_atomically

    @_settings(examples)
    @given(st.sampled_from(["new", "existing", "symlink", "dangling", "devnull", "fifo", "folder", "loop",
                            "missing_folder"]), st.text(max_size=50))
    def lands(kind, content):
        folder = Path(tempfile.mkdtemp())
        path = folder / "out.json"
        real = folder / "real.json"
        received = []
        if kind == "existing":
            path.write_text("old")
        elif kind == "symlink":
            real.write_text("old")
            path.symlink_to(real)
        elif kind == "dangling":
            path.symlink_to(real)
        elif kind == "devnull":
            path = Path("/dev/null")
        elif kind == "fifo":
            os.mkfifo(path)
            reader = threading.Thread(target=lambda: received.append(path.read_bytes().decode()), daemon=True)
            reader.start()
        elif kind == "folder":
            path.mkdir()
        elif kind == "loop":
            path.symlink_to(path)
        elif kind == "missing_folder":
            path = folder / "absent" / "out.json"
        try:
            write_text_atomically(path, content)
        except OutputError as error:
            assert kind in ("folder", "loop", "missing_folder") and str(path) in str(error), (kind, str(error))
        else:
            assert kind not in ("folder", "loop", "missing_folder"), kind
            if kind in ("new", "existing", "symlink", "dangling"):
                assert (real if kind in ("symlink", "dangling") else path).read_bytes().decode() == content
                assert kind not in ("symlink", "dangling") or path.is_symlink()
            if kind == "fifo":
                reader.join(timeout=30)
                assert received == [content] and stat.S_ISFIFO(os.stat(path).st_mode)
            if kind == "devnull":
                assert stat.S_ISCHR(os.stat(path).st_mode)
        assert not [p for p in folder.rglob(".*") if p.is_file()], kind

    lands()


TRAINING_RUNS_PER_EXAMPLE = 10  # a kill point costs two training runs: one example in ten gets one


def run_kill_points(examples: int) -> None:
    """A tiny training run killed before one of its writes (checkpoint, best model, metrics row),
    then resumed from its last.pt (or started again without one): the same models and metrics rows
    as a run never killed. ``examples // 10`` kill points (a deep pass of 5000 tries 500)."""
    import json

    from conftest import ChairPairs
    import vrnet_ext.learning.train as train_module
    from vrnet_ext.learning.train import TrainConfig, train
    from vrnet_ext.model.checkpoints import read_checkpoint

    class Killed(BaseException):
        pass

    writes, kill_at = [], [None]
    save, log = train_module._save, train_module._log

    def write(real, *args):
        if len(writes) == kill_at[0]:
            raise Killed
        writes.append(1)
        real(*args)

    train_module._save = lambda checkpoint, path: write(save, checkpoint, path)
    train_module._log = lambda out_dir, record: write(log, out_dir, record)

    def run(out, **overrides):
        cfg = TrainConfig.from_preset("tiny", out_dir=str(out), progress=False, stage1_epochs=2, stage2_epochs=1,
                                      checkpoint_minutes=1e9, **overrides)
        train(cfg, datasets=(ChairPairs(8, 0), ChairPairs(4, 1)))

    def outcome(out):
        models = {p.name: read_checkpoint(p)["model"] for p in sorted(out.glob("*.pt"))}
        rows = [{k: v for k, v in json.loads(line).items() if not k.endswith("seconds")}
                for line in (out / "metrics.jsonl").read_text().splitlines()]
        return models, rows

    folder = Path(tempfile.mkdtemp())
    run(folder / "straight")
    straight, total = outcome(folder / "straight"), len(writes)

    @_settings(max(1, examples // TRAINING_RUNS_PER_EXAMPLE))
    @given(st.integers(0, total - 1), st.integers(0, 10**6))
    def resumes(k, tag):
        out = folder / f"k{k}_{tag}"
        writes.clear()
        kill_at[0] = k
        try:
            run(out)
            raise AssertionError("the kill did not happen")
        except Killed:
            pass
        kill_at[0] = None
        run(out, resume=str(out / "last.pt")) if (out / "last.pt").exists() else run(out)
        models, rows = outcome(out)
        assert rows == straight[1] and set(models) == set(straight[0]), k
        for name, weights in models.items():
            assert all(torch.equal(weights[p], straight[0][name][p]) for p in weights), (k, name)

    resumes()


OPS = {
    "knn": (knn_case(), check_knn),
    "gather_reduce": (graph_case(), check_gather_reduce),
    "edge_norm_max": (edge_norm_max_case(), check_edge_norm_max),
    "svd3x3": (matrices().map(lambda A: (A,)), check_svd3x3),
    "kabsch": (kabsch_case(), check_kabsch),
    "robust_kabsch": (robust_kabsch_case(), check_robust_kabsch),
    "pairwise_distance_loss": (pdl_case(), check_pairwise_distance_loss),
}
RUNNERS = {"malformed": run_malformed, "readers": run_readers, "checkpoints": run_checkpoints,
           "second_order": run_second_order, "memory_plan": run_memory_plan, "georeferenced": run_georeferenced,
           "full_disk": run_full_disk, "spatial_consistency": run_spatial_consistency,
           "strict_readers": run_strict_readers, "checkpoint_tensors": run_checkpoint_tensors,
           "output_paths": run_output_paths, "kill_points": run_kill_points}
TARGETS = sorted(OPS) + sorted(RUNNERS)


def run(target: str, examples: int) -> None:
    torch.set_num_threads(1)
    if target in OPS:
        strategy, check = OPS[target]

        @_settings(examples)
        @given(strategy)
        def property_holds(case):
            check(*case)

        property_holds()
    else:
        RUNNERS[target](examples)
    print(f"fuzz {target}: {examples} examples passed")


if __name__ == "__main__":
    run(sys.argv[1], int(sys.argv[2]))
