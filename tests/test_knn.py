import importlib

import pytest
import torch

from conftest import (DTYPES, compile_fullgraph, non_contiguous, opcheck, requires_ext,
                      tolerances, under_each_cpu_dispatch)
from vrnet_ext import ops
from vrnet_ext.ops import trusted_values


def assert_knn_matches(dist, idx, query, ref, k, exclude_self=False):
    """Compare with the reference, tolerating swaps between neighbours at (nearly) equal distance."""
    ref_dist, ref_idx = ops.knn(query, ref, k, exclude_self=exclude_self, backend="torch")
    tol = tolerances(query.dtype)
    torch.testing.assert_close(dist, ref_dist, rtol=tol["rtol"], atol=tol["atol"] * 10)
    exact = ((query.unsqueeze(2) - ref.gather(1, idx.flatten(1).unsqueeze(-1).expand(-1, -1, ref.shape[2]))
              .view(*idx.shape, -1)) ** 2).sum(-1)
    torch.testing.assert_close(dist, exact, rtol=tol["rtol"], atol=tol["atol"] * 10)
    mismatch = idx != ref_idx
    if mismatch.any():  # only near-ties may differ
        gap = (ref_dist - dist).abs()[mismatch]
        assert gap.max() <= 1e-4 * (1 + ref_dist.abs().max()), "index differs beyond near-ties"
    assert bool((idx >= 0).all()) and bool((idx < ref.shape[1]).all())
    if exclude_self:
        assert not bool((idx == torch.arange(query.shape[1]).view(1, -1, 1)).any())


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("C", [1, 3, 5, 64, 512])
@pytest.mark.parametrize("B,N,M,k", [(1, 1, 1, 1), (1, 37, 53, 53), (3, 301, 257, 20), (2, 1029, 1100, 7)])
def test_parity_with_reference(device, dtype, C, B, N, M, k):
    query = torch.randn(B, N, C, dtype=dtype)
    ref = torch.randn(B, M, C, dtype=dtype)
    dist, idx = ops.knn(query, ref, k)
    assert dist.shape == idx.shape == (B, N, k) and idx.dtype == torch.int64 and dist.dtype == dtype
    assert bool((dist[..., 1:] >= dist[..., :-1]).all()), "distances must be ascending"
    assert_knn_matches(dist, idx, query, ref, k)


@requires_ext
@pytest.mark.parametrize("C", [3, 64])
@pytest.mark.parametrize("dtype", DTYPES)
def test_exclude_self_and_non_contiguous(device, C, dtype):
    points = non_contiguous(torch.randn(2, 333, C, dtype=dtype))
    dist, idx = ops.knn(points, points, 332, exclude_self=True)
    assert_knn_matches(dist, idx, points, points, 332, exclude_self=True)


@requires_ext
@pytest.mark.parametrize("name", ["sphere_surface", "plane", "clusters", "far_queries", "beside_on_one_axis",
                                  "duplicates"])
def test_grid_on_awkward_distributions(device, name):
    g = torch.Generator().manual_seed(1)
    ref = torch.randn(1, 3001, 3, generator=g, device="cpu")
    query = torch.randn(1, 777, 3, generator=g, device="cpu")
    if name == "sphere_surface":
        ref = ref / ref.norm(dim=-1, keepdim=True)
    elif name == "plane":
        ref[..., 2] = 0.0
        query[..., 2] = 0.0
    elif name == "clusters":
        ref = ref * 1e-3 + torch.randint(0, 2, (1, 3001, 1), generator=g, device="cpu") * 100.0
    elif name == "far_queries":
        query = query + 50.0
    elif name == "beside_on_one_axis":  # outside the grid along x only: the search bound mixes both cases
        query[..., 0] += 7.0
    else:
        ref = ref[:, :10].repeat(1, 300, 1)
    query, ref = query.to(device), ref.to(device)
    dist, idx = ops.knn(query, ref, 16)
    assert_knn_matches(dist, idx, query, ref, 16)


@requires_ext
@pytest.mark.parametrize("C", [3, 64])
def test_ties_broken_by_lower_index(device, C):
    base = torch.randn(1, 5, C, dtype=torch.float64)
    ref = base.repeat(1, 4, 1)  # every point present 4 times: indices j, j+5, j+10, j+15
    query = base[:, :2]
    for backend in ("ext", "torch"):
        dist, idx = ops.knn(query, ref, 6, backend=backend)
        expected = torch.sort(torch.cdist(query, ref).square(), dim=-1, stable=True).indices[..., :6]
        assert torch.equal(idx[..., :4], expected[..., :4]), backend
        assert torch.equal(idx[0, 0, :4], torch.tensor([0, 5, 10, 15])), backend


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("trusted", [False, True])
def test_reference_orders_crowded_ties_by_index(dtype, trusted, monkeypatch):
    """7 shuffled copies of 6 points: rows where more points tie with the k-th distance than fit
    keep the lowest indices, as a stable sort of the distances does, inside trusted_values (no
    branch on the data) as outside, the float32 keys in one chunk or several; queries far from the
    origin too."""
    knn_module = importlib.import_module("vrnet_ext.ops.knn")
    g = torch.Generator().manual_seed(3)
    base = torch.randn(2, 6, 5, dtype=dtype, generator=g)
    ref = base.repeat(1, 7, 1)[:, torch.randperm(42, generator=g)] + 1e3
    query = torch.cat([base[:, :3] + 1e3, torch.randn(2, 4, 5, dtype=dtype, generator=g) + 1e3], 1)
    with trusted_values(trusted):
        dist, idx = ops.knn(query, ref, 10, backend="torch")
    scores = torch.cdist(query, ref).square()
    assert torch.equal(idx, torch.sort(scores, dim=-1, stable=True).indices[..., :10])
    assert torch.equal(dist, scores.gather(-1, idx))
    monkeypatch.setattr(knn_module, "KEY_CHUNK_ELEMENTS", 3 * 42)  # float32 keys in chunks of 3 rows
    with trusted_values(trusted):
        assert torch.equal(ops.knn(query, ref, 10, backend="torch")[1], idx)


@requires_ext
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("copies", [3, 200])
def test_many_exact_duplicates_in_one_tile(dtype, copies):
    """A cloud of one tile made of `copies` copies of 4 points: with 200 copies every row's bound
    passes far more columns than a row buffers, and the search takes the reservoir; either way the
    k nearest are the lowest indices at distance 0, then the next."""
    base = torch.randn(1, 4, 16, dtype=dtype, generator=torch.Generator().manual_seed(2))
    cloud = base.repeat(1, copies, 1)
    dist, idx = ops.knn(cloud, cloud, 10, exclude_self=True)
    exact = torch.cdist(cloud.double(), cloud.double(), compute_mode="donot_use_mm_for_euclid_dist").square()[0]
    exact.fill_diagonal_(float("inf"))
    expected = torch.sort(exact, dim=-1, stable=True).indices[:, :10]
    assert torch.equal(idx[0], expected)
    torch.testing.assert_close(dist[0].double(), exact.gather(1, expected), **tolerances(dtype))


@requires_ext
@pytest.mark.parametrize("C", [3, 5])
def test_gradcheck(device, C):
    query = torch.rand(2, 9, C, dtype=torch.float64, requires_grad=True)
    ref = torch.rand(2, 11, C, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q, r: ops.knn(q, r, 4)[0], (query, ref))


@requires_ext
@pytest.mark.parametrize("C", [3, 64])
def test_gradient_matches_reference(device, C):
    query = torch.randn(2, 100, C, dtype=torch.float64, requires_grad=True)
    ref = torch.randn(2, 120, C, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(2, 100, 8, dtype=torch.float64)
    grads = []
    for backend in ("ext", "torch"):
        (ops.knn(query, ref, 8, backend=backend)[0] * weights).sum().backward()
        grads.append((query.grad.clone(), ref.grad.clone()))
        query.grad = ref.grad = None
    torch.testing.assert_close(grads[0], grads[1])


@requires_ext
@pytest.mark.parametrize("C", [3, 7])
def test_opcheck(device, C):
    query = torch.randn(2, 20, C, requires_grad=True)
    ref = torch.randn(2, 25, C, requires_grad=True)
    opcheck(torch.ops.vrnet_ext.knn.default, (query, ref, 5, False))
    opcheck(torch.ops.vrnet_ext.knn.default, (ref, ref, 5, True))


@requires_ext
@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_torch_compile_fullgraph(device, backend):
    query, ref = torch.randn(2, 50, 3), torch.randn(2, 60, 3)
    ref[1, :9] = ref[1, 0]  # more ties with the k-th distance than fit: the lowest indices win
    query[1, 0] = ref[1, 0]
    fn = compile_fullgraph(lambda q, r: ops.knn(q, r, 6, backend=backend))
    torch.testing.assert_close(fn(query, ref), ops.knn(query, ref, 6, backend=backend))
    assert fn(query, ref)[1][1, 0].tolist() == list(range(6))


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_bad_input(device, backend):
    good = torch.randn(2, 10, 3)
    cases = [
        ((torch.randn(10, 3), good, 3), ValueError, "query"),
        ((good, torch.randn(2, 10, 4), 3), ValueError, "ref"),
        ((good, torch.randn(3, 10, 3), 3), ValueError, "ref"),
        ((good, good, 0), ValueError, "k"),
        ((good, good, 11), ValueError, "k"),
        ((good.int(), good, 3), TypeError, "query"),
        ((good.half(), good.double(), 3), TypeError, "ref"),  # float16 is promoted to float32, not to float64
        ((good, good.double(), 3), TypeError, "ref"),
        ((good, good.to("meta"), 3), ValueError, "ref"),
        ((good, torch.randn(2, 0, 3), 1), ValueError, "k"),
        ((torch.randn(2, 0, 3), good, 1), ValueError, "query"),
    ]
    for args, error, name in cases:
        with pytest.raises(error, match=name):
            ops.knn(*args, backend=backend)
    with pytest.raises(ValueError, match="k"):
        ops.knn(good, good, 10, exclude_self=True, backend=backend)
    for bad in (float("nan"), float("inf")):
        poisoned = good.clone()
        poisoned[1, 3, 2] = bad
        with pytest.raises(ValueError, match="NaN or Inf"):
            ops.knn(poisoned, good, 3, backend=backend)
        with pytest.raises(ValueError, match="NaN or Inf"):
            ops.knn(good, poisoned, 3, backend=backend)
    with pytest.raises(ValueError, match="backend"):
        ops.knn(good, good, 3, backend="cuda-magic")


def _brute_force(query, ref, k):
    """float64 brute force: (B, N, k) distances of the k nearest."""
    d = ((query.double()[:, :, None] - ref.double()[:, None]) ** 2).sum(-1)
    return d.topk(k, largest=False, sorted=True).values


def _exact_distances(query, ref, idx):
    gathered = ref.double().gather(1, idx.reshape(idx.shape[0], -1, 1).expand(-1, -1, ref.shape[2]))
    return ((query.double()[:, :, None] - gathered.reshape(*idx.shape, -1)) ** 2).sum(-1)


@pytest.mark.parametrize("offset, C, dtype", [(100.0, 4, torch.float32), (1000.0, 4, torch.float32),
                                              (1000.0, 1, torch.float32), (1e4, 2, torch.float32),
                                              (1e6, 64, torch.float64), (-3e3, 16, torch.float32)])
def test_feature_knn_is_exact_far_from_the_origin(offset, C, dtype):
    # |q|^2 + |r|^2 - 2 q.r cancels catastrophically for clouds far from the origin; the GEMM path
    # must still return the true nearest neighbours (regression: 46-100 % of rows were wrong).
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(2, 512, C, generator=g, dtype=torch.float64) + offset).to(dtype)
    _, idx = ops.knn(x, x, 8)
    torch.testing.assert_close(_exact_distances(x, x, idx), _brute_force(x, x, 8), rtol=0, atol=0)


def test_feature_knn_with_overflowing_norms_returns_valid_indices():
    # squared norms overflow float32 here: indices must still point into ref (regression:
    # uninitialised memory came back as indices), each row its own k distinct points.
    x = torch.rand(1, 300, 4, generator=torch.Generator().manual_seed(0)) * 1e20
    dist2, idx = ops.knn(x, x, 5)
    assert int(idx.min()) >= 0 and int(idx.max()) < 300
    assert all(len(set(row.tolist())) == 5 for row in idx[0])
    assert torch.equal(idx[0, :, 0], torch.arange(300)) and not dist2.isnan().any()


@pytest.mark.parametrize("dtype", DTYPES)
def test_far_strays_do_not_change_the_grid_search(dtype):
    """One point 100 km away (and two close together far away, and a stray at another corner): the
    results equal float64 brute force with exact differences, queries far out included."""
    torch.manual_seed(3)
    cloud = torch.rand(1, 3000, 3, dtype=dtype) * 10
    strays = torch.tensor([[1e5, 0.0, 0.0], [1e5, 0.5, 0.0], [-3e4, 2e4, 7e3]], dtype=dtype)
    cloud = torch.cat([cloud, strays.unsqueeze(0)], dim=1)
    for query, ref, k, exclude in ((cloud, cloud, 4, True), (cloud[:, ::7].contiguous(), cloud, 3, False)):
        dist, idx = ops.knn(query, ref, k, exclude_self=exclude)
        exact = (query.double()[0, :, None] - ref.double()[0, None]).square().sum(-1)
        if exclude:
            exact.fill_diagonal_(float("inf"))
        exact_dist, exact_idx = exact.topk(k, dim=1, largest=False)
        torch.testing.assert_close(dist[0].double(), exact_dist, **tolerances(dtype))
        assert (idx[0] == exact_idx).float().mean() > 0.999  # only exact ties may order differently
    # the two far strays find each other
    _, idx = ops.knn(cloud, cloud, 1, exclude_self=True)
    assert idx[0, 3000, 0] == 3001 and idx[0, 3001, 0] == 3000


@requires_ext
def test_the_vector_and_the_portable_feature_search_agree(tmp_path):
    """Where the CPU has AVX-512 the tiles' distances, subset minima and offers run as vector code;
    VRNET_CPU_DISPATCH=generic keeps the portable loops. Same distances and indices, bit for bit:
    k under and over the 16 subsets that bound a fresh row, several reference tiles (M > 1024),
    exact duplicates (ties) and the query's own column excluded, in both precisions; clouds of one
    tile (M <= 1024), including one whose bound passes every column (150 copies of each point)."""
    script = ("import sys, torch; from vrnet_ext import ops; g = torch.Generator().manual_seed(5); out = []\n"
              "for dtype in (torch.float32, torch.float64):\n"
              "    x = torch.randn(2, 1500, 32, generator=g, dtype=dtype); x[:, 700:900] = x[:, 100:300]\n"
              "    out += [ops.knn(x, x, k, exclude_self=es) for k in (1, 10, 16, 17, 40) for es in (False, True)]\n"
              "    out.append(ops.knn(x[:, :37, :5], x[:, :, :5], 12))\n"
              "    y = x[:, :768].contiguous(); out += [ops.knn(y, y, k, exclude_self=True) for k in (1, 10, 16)]\n"
              "    z = torch.zeros(1, 300, 8, dtype=dtype); z[:, 150:] = 1; out.append(ops.knn(z, z, 10))\n"
              "torch.save(out, sys.argv[1])")
    results = under_each_cpu_dispatch(script, tmp_path)
    for (dist_vector, idx_vector), (dist_generic, idx_generic) in zip(*results):
        assert torch.equal(dist_vector, dist_generic) and torch.equal(idx_vector, idx_generic)


def test_tensor_core_diagnostics_refuse_what_the_tensor_cores_do_not_search():
    """ops.knn.tensor_core_unproven_rows names why it cannot answer (here: a CPU tensor, float64, wide rows)."""
    from vrnet_ext.ops.knn import tensor_core_unproven_rows

    rows = torch.randn(1, 40, 16)
    for query, k in ((rows, 5), (rows.double(), 5), (torch.randn(1, 40, 200), 5)):
        with pytest.raises(ValueError, match="tensor-core search takes float32 rows"):
            tensor_core_unproven_rows(query, query, k)
    with pytest.raises(ValueError, match="k must be in"):
        tensor_core_unproven_rows(rows, rows, 41)
