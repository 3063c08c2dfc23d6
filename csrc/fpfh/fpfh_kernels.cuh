// CUDA Fast Point Feature Histograms: one thread per point running the shared per-point routines
// (fpfh/fpfh_math.h), as the CPU kernel does; every SPFH first, then every FPFH.
#pragma once

#include "common/cuda_device.cuh"
#include "fpfh/fpfh_math.h"

namespace vrnet {

template <typename scalar_t>
__global__ void spfh_kernel(const scalar_t* __restrict__ points, const scalar_t* __restrict__ normals,
                            const int64_t* __restrict__ idx, const scalar_t* __restrict__ dist2, int64_t N, int64_t k,
                            scalar_t r2, scalar_t* __restrict__ spfh) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < N) spfh_one(points, normals, idx + i * k, dist2 + i * k, i, k, r2, spfh + i * fpfh_detail::kFeatures);
}

template <typename scalar_t>
__global__ void fpfh_kernel(const scalar_t* __restrict__ spfh, const int64_t* __restrict__ idx,
                            const scalar_t* __restrict__ dist2, int64_t N, int64_t k, scalar_t r2,
                            scalar_t* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < N) fpfh_one(spfh, idx + i * k, dist2 + i * k, i, k, r2, out + i * fpfh_detail::kFeatures);
}

}  // namespace vrnet
