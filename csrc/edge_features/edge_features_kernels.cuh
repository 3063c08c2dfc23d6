// CUDA edge tensor out[b, :, n, j] = [x_idx - x_n ; x_n] (one thread per output element) and its
// backward, which gathers through the inverse graph (one thread per input element, no atomics:
// deterministic).
#pragma once

#include "common/cuda_device.cuh"

namespace vrnet {

template <typename scalar_t>
__global__ void edge_features_kernel(const scalar_t* __restrict__ x, const int64_t* __restrict__ idx, int64_t B,
                                     int64_t C, int64_t N, int64_t k, scalar_t* __restrict__ out) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N * k) return;
  const int64_t nj = t % (N * k), bc = t / (N * k), b = bc / C, c = bc % C, n = nj / k;
  const scalar_t centre = x[bc * N + n];
  out[(b * 2 * C + c) * N * k + nj] = x[bc * N + idx[b * N * k + nj]] - centre;
  out[(b * 2 * C + C + c) * N * k + nj] = centre;
}

// grad_x[b, c, m] = sum over edges (n, j) into m of g_diff[c, n, j] + sum_j (g_centre[c, m, j] - g_diff[c, m, j]).
template <typename scalar_t>
__global__ void edge_features_backward_kernel(const scalar_t* __restrict__ grad, const int64_t* __restrict__ order,
                                              const int64_t* __restrict__ row_ptr, int64_t B, int64_t C, int64_t N,
                                              int64_t k, scalar_t* __restrict__ grad_x) {
  const int64_t t = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= B * C * N) return;
  const int64_t m = t % N, bc = t / N, b = bc / C, c = bc % C;
  const scalar_t* g_diff = grad + (b * 2 * C + c) * N * k;
  const scalar_t* g_centre = grad + (b * 2 * C + C + c) * N * k;
  const int64_t* edges = order + b * N * k;
  scalar_t acc = 0;
  for (int64_t e = row_ptr[b * (N + 1) + m]; e < row_ptr[b * (N + 1) + m + 1]; ++e) acc += g_diff[edges[e]];
  for (int64_t j = 0; j < k; ++j) acc += g_centre[m * k + j] - g_diff[m * k + j];
  grad_x[t] = acc;
}

}  // namespace vrnet
