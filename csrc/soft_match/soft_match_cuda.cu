// CUDA streamed soft matching, the definition of soft_match_cpu.cpp with the simplest schedule that
// keeps memory at O((N + M)(c + D)): one thread per query row streams over the keys (forward: a
// running maximum, normaliser and row peak, then the normalised weighted sum of the values; backward
// dQ), and one thread per key row streams over the queries (backward dK and dV). No atomics: every
// output row is written by one thread in a fixed order. Arithmetic in double for the scores and
// their exponentials. Written and compiled against the CUDA torch headers, not yet run on a GPU
// (see README "GPU"); the tile-based version with shared memory is future work.
#include <ATen/ops/empty.h>
#include <ATen/ops/isfinite.h>
#include <ATen/ops/mul.h>
#include <ATen/ops/sub.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <cmath>

#include "common/cuda_utils.cuh"
#include "soft_match/soft_match.h"

namespace vrnet {
namespace {

template <typename scalar_t>
__device__ double score(const scalar_t* q, const scalar_t* k, int64_t C, double scale) {
  double dot = 0;
  for (int64_t c = 0; c < C; ++c) dot += double(q[c]) * double(k[c]);
  return dot * scale;
}

// P_ij = exp(s_ij - lse_i) and dS_ij = P_ij (dO_i . v_j + shift_i) of one (query, key) pair.
template <typename scalar_t>
__device__ void pair_grads(const scalar_t* q, const scalar_t* g, const scalar_t* k, const scalar_t* v, int64_t C,
                           int64_t D, double scale, double lse, double shift, double* p, double* ds) {
  double dp = 0;
  for (int64_t d = 0; d < D; ++d) dp += double(g[d]) * double(v[d]);
  *p = exp(score(q, k, C, scale) - lse);
  *ds = *p * (dp + shift);
}

// Row (b, i): pass 1 the row maximum (first index on ties) and normaliser, pass 2 the output row.
template <typename scalar_t>
__global__ void soft_match_forward_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                          const scalar_t* __restrict__ values, int64_t B, int64_t N, int64_t M,
                                          int64_t C, int64_t D, double scale, scalar_t* __restrict__ out,
                                          scalar_t* __restrict__ lse, int64_t* __restrict__ argmax) {
  const int64_t row = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (row >= B * N) return;
  const int64_t b = row / N;
  const scalar_t* q = query + row * C;
  const scalar_t* keys = key + b * M * C;
  const scalar_t* vals = values + b * M * D;
  double best = -INFINITY, total = 0;
  int64_t best_j = 0;
  for (int64_t j = 0; j < M; ++j) {
    const double s = score(q, keys + j * C, C, scale);
    if (s > best) {
      total = total * exp(best - s) + 1.0;
      best = s;
      best_j = j;
    } else {
      total += exp(s - best);
    }
  }
  scalar_t* o = out + row * D;
  for (int64_t d = 0; d < D; ++d) o[d] = 0;
  for (int64_t j = 0; j < M; ++j) {
    const double p = exp(score(q, keys + j * C, C, scale) - best) / total;
    for (int64_t d = 0; d < D; ++d) o[d] += static_cast<scalar_t>(p * double(vals[j * D + d]));
  }
  lse[row] = static_cast<scalar_t>(best + log(total));
  argmax[row] = best_j;
}

// Query row (b, i): dq_i = scale sum_j P_ij (dO_i . v_j + shift_i) k_j, shift_i = dlse_i - dO_i . O_i.
template <typename scalar_t>
__global__ void soft_match_grad_query_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                             const scalar_t* __restrict__ values, const scalar_t* __restrict__ grad_out,
                                             const scalar_t* __restrict__ lse, const scalar_t* __restrict__ shift,
                                             int64_t B, int64_t N, int64_t M, int64_t C, int64_t D, double scale,
                                             scalar_t* __restrict__ grad_query) {
  const int64_t row = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (row >= B * N) return;
  const int64_t b = row / N;
  const scalar_t* q = query + row * C;
  const scalar_t* g = grad_out + row * D;
  scalar_t* dq = grad_query + row * C;
  for (int64_t c = 0; c < C; ++c) dq[c] = 0;
  for (int64_t j = 0; j < M; ++j) {
    const scalar_t* k = key + (b * M + j) * C;
    const scalar_t* v = values + (b * M + j) * D;
    double p, ds;
    pair_grads(q, g, k, v, C, D, scale, double(lse[row]), double(shift[row]), &p, &ds);
    for (int64_t c = 0; c < C; ++c) dq[c] += static_cast<scalar_t>(scale * ds * double(k[c]));
  }
}

// Key row (b, j): dk_j = scale sum_i dS_ij q_i, dv_j = sum_i P_ij dO_i.
template <typename scalar_t>
__global__ void soft_match_grad_key_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                           const scalar_t* __restrict__ values, const scalar_t* __restrict__ grad_out,
                                           const scalar_t* __restrict__ lse, const scalar_t* __restrict__ shift,
                                           int64_t B, int64_t N, int64_t M, int64_t C, int64_t D, double scale,
                                           scalar_t* __restrict__ grad_key, scalar_t* __restrict__ grad_values) {
  const int64_t row = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (row >= B * M) return;
  const int64_t b = row / M;
  const scalar_t* k = key + row * C;
  const scalar_t* v = values + row * D;
  scalar_t* dk = grad_key + row * C;
  scalar_t* dv = grad_values + row * D;
  for (int64_t c = 0; c < C; ++c) dk[c] = 0;
  for (int64_t d = 0; d < D; ++d) dv[d] = 0;
  for (int64_t i = 0; i < N; ++i) {
    const int64_t qrow = b * N + i;
    const scalar_t* q = query + qrow * C;
    const scalar_t* g = grad_out + qrow * D;
    double p, ds;
    pair_grads(q, g, k, v, C, D, scale, double(lse[qrow]), double(shift[qrow]), &p, &ds);
    for (int64_t c = 0; c < C; ++c) dk[c] += static_cast<scalar_t>(scale * ds * double(q[c]));
    for (int64_t d = 0; d < D; ++d) dv[d] += static_cast<scalar_t>(p * double(g[d]));
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_cuda(const at::Tensor& query_in, const at::Tensor& key_in,
                                                               const at::Tensor& values_in, double scale) {
  check_soft_match_inputs(query_in, key_in, values_in, scale);
  const c10::cuda::CUDAGuard guard(query_in.device());
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  check_on_device({finite_condition(query, "query"), finite_condition(key, "key"),
                   finite_condition(values, "values")});
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1), C = query.size(2), D = values.size(2);
  at::Tensor out = at::empty({B, N, D}, query.options());
  at::Tensor lse = at::empty({B, N}, query.options());
  at::Tensor argmax = at::empty({B, N}, query.options().dtype(at::kLong));
  if (B * N > 0) {
    AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_cuda", [&] {
      soft_match_forward_kernel<scalar_t><<<blocks_for(B * N), kThreads, 0, current_stream()>>>(
          query.const_data_ptr<scalar_t>(), key.const_data_ptr<scalar_t>(), values.const_data_ptr<scalar_t>(), B, N,
          M, C, D, scale, out.mutable_data_ptr<scalar_t>(), lse.mutable_data_ptr<scalar_t>(),
          argmax.mutable_data_ptr<int64_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    check_on_device({{at::isfinite(lse).all(), "soft_match scores overflow: scale * query . key is not finite"}});
  }
  return {out, lse, argmax};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> soft_match_backward_cuda(
    const at::Tensor& grad_out_in, const at::Tensor& grad_lse_in, const at::Tensor& query_in,
    const at::Tensor& key_in, const at::Tensor& values_in, const at::Tensor& out_in, const at::Tensor& lse_in,
    double scale) {
  check_soft_match_backward_inputs(grad_out_in, grad_lse_in, query_in, key_in, values_in, out_in, lse_in, scale);
  const c10::cuda::CUDAGuard guard(query_in.device());
  const at::Tensor query = query_in.contiguous(), key = key_in.contiguous(), values = values_in.contiguous();
  const at::Tensor grad_out = grad_out_in.contiguous(), lse = lse_in.contiguous();
  const at::Tensor shift = at::sub(grad_lse_in, at::mul(grad_out, out_in).sum(2)).contiguous();
  at::Tensor grad_query = at::zeros_like(query), grad_key = at::zeros_like(key);
  at::Tensor grad_values = at::zeros_like(values);
  const int64_t B = query.size(0), N = query.size(1), M = key.size(1), C = query.size(2), D = values.size(2);
  if (B * N > 0) {
    AT_DISPATCH_FLOATING_TYPES(query.scalar_type(), "soft_match_backward_cuda", [&] {
      soft_match_grad_query_kernel<scalar_t><<<blocks_for(B * N), kThreads, 0, current_stream()>>>(
          query.const_data_ptr<scalar_t>(), key.const_data_ptr<scalar_t>(), values.const_data_ptr<scalar_t>(),
          grad_out.const_data_ptr<scalar_t>(), lse.const_data_ptr<scalar_t>(), shift.const_data_ptr<scalar_t>(), B,
          N, M, C, D, scale, grad_query.mutable_data_ptr<scalar_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      soft_match_grad_key_kernel<scalar_t><<<blocks_for(B * M), kThreads, 0, current_stream()>>>(
          query.const_data_ptr<scalar_t>(), key.const_data_ptr<scalar_t>(), values.const_data_ptr<scalar_t>(),
          grad_out.const_data_ptr<scalar_t>(), lse.const_data_ptr<scalar_t>(), shift.const_data_ptr<scalar_t>(), B,
          N, M, C, D, scale, grad_key.mutable_data_ptr<scalar_t>(), grad_values.mutable_data_ptr<scalar_t>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
  }
  return {grad_query, grad_key, grad_values};
}

}  // namespace

TORCH_LIBRARY_IMPL(vrnet_ext, CUDA, m) {
  m.impl("soft_match", &soft_match_cuda);
  m.impl("soft_match_backward", &soft_match_backward_cuda);
}

}  // namespace vrnet
