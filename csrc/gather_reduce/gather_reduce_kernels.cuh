// CUDA fused neighbour gather + reduction, one thread per output (b, c, n); max/min keep the first
// winning neighbour slot (or the first NaN) exactly as the CPU kernel. The backward gathers through
// the inverse graph, one thread per value (b, c, m), so it has no atomics and is deterministic.
#pragma once

#include "common/cuda_device.cuh"
#include "gather_reduce/reduce.h"

namespace vrnet {

template <typename scalar_t, Reduce R>
__global__ void gather_reduce_kernel(const scalar_t* __restrict__ values, const int64_t* __restrict__ idx, int64_t B,
                                     int64_t C, int64_t M, int64_t N, int64_t k, scalar_t* __restrict__ out,
                                     int64_t* __restrict__ arg) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N) return;
  const int64_t n = t % N, bc = t / N, b = bc / C;
  const scalar_t* row = values + bc * M;
  const int64_t* nb = idx + (b * N + n) * k;
  if constexpr (R == Reduce::kMax || R == Reduce::kMin) {
    scalar_t best_v = row[nb[0]];
    int64_t best = 0;
    bool has_nan = best_v != best_v;
    for (int64_t j = 1; j < k && !has_nan; ++j) {
      const scalar_t v = row[nb[j]];
      if (v != v) {
        has_nan = true;
        best_v = v;
        best = j;
      } else if (R == Reduce::kMax ? v > best_v : v < best_v) {
        best_v = v;
        best = j;
      }
    }
    out[t] = best_v;
    arg[t] = best;
  } else {
    scalar_t acc = 0;
    for (int64_t j = 0; j < k; ++j) acc += row[nb[j]];
    out[t] = R == Reduce::kMean ? acc / static_cast<scalar_t>(k) : acc;
  }
}

// grad_values[b, c, m] = sum over edges (n, j) into m of grad[b, c, n] (times 1/k for mean; only the
// winning slot j = arg[b, c, n] for max/min, when arg is given).
template <typename scalar_t>
__global__ void gather_reduce_backward_kernel(const scalar_t* __restrict__ grad, const int64_t* __restrict__ arg,
                                              const int64_t* __restrict__ order, const int64_t* __restrict__ row_ptr,
                                              int64_t B, int64_t C, int64_t M, int64_t N, int64_t k, scalar_t scale,
                                              scalar_t* __restrict__ grad_values) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * M) return;
  const int64_t m = t % M, bc = t / M, b = bc / C;
  const int64_t* edges = order + b * N * k;
  const scalar_t* g = grad + bc * N;
  const int64_t* a = arg ? arg + bc * N : nullptr;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (M + 1) + m]; e < row_ptr[b * (M + 1) + m + 1]; ++e) {
    const int64_t pos = edges[e], n = pos / k;
    if (a == nullptr) acc += g[n] * scale;
    else if (a[n] == pos % k) acc += g[n];
  }
  grad_values[t] = acc;
}

}  // namespace vrnet
