"""k-nearest neighbours: ``dist2, idx = knn(query, ref, k)``.

Compiled kernel: a uniform-grid search for C = 3 and, for other C, GEMM tiles (256 queries x 1024
refs) scanned by a per-query reservoir (candidates under the running k-th distance are buffered
and pruned with nth_element); neither builds the N x M distance matrix. On a GPU with TF32 tensor
cores, float32 rows of 4 to ``TENSOR_CORE_MAX_CHANNELS`` values and k up to ``TENSOR_CORE_MAX_K``
(:func:`on_tensor_cores`) take candidates from tensor-core products (three TF32 passes) of the clouds
centred on the reference mean, rank them by exact distance, and prove the ranking with a bound on the
products' error (rows without the proof are scanned whole): the CPU's distances and indices.
Reference: ``torch.cdist`` + ``topk``.
"""
from __future__ import annotations

import torch

from vrnet_ext._extension import has_extension, use_extension
from vrnet_ext.ops._checks import (LOW_PRECISION_DTYPES, check_finite, check_float, check_same, check_shape,
                                   first_order_only, float32_region, promote_low_precision, trusted_values,
                                   values_checked)
from vrnet_ext.runtime import cuda_has_tensor_cores

# The CUDA tensor-core search (csrc/knn/knn_kernels.cuh: kKnnTensorCoreMaxC, kKnnTensorCoreMaxK; its shared
# tiles and register lists): rows of 4 to TENSOR_CORE_MAX_CHANNELS values, at most TENSOR_CORE_MAX_K neighbours.
TENSOR_CORE_MAX_CHANNELS = 128
TENSOR_CORE_MAX_K = 32


def on_tensor_cores(device: torch.device, dtype: torch.dtype, channels: int, k: int) -> bool:
    """Whether the compiled kNN searches rows of ``channels`` values of ``dtype`` on ``device`` for k
    neighbours on its TF32 tensor cores (float32 or promoted to it, 3 < channels <=
    TENSOR_CORE_MAX_CHANNELS, k <= TENSOR_CORE_MAX_K, a GPU of compute capability 8.0 or later)."""
    return (device.type == "cuda" and (dtype == torch.float32 or dtype in LOW_PRECISION_DTYPES)
            and 3 < channels <= TENSOR_CORE_MAX_CHANNELS and k <= TENSOR_CORE_MAX_K and cuda_has_tensor_cores(device))


def _validate(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool) -> None:
    check_float(query, "query")
    check_float(ref, "ref")
    check_shape(query, "query", 3, "(B, N, C)")
    check_shape(ref, "ref", 3, "(B, M, C)")
    check_same({"query": query, "ref": ref})
    if ref.shape[0] != query.shape[0] or ref.shape[2] != query.shape[2]:
        raise ValueError(f"ref must have shape (B, M, C) = ({query.shape[0]}, M, {query.shape[2]}), "
                         f"got {tuple(ref.shape)}")
    if query.shape[1] == 0:
        raise ValueError("query is empty: it needs at least one point")
    if not isinstance(k, int) or isinstance(k, bool):
        raise TypeError(f"k must be an int, got {type(k).__name__}")
    if exclude_self and query.shape[1] != ref.shape[1]:
        raise ValueError("exclude_self=True needs query and ref to be the same cloud (N == M)")
    available = ref.shape[1] - (1 if exclude_self else 0)
    if k < 1 or k > available:
        raise ValueError(f"k must be in [1, {available}] for a ref cloud of {ref.shape[1]} points"
                         f"{' (self excluded)' if exclude_self else ''}, got {k}")


KEY_CHUNK_ELEMENTS = 1 << 24  # _smallest's int64 keys per chunk of rows (128 MB)


def _smallest(dist2: torch.Tensor, k: int) -> torch.Tensor:
    """(..., M) squared distances -> (..., k) indices of the k smallest, ascending, ties by lower
    index, without a branch on the data (no host synchronisation on a GPU).

    float32: non-negative floats order as their bit patterns (NaN, sign cleared, above +inf), so a
    key of the distance's bits above the index's is unique and one ``topk`` over the keys orders
    ties by index. float64 leaves no bits for the index: ``topk``, the candidates in index order, a
    stable sort by distance, and rows where more points tie with the k-th distance than fit sorted
    whole (every row while compiling or inside ``trusted_values``, else only those: one check)."""
    if dist2.dtype == torch.float32:
        count = dist2.shape[-1]
        index_bits = max(1, (count - 1).bit_length())
        rows = dist2.reshape(-1, count)
        chunk = max(1, KEY_CHUNK_ELEMENTS // count)  # the int64 keys of a few rows at a time, not of all
        smallest = []
        for start in range(0, len(rows), chunk):
            keys = rows[start:start + chunk].view(torch.int32).to(torch.int64).bitwise_and_(0x7FFFFFFF)
            keys.bitwise_left_shift_(index_bits).bitwise_or_(torch.arange(count, device=dist2.device))
            smallest.append(keys.topk(k, dim=-1, largest=False, sorted=True).values.bitwise_and_((1 << index_bits) - 1))
        return torch.cat(smallest).view(*dist2.shape[:-1], k)
    values, idx = dist2.topk(k, dim=-1, largest=False, sorted=True)
    idx = idx.sort(dim=-1).values
    idx = idx.gather(-1, dist2.gather(-1, idx).sort(dim=-1, stable=True).indices)
    crowded = (dist2 <= values[..., -1:]).sum(-1) > k
    if not values_checked():
        lowest = dist2.sort(dim=-1, stable=True).indices[..., :k]
        return torch.where(crowded.unsqueeze(-1), lowest, idx)
    if bool(crowded.any()):
        idx[crowded] = dist2[crowded].sort(dim=-1, stable=True).indices[..., :k]
    return idx


def knn_reference(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool = False):
    """Pure-PyTorch kNN: the full (B, N, M) distance matrix, then the k smallest; ties by lower index."""
    check_finite(query, "query")
    check_finite(ref, "ref")
    dist2 = torch.cdist(query, ref).square()
    if exclude_self:
        eye = torch.eye(ref.shape[1], dtype=torch.bool, device=ref.device)
        dist2 = dist2.masked_fill(eye, float("inf"))
    idx = _smallest(dist2.detach(), k)
    return dist2.gather(-1, idx), idx


def knn(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool = False, backend: str = "ext"):
    """k nearest neighbours of every query point among the ref points.

    Args:
        query: (B, N, C) float32/float64 points or features (bfloat16/float16 are promoted to
            float32, as under autocast).
        ref: (B, M, C), same dtype and device.
        k: neighbours per query, 1 <= k <= M (M - 1 with ``exclude_self``).
        exclude_self: drop ref index n for query n (query and ref are the same cloud).
        backend: ``"ext"`` (compiled kernel when available) or ``"torch"`` (reference).

    Returns:
        dist2 (B, N, k): squared Euclidean distances, ascending, ties by lower index;
        differentiable with respect to query and ref.
        idx (B, N, k) int64 indices into ref.

    Precision (checked by the fuzz suite against float64 brute force): ``dist2`` is the sum of
    squared coordinate differences computed in the input dtype, so distances and ranking agree
    with float64 up to a few ulps of the squared extent of the clouds (around their mean), at any
    offset from the origin. Distances beyond the dtype's range come out as +inf (those neighbours
    are then ordered by index).
    """
    query, ref = promote_low_precision(query), promote_low_precision(ref)
    _validate(query, ref, k, exclude_self)
    if use_extension(backend, query.device):
        return torch.ops.vrnet_ext.knn(query, ref, k, exclude_self)
    with float32_region(query):
        return knn_reference(query, ref, k, exclude_self)


def tensor_core_unproven_rows(query: torch.Tensor, ref: torch.Tensor, k: int,
                              exclude_self: bool = False) -> torch.Tensor:
    """Diagnostics of the CUDA tensor-core search (:func:`on_tensor_cores` must hold): (B, N) bool, the
    query rows whose candidates' ranking its error bound cannot prove, which :func:`knn` then scans whole
    (each costs a full row of exact distances). ``benchmarks/knn_proof_rate.py`` models the same on the CPU."""
    _validate(query, ref, k, exclude_self)
    if not on_tensor_cores(query.device, query.dtype, query.shape[2], k):
        raise ValueError(f"the tensor-core search takes float32 rows of 4 to {TENSOR_CORE_MAX_CHANNELS} values on a "
                         f"GPU of compute capability 8.0 or later, k <= {TENSOR_CORE_MAX_K}; got "
                         f"{query.dtype} rows of {query.shape[2]} on {query.device}, k = {k}")
    return torch.ops.vrnet_ext.knn_unproven_rows(query.float(), ref.float(), k, exclude_self)


if has_extension():

    @torch.library.register_fake("vrnet_ext::knn")
    def _knn_fake(query, ref, k, exclude_self):
        shape = (query.shape[0], query.shape[1], k)
        return query.new_empty(shape), query.new_empty(shape, dtype=torch.int64)

    @torch.library.register_fake("vrnet_ext::knn_unproven_rows")
    def _knn_unproven_rows_fake(query, ref, k, exclude_self):
        return query.new_empty(query.shape[:2], dtype=torch.bool)

    @torch.library.register_fake("vrnet_ext::knn_backward")
    def _knn_backward_fake(grad_dist2, query, ref, idx):
        return torch.empty_like(query), torch.empty_like(ref)

    def _knn_setup_context(ctx, inputs, output):
        query, ref, _, _ = inputs
        ctx.save_for_backward(query, ref, output[1])
        ctx.trusted = not values_checked()  # the forward's indices: in range

    def _knn_backward(ctx, grad_dist2, _grad_idx):
        query, ref, idx = ctx.saved_tensors
        first_order_only("knn", grad_dist2, query, ref)
        with trusted_values(ctx.trusted):
            grad_query, grad_ref = torch.ops.vrnet_ext.knn_backward(grad_dist2, query, ref, idx)
        return grad_query, grad_ref, None, None

    torch.library.register_autograd("vrnet_ext::knn", _knn_backward, setup_context=_knn_setup_context)
