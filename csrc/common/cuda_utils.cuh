// Helpers shared by the CUDA kernels: launch geometry, the current stream, warp reductions, exact
// (never FMA-contracted) arithmetic for results that must match the CPU kernels bit for bit, and
// the inverse of a neighbour graph used by every deterministic scatter-free backward.
#pragma once

#include <ATen/ops/arange.h>
#include <ATen/ops/searchsorted.h>
#include <ATen/ops/sort.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <cstdint>

#include "common/common.h"

namespace vrnet {

constexpr int kThreads = 256;

inline unsigned int blocks_for(int64_t work, int threads = kThreads) {
  return static_cast<unsigned int>(std::max<int64_t>(1, (work + threads - 1) / threads));
}

inline cudaStream_t current_stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

// a + b and a * b rounded once each: nvcc would otherwise contract a * b + c into an FMA and the
// results would differ from the CPU kernels in the last bit.
__device__ inline float add_rn(float a, float b) { return __fadd_rn(a, b); }
__device__ inline double add_rn(double a, double b) { return __dadd_rn(a, b); }
__device__ inline float sub_rn(float a, float b) { return __fsub_rn(a, b); }
__device__ inline double sub_rn(double a, double b) { return __dsub_rn(a, b); }
__device__ inline float mul_rn(float a, float b) { return __fmul_rn(a, b); }
__device__ inline double mul_rn(double a, double b) { return __dmul_rn(a, b); }

// Sum over the 32 lanes of a warp; every lane gets the total (fixed order: deterministic).
__device__ inline double warp_sum(double v) {
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(0xffffffffu, v, offset);
  return v;
}

// Inverse of a neighbour graph idx (B, N, k) with values in [0, M): for target m of batch b, the
// flat positions p = n * k + j with idx[b, n, j] == m are order[b, row_ptr[b, m] : row_ptr[b, m + 1]],
// ascending. Lets a backward gather per target instead of scattering with atomics.
struct Incidence {
  at::Tensor order;    // (B, N * k) int64
  at::Tensor row_ptr;  // (B, M + 1) int64
};

inline Incidence build_incidence(const at::Tensor& idx, int64_t num_targets) {
  const int64_t B = idx.size(0);
  const at::Tensor flat = idx.reshape({B, -1});
  const auto [sorted, order] = flat.sort(/*stable=*/true, /*dim=*/1, /*descending=*/false);
  const at::Tensor targets = at::arange(num_targets + 1, idx.options()).expand({B, num_targets + 1}).contiguous();
  return {order.contiguous(), at::searchsorted(sorted, targets).contiguous()};
}

}  // namespace vrnet
