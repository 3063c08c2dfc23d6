// CUDA streamed soft matching, tiled: one block per tile of kSoftMatchRows rows of one side, one
// thread per row, the other side streamed through dynamic shared memory in tiles of `tile` rows that
// all threads of the block load together; memory O((N + M)(c + D)), never the N x M matrix.
//   forward: query tiles; keys and values streamed; the online-softmax recurrence per row (running
//            maximum m with the first index on ties, normaliser l and output accumulator, rescaled
//            by e^(m_old - m_new) when the maximum grows), as soft_match_cpu.cpp.
//   dQ:      query tiles; keys and values streamed; dq_i = scale sum_j dS_ij k_j.
//   dK, dV:  key tiles; queries, dO, lse and shift streamed; dk_j = scale sum_i dS_ij q_i,
//            dv_j = sum_i P_ij dO_i.
// with P_ij = e^(s_ij - lse_i), dS_ij = P_ij (dO_i . v_j + shift_i), shift_i = dlse_i - dO_i . O_i.
// Scores and exponentials in double; every output row is written by one thread in a fixed order
// (no atomics: deterministic). Rows past the end help load the tiles and compute nothing.
#pragma once

#include <math.h>

#include "common/cuda_device.cuh"

namespace vrnet {

constexpr int kSoftMatchRows = 64;  // rows (threads) per block

template <typename scalar_t>
__device__ inline double soft_match_score(const scalar_t* q, const scalar_t* k, int64_t C, double scale) {
  double dot = 0;
  for (int64_t c = 0; c < C; ++c) dot += double(q[c]) * double(k[c]);
  return dot * scale;
}

// Copies rows [r0, r0 + count) of `width` values each from `source` to `tile` (all threads help).
template <typename scalar_t>
__device__ inline void soft_match_load(const scalar_t* source, int64_t r0, int count, int64_t width, scalar_t* tile) {
  const int64_t total = count * width;
  for (int64_t t = threadIdx.x; t < total; t += blockDim.x) tile[t] = source[r0 * width + t];
}

// Streams the M keys and values of one batch (key: (M, C), values: (M, D)) through the block's
// dynamic shared memory in tiles of `tile` rows and calls visit(j, k_j, v_j) for every key j in
// order when `active`. Every thread of the block must call it (all help load the tiles).
template <typename scalar_t, typename Visit>
__device__ inline void soft_match_for_each_key(const scalar_t* key, const scalar_t* values, int64_t M, int64_t C,
                                               int64_t D, int tile, bool active, Visit visit) {
  VRNET_DYNAMIC_SHARED(unsigned char, shared_bytes);
  scalar_t* key_tile = reinterpret_cast<scalar_t*>(shared_bytes);
  scalar_t* value_tile = key_tile + tile * C;
  for (int64_t k0 = 0; k0 < M; k0 += tile) {
    const int count = static_cast<int>(M - k0 < tile ? M - k0 : tile);
    __syncthreads();
    soft_match_load(key, k0, count, C, key_tile);
    soft_match_load(values, k0, count, D, value_tile);
    __syncthreads();
    if (!active) continue;
    for (int j = 0; j < count; ++j) visit(k0 + j, key_tile + j * C, value_tile + j * D);
  }
}

template <typename scalar_t>
__global__ void soft_match_forward_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                          const scalar_t* __restrict__ values, int64_t N, int64_t M, int64_t C,
                                          int64_t D, double scale, int tile, scalar_t* __restrict__ out,
                                          scalar_t* __restrict__ lse, int64_t* __restrict__ argmax) {
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kSoftMatchRows + threadIdx.x;
  const bool active = i < N;
  const int64_t row = b * N + i;
  const scalar_t* q = query + row * C;
  scalar_t* o = out + row * D;
  if (active)
    for (int64_t d = 0; d < D; ++d) o[d] = 0;
  double best = -INFINITY, total = 0;
  int64_t best_j = 0;
  soft_match_for_each_key(key + b * M * C, values + b * M * D, M, C, D, tile, active,
                          [&](int64_t j, const scalar_t* k, const scalar_t* v) {
                            const double s = soft_match_score(q, k, C, scale);
                            if (s > best) {  // a new maximum: rescale what was accumulated
                              const double rescale = exp(best - s);
                              total = total * rescale + 1.0;
                              for (int64_t d = 0; d < D; ++d)
                                o[d] = static_cast<scalar_t>(double(o[d]) * rescale + double(v[d]));
                              best = s;
                              best_j = j;
                            } else {
                              const double p = s == -INFINITY ? 0.0 : exp(s - best);  // an overflowed score weighs 0
                              total += p;
                              for (int64_t d = 0; d < D; ++d) o[d] = static_cast<scalar_t>(double(o[d]) + p * double(v[d]));
                            }
                          });
  if (!active) return;
  for (int64_t d = 0; d < D; ++d) o[d] = static_cast<scalar_t>(double(o[d]) / total);
  lse[row] = static_cast<scalar_t>(best + log(total));
  argmax[row] = best_j;
}

template <typename scalar_t>
__global__ void soft_match_grad_query_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                             const scalar_t* __restrict__ values, const scalar_t* __restrict__ grad_out,
                                             const scalar_t* __restrict__ lse, const scalar_t* __restrict__ shift,
                                             int64_t N, int64_t M, int64_t C, int64_t D, double scale, int tile,
                                             scalar_t* __restrict__ grad_query) {
  const int64_t b = blockIdx.y, i = static_cast<int64_t>(blockIdx.x) * kSoftMatchRows + threadIdx.x;
  const bool active = i < N;
  const int64_t row = b * N + i;
  const scalar_t* q = query + row * C;
  const scalar_t* g = grad_out + row * D;
  scalar_t* dq = grad_query + row * C;
  const double row_lse = active ? double(lse[row]) : 0.0, row_shift = active ? double(shift[row]) : 0.0;
  if (active)
    for (int64_t c = 0; c < C; ++c) dq[c] = 0;
  soft_match_for_each_key(key + b * M * C, values + b * M * D, M, C, D, tile, active,
                          [&](int64_t, const scalar_t* k, const scalar_t* v) {
                            double dp = 0;
                            for (int64_t d = 0; d < D; ++d) dp += double(g[d]) * double(v[d]);
                            const double ds = exp(soft_match_score(q, k, C, scale) - row_lse) * (dp + row_shift);
                            for (int64_t c = 0; c < C; ++c)
                              dq[c] = static_cast<scalar_t>(double(dq[c]) + scale * ds * double(k[c]));
                          });
}

template <typename scalar_t>
__global__ void soft_match_grad_key_kernel(const scalar_t* __restrict__ query, const scalar_t* __restrict__ key,
                                           const scalar_t* __restrict__ values, const scalar_t* __restrict__ grad_out,
                                           const scalar_t* __restrict__ lse, const scalar_t* __restrict__ shift,
                                           int64_t N, int64_t M, int64_t C, int64_t D, double scale, int tile,
                                           scalar_t* __restrict__ grad_key, scalar_t* __restrict__ grad_values) {
  VRNET_DYNAMIC_SHARED(unsigned char, shared_bytes);
  scalar_t* query_tile = reinterpret_cast<scalar_t*>(shared_bytes);
  scalar_t* grad_tile = query_tile + tile * C;
  scalar_t* lse_tile = grad_tile + tile * D;
  scalar_t* shift_tile = lse_tile + tile;
  const int64_t b = blockIdx.y, j = static_cast<int64_t>(blockIdx.x) * kSoftMatchRows + threadIdx.x;
  const bool active = j < M;
  const int64_t row = b * M + j;
  const scalar_t* k = key + row * C;
  const scalar_t* v = values + row * D;
  scalar_t* dk = grad_key + row * C;
  scalar_t* dv = grad_values + row * D;
  if (active) {
    for (int64_t c = 0; c < C; ++c) dk[c] = 0;
    for (int64_t d = 0; d < D; ++d) dv[d] = 0;
  }
  for (int64_t i0 = 0; i0 < N; i0 += tile) {
    const int count = static_cast<int>(N - i0 < tile ? N - i0 : tile);
    __syncthreads();
    soft_match_load(query + b * N * C, i0, count, C, query_tile);
    soft_match_load(grad_out + b * N * D, i0, count, D, grad_tile);
    soft_match_load(lse + b * N, i0, count, 1, lse_tile);
    soft_match_load(shift + b * N, i0, count, 1, shift_tile);
    __syncthreads();
    if (!active) continue;
    for (int i = 0; i < count; ++i) {
      const scalar_t* q = query_tile + i * C;
      const scalar_t* g = grad_tile + i * D;
      double dp = 0;
      for (int64_t d = 0; d < D; ++d) dp += double(g[d]) * double(v[d]);
      const double p = exp(soft_match_score(q, k, C, scale) - double(lse_tile[i]));
      const double ds = p * (dp + double(shift_tile[i]));
      for (int64_t c = 0; c < C; ++c) dk[c] = static_cast<scalar_t>(double(dk[c]) + scale * ds * double(q[c]));
      for (int64_t d = 0; d < D; ++d) dv[d] = static_cast<scalar_t>(double(dv[d]) + p * double(g[d]));
    }
  }
}

}  // namespace vrnet
