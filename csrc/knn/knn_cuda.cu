// CUDA kNN. C = 3: one thread per query scans the reference cloud in shared-memory tiles and keeps
// its top-k in a register-resident sorted buffer (RegisterTopK; exact differences, as the CPU grid
// search). Other C:
// cuBLAS dot products over bounded chunks of the reference cloud (never the N x M matrix), each
// chunk scanned by a kernel that merges it into the running per-query top-k. k > 64: bounded chunks
// of query rows, their distances sorted (stable). Same results and tie-breaking (ascending distance,
// then lower index) as the CPU kernel; the backward gathers through the inverse graph, so it is
// deterministic.
#include <ATen/ops/bmm.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include "common/cuda_utils.cuh"
#include "knn/knn.h"

namespace vrnet {
namespace {

constexpr int kTile = 256;                     // reference points per shared-memory tile (C = 3)
constexpr int64_t kChunkElements = 8 << 20;    // dot-product chunk budget (B x queries x refs)

template <typename scalar_t>
__device__ inline scalar_t sq_dist3(scalar_t qx, scalar_t qy, scalar_t qz, const scalar_t* r) {
  const scalar_t dx = qx - r[0], dy = qy - r[1], dz = qz - r[2];
  return add_rn(add_rn(mul_rn(dx, dx), mul_rn(dy, dy)), mul_rn(dz, dz));
}

// The first k entries of a buffer to global memory (the guard keeps the indices compile-time).
template <typename scalar_t, int KMAX>
__device__ inline void store(const RegisterTopK<scalar_t, KMAX>& top, int64_t k, scalar_t* dist, int64_t* idx) {
  VRNET_UNROLL
  for (int j = 0; j < KMAX; ++j)
    if (j < k) {
      dist[j] = top.dist[j];
      idx[j] = top.idx[j];
    }
}

template <typename scalar_t, int KMAX>
__global__ void knn3_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ ref, int64_t N,
                            int64_t M, int64_t k, bool exclude_self, scalar_t* __restrict__ dist_out,
                            int64_t* __restrict__ idx_out) {
  __shared__ scalar_t tile[3 * kTile];
  const int64_t b = blockIdx.y;
  const int64_t n = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const bool active = n < N;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  scalar_t worst = top.worst();
  scalar_t qx = 0, qy = 0, qz = 0;
  if (active) {
    const scalar_t* q = query + (b * N + n) * 3;
    qx = q[0];
    qy = q[1];
    qz = q[2];
  }
  const int64_t self = exclude_self ? n : -1;
  for (int64_t r0 = 0; r0 < M; r0 += kTile) {
    const int count = static_cast<int>(M - r0 < kTile ? M - r0 : kTile);
    __syncthreads();
    for (int t = threadIdx.x; t < 3 * count; t += blockDim.x) tile[t] = ref[(b * M + r0) * 3 + t];
    __syncthreads();
    if (!active) continue;
    for (int j = 0; j < count; ++j) {
      const scalar_t d = sq_dist3(qx, qy, qz, tile + 3 * j);
      if (d <= worst && r0 + j != self) {
        top.push(d, static_cast<int32_t>(r0 + j));
        worst = top.worst();
      }
    }
  }
  if (active) store(top, k, dist_out + (b * N + n) * k, idx_out + (b * N + n) * k);
}

// Merges one chunk of dot products dots[b, j, n] = ref[b, r0 + j] . query[b, q0 + n] into the
// running top-k of queries q0.. (state kept in dist_out/idx_out between chunks).
template <typename scalar_t, int KMAX>
__global__ void knn_chunk_kernel(const scalar_t* __restrict__ dots, const scalar_t* __restrict__ query_norm,
                                 const scalar_t* __restrict__ ref_norm, int64_t N, int64_t M, int64_t q0,
                                 int64_t query_count, int64_t r0, int64_t ref_count, int64_t k, bool exclude_self,
                                 scalar_t* __restrict__ dist_out, int64_t* __restrict__ idx_out) {
  const int64_t b = blockIdx.y;
  const int64_t local = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (local >= query_count) return;
  const int64_t n = q0 + local;
  RegisterTopK<scalar_t, KMAX> top;
  top.reset(static_cast<int32_t>(M));
  scalar_t* d_row = dist_out + (b * N + n) * k;
  int64_t* i_row = idx_out + (b * N + n) * k;
  if (r0 > 0) {  // the k best of the earlier chunks (the other KMAX - k slots stay empty)
    VRNET_UNROLL
    for (int j = 0; j < KMAX; ++j)
      if (j < k) {
        top.dist[j] = d_row[j];
        top.idx[j] = static_cast<int32_t>(i_row[j]);
      }
  }
  scalar_t worst = top.worst();
  const scalar_t qn = query_norm[b * N + n];
  const scalar_t* col = dots + b * ref_count * query_count + local;
  for (int64_t j = 0; j < ref_count; ++j) {
    const int64_t m = r0 + j;
    // Same expression and rounding as the CPU tiles: max(|q|^2 + |r|^2 - 2 q.r, 0).
    scalar_t d = sub_rn(add_rn(qn, ref_norm[b * M + m]), mul_rn(scalar_t(2), col[j * query_count]));
    d = d > scalar_t(0) ? d : scalar_t(0);
    if (d <= worst && !(exclude_self && m == n)) {
      top.push(d, static_cast<int32_t>(m));
      worst = top.worst();
    }
  }
  store(top, k, d_row, i_row);
}

// Calls fn(std::integral_constant<int, KMAX>) with the smallest register buffer that holds k <= 64
// (ptxas: no local memory up to 64 slots).
template <typename Fn>
void dispatch_kmax(int64_t k, Fn&& fn) {
  static_assert(kCudaRegisterK == 64, "the buffer sizes below end at kCudaRegisterK");
  if (k <= 8) fn(std::integral_constant<int, 8>{});
  else if (k <= 16) fn(std::integral_constant<int, 16>{});
  else if (k <= 32) fn(std::integral_constant<int, 32>{});
  else fn(std::integral_constant<int, 64>{});
}

// k > kCudaRegisterK: rows of queries in chunks of at most kChunkElements distances, each row sorted
// (stable, so equal distances keep index order). C = 3 uses exact differences like the other paths.
void knn_by_sorting(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
                    at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  const int64_t rows = std::min<int64_t>(N, std::max<int64_t>(1, kChunkElements / (B * M)));
  const at::Tensor ref_norm = ref.square().sum(-1).unsqueeze(1);  // (B, 1, M)
  for (int64_t q0 = 0; q0 < N; q0 += rows) {
    const int64_t count = std::min(rows, N - q0);
    const at::Tensor q = query.narrow(1, q0, count);
    at::Tensor d;
    if (C == 3) {  // (dx^2 + dy^2) + dz^2 in separate roundings, as the CPU grid search
      const at::Tensor diff = q.unsqueeze(2).sub(ref.unsqueeze(1));
      d = diff.select(-1, 0).square().add(diff.select(-1, 1).square()).add(diff.select(-1, 2).square());
    } else {
      d = q.square().sum(-1).unsqueeze(2).add(ref_norm).sub(at::bmm(q, ref.transpose(1, 2)).mul(2)).clamp_min(0);
    }
    if (exclude_self) d.diagonal(q0, 1, 2).fill_(std::numeric_limits<double>::infinity());
    const auto [sorted, order] = d.sort(/*stable=*/true, /*dim=*/-1, /*descending=*/false);
    dist.narrow(1, q0, count).copy_(sorted.narrow(-1, 0, k));
    idx.narrow(1, q0, count).copy_(order.narrow(-1, 0, k));
  }
}

template <typename scalar_t>
void knn_features(const at::Tensor& query, const at::Tensor& ref, int64_t k, bool exclude_self, at::Tensor& dist,
                  at::Tensor& idx) {
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1);
  const at::Tensor query_norm = query.square().sum(-1).contiguous();
  const at::Tensor ref_norm = ref.square().sum(-1).contiguous();
  const int64_t query_chunk = std::min<int64_t>(N, std::max<int64_t>(1, kChunkElements / (B * std::min<int64_t>(M, 1024))));
  const int64_t ref_chunk = std::min<int64_t>(M, std::max<int64_t>(1, kChunkElements / (B * query_chunk)));
  for (int64_t q0 = 0; q0 < N; q0 += query_chunk) {
    const int64_t query_count = std::min(query_chunk, N - q0);
    const at::Tensor query_t = query.narrow(1, q0, query_count).transpose(1, 2);  // (B, C, n)
    for (int64_t r0 = 0; r0 < M; r0 += ref_chunk) {
      const int64_t ref_count = std::min(ref_chunk, M - r0);
      const at::Tensor dots = at::bmm(ref.narrow(1, r0, ref_count), query_t).contiguous();  // (B, m, n)
      dispatch_kmax(k, [&](auto kmax) {
        knn_chunk_kernel<scalar_t, decltype(kmax)::value>
            <<<dim3(blocks_for(query_count), B), kThreads, 0, current_stream()>>>(
                dots.const_data_ptr<scalar_t>(), query_norm.const_data_ptr<scalar_t>(),
                ref_norm.const_data_ptr<scalar_t>(), N, M, q0, query_count, r0, ref_count, k, exclude_self,
                dist.mutable_data_ptr<scalar_t>(), idx.mutable_data_ptr<int64_t>());
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    }
  }
}

std::tuple<at::Tensor, at::Tensor> knn_cuda(const at::Tensor& query_in, const at::Tensor& ref_in, int64_t k,
                                            bool exclude_self) {
  check_knn_inputs(query_in, ref_in, k, exclude_self);
  const c10::cuda::CUDAGuard guard(query_in.device());
  const at::Tensor query = query_in.contiguous(), ref = ref_in.contiguous();
  check_on_device({finite_condition(query, "query"), finite_condition(ref, "ref")});
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2);
  at::Tensor dist = at::empty({B, N, k}, query.options());
  at::Tensor idx = at::empty({B, N, k}, query.options().dtype(at::kLong));
  if (N == 0 || B == 0) return {dist, idx};
  if (k > kCudaRegisterK) {
    knn_by_sorting(query, ref, k, exclude_self, dist, idx);
    return {dist, idx};
  }
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_cuda", [&] {
    if (C == 3) {
      dispatch_kmax(k, [&](auto kmax) {
        knn3_kernel<scalar_t, decltype(kmax)::value><<<dim3(blocks_for(N), B), kThreads, 0, current_stream()>>>(
            query.const_data_ptr<scalar_t>(), ref.const_data_ptr<scalar_t>(), N, M, k, exclude_self,
            dist.mutable_data_ptr<scalar_t>(), idx.mutable_data_ptr<int64_t>());
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      });
    } else {
      knn_features<scalar_t>(query, ref, k, exclude_self, dist, idx);
    }
  });
  return {dist, idx};
}

// grad_query[b, n, c] = sum_j 2 g[b, n, j] (q[b, n, c] - r[b, idx, c]).
template <typename scalar_t>
__global__ void knn_grad_query_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ query,
                                      const scalar_t* __restrict__ ref, const int64_t* __restrict__ idx, int64_t B,
                                      int64_t N, int64_t M, int64_t C, int64_t k, scalar_t* __restrict__ grad_query) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * N * C) return;
  const int64_t c = t % C, bn = t / C, b = bn / N;
  const scalar_t q = query[t];
  scalar_t acc = 0;
  for (int64_t j = 0; j < k; ++j) {
    const int64_t m = idx[bn * k + j];
    acc += 2 * grad[bn * k + j] * (q - ref[(b * M + m) * C + c]);
  }
  grad_query[t] = acc;
}

// grad_ref[b, m, c] = -sum over edges (n, j) into m of 2 g[b, n, j] (q[b, n, c] - r[b, m, c]).
template <typename scalar_t>
__global__ void knn_grad_ref_kernel(const scalar_t* __restrict__ grad, const scalar_t* __restrict__ query,
                                    const scalar_t* __restrict__ ref, const int64_t* __restrict__ order,
                                    const int64_t* __restrict__ row_ptr, int64_t B, int64_t N, int64_t M, int64_t C,
                                    int64_t k, scalar_t* __restrict__ grad_ref) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * M * C) return;
  const int64_t c = t % C, bm = t / C, b = bm / M, m = bm % M;
  const scalar_t r = ref[t];
  const int64_t* edges = order + b * N * k;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (M + 1) + m]; e < row_ptr[b * (M + 1) + m + 1]; ++e) {
    const int64_t pos = edges[e], n = pos / k;
    acc -= 2 * grad[b * N * k + pos] * (query[(b * N + n) * C + c] - r);
  }
  grad_ref[t] = acc;
}

std::tuple<at::Tensor, at::Tensor> knn_backward_cuda(const at::Tensor& grad_in, const at::Tensor& query_in,
                                                     const at::Tensor& ref_in, const at::Tensor& idx_in) {
  check_knn_backward_inputs(grad_in, query_in, ref_in, idx_in);
  const c10::cuda::CUDAGuard guard(query_in.device());
  const at::Tensor grad = grad_in.contiguous(), query = query_in.contiguous();
  const at::Tensor ref = ref_in.contiguous(), idx = idx_in.contiguous();
  const int64_t B = query.size(0), N = query.size(1), M = ref.size(1), C = query.size(2), k = idx.size(2);
  at::Tensor grad_query = at::zeros_like(query), grad_ref = at::zeros_like(ref);
  if (B * N == 0) return {grad_query, grad_ref};
  const Incidence inc = build_incidence(idx, M);
  AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "knn_backward_cuda", [&] {
    knn_grad_query_kernel<scalar_t><<<blocks_for(B * N * C), kThreads, 0, current_stream()>>>(
        grad.const_data_ptr<scalar_t>(), query.const_data_ptr<scalar_t>(), ref.const_data_ptr<scalar_t>(),
        idx.const_data_ptr<int64_t>(), B, N, M, C, k, grad_query.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    knn_grad_ref_kernel<scalar_t><<<blocks_for(B * M * C), kThreads, 0, current_stream()>>>(
        grad.const_data_ptr<scalar_t>(), query.const_data_ptr<scalar_t>(), ref.const_data_ptr<scalar_t>(),
        inc.order.const_data_ptr<int64_t>(), inc.row_ptr.const_data_ptr<int64_t>(), B, N, M, C, k,
        grad_ref.mutable_data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {grad_query, grad_ref};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("knn", &knn_cuda);
  m.impl("knn_backward", &knn_backward_cuda);
}

}  // namespace vrnet
