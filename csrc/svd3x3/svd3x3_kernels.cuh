// CUDA batched 3x3 SVD: one thread per matrix running the shared double-precision Jacobi routine
// (svd3x3/svd3x3_math.h), and its backward, likewise one thread per matrix.
#pragma once

#include "common/cuda_device.cuh"
#include "svd3x3/svd3x3_math.h"

namespace vrnet {

template <typename scalar_t>
__global__ void svd3x3_kernel(const scalar_t* __restrict__ A, int64_t B, scalar_t* __restrict__ U,
                              scalar_t* __restrict__ S, scalar_t* __restrict__ V) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b < B) svd3x3_one(A + 9 * b, U + 9 * b, S + 3 * b, V + 9 * b);
}

template <typename scalar_t>
__global__ void svd3x3_backward_kernel(const scalar_t* __restrict__ gU, const scalar_t* __restrict__ gS,
                                       const scalar_t* __restrict__ gV, const scalar_t* __restrict__ U,
                                       const scalar_t* __restrict__ S, const scalar_t* __restrict__ V, int64_t B,
                                       scalar_t* __restrict__ gA) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b < B) svd3x3_backward_one(gU + 9 * b, gS + 3 * b, gV + 9 * b, U + 9 * b, S + 3 * b, V + 9 * b, gA + 9 * b);
}

}  // namespace vrnet
